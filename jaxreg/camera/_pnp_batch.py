"""Batches of PnP problems for :mod:`jaxreg.camera.pnp`: the host-side checks of the public
solvers' arguments, and one compiled program over a flat batch of problems (starts,
refinement of every start together, choice, covariances).

Leading batch axes of every argument broadcast; a problem's trailing (core) dimensions are
``_CORE_NDIMS``. Inside a program the batch is flat, ``(B,)``.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxreg.camera._pnp_covariance import covariances as pose_covariances
from jaxreg.camera._pnp_refine import refine_poses
from jaxreg.camera.model import _canonical_dist
from jaxreg.core._leaves import as_array
from jaxreg.core._sizes import bucket, pad_rows, power_of_two

__all__ = ["checked_inputs", "solve_batch", "solve_padded"]

# Trailing (core) dimensions of object_points, image_points, K, dist_coeffs, weights.
_CORE_NDIMS = (2, 2, 2, 1, 1)


def checked_inputs(name, object_points, image_points, K, dist_coeffs, weights, sigma_px):
    """Host-side shape checks; returns float arrays of one dtype (numpy for host input, so that
    checking compiles no device program; JAX arrays and tracers stay JAX arrays), sigma_px in
    that dtype and the broadcast batch shape."""
    object_points, image_points, K = (as_array(a) for a in (object_points, image_points, K))
    if object_points.ndim < 2 or object_points.shape[-1] != 3:
        raise ValueError(f"{name}: object_points must be (..., N, 3), got {object_points.shape}")
    if image_points.ndim < 2 or image_points.shape[-1] != 2:
        raise ValueError(f"{name}: image_points must be (..., N, 2), got {image_points.shape}")
    n = object_points.shape[-2]
    if image_points.shape[-2] != n:
        raise ValueError(f"{name}: {n} object points but {image_points.shape[-2]} image points")
    if n < 4:
        raise ValueError(f"{name} needs at least 4 correspondences, got {n}")
    if K.ndim < 2 or K.shape[-2:] != (3, 3):
        raise ValueError(f"{name}: K must be (3, 3) or (..., 3, 3), got {K.shape}")
    dist_coeffs = None if dist_coeffs is None else _canonical_dist(as_array(dist_coeffs))
    weights = np.ones(object_points.shape[:-1]) if weights is None else as_array(weights)
    if weights.ndim < 1 or weights.shape[-1] != n:
        raise ValueError(f"{name}: weights must be (..., {n}), got {weights.shape}")
    arrays = [object_points, image_points, K, dist_coeffs, weights]
    dtype = np.result_type(*(a.dtype for a in arrays if a is not None), np.float32)
    dtype = jax.dtypes.canonicalize_dtype(dtype if np.issubdtype(dtype, np.floating) else float)
    arrays = [None if a is None else a.astype(dtype) for a in arrays]
    try:
        batch = np.broadcast_shapes(
            *(
                a.shape[: a.ndim - k]
                for a, k in zip(arrays, _CORE_NDIMS, strict=True)
                if a is not None
            )
        )
    except ValueError as err:
        shapes = [None if a is None else a.shape for a in arrays]
        raise ValueError(f"{name}: batch axes do not broadcast: {shapes}") from err
    sigma_px = as_array(sigma_px).astype(dtype)
    if sigma_px.ndim != 0:
        raise ValueError(f"{name}: sigma_px must be a scalar, got shape {sigma_px.shape}")
    return arrays, sigma_px, tuple(batch)


def solve_batch(starts_fn, choose_fn, finish_fn, arrays, batch, sigma_px, *, refine, iterations):
    """Solve every problem of the broadcast leading `batch` axes (one problem when
    `batch == ()`): `starts_fn(X, uv, K, dist, w) -> _Starts` per problem, the refinement of all
    starts of all problems together (`refine_poses`), `choose_fn` per problem, the covariances
    of the whole batch at once (`pose_covariances`), then `finish_fn` per problem."""
    size = int(np.prod(batch))
    flat, axes = [], []
    for a, k in zip(arrays, _CORE_NDIMS, strict=True):
        if a is None or a.ndim == k:
            flat.append(a)
            axes.append(None)
        else:
            core_shape = a.shape[a.ndim - k :]
            flat.append(jnp.broadcast_to(a, batch + core_shape).reshape(size, *core_shape))
            axes.append(0)
    if not batch:  # one problem: a batch of one, so that every stage is written for a batch
        for i in (0, 1, 4):  # object points, image points, weights (never None)
            flat[i], axes[i] = flat[i][None], 0
    K, dist = flat[2], flat[3]
    st = jax.vmap(starts_fn, in_axes=axes)(*flat)
    if refine:
        poses, its, conv = refine_poses(
            st.starts,
            st.go,
            st.X,
            st.uv,
            K,
            dist,
            st.w,
            max_iterations=iterations,
            axes=axes[2:4],
        )
    else:
        poses = st.starts
        its = jnp.zeros(st.go.shape, jnp.int32)
        conv = jnp.ones(st.go.shape, bool)
    refined = jax.vmap(choose_fn, in_axes=(0, 0, 0, 0, axes[2], axes[3]))(
        st, poses, its, conv, K, dist
    )
    cov = pose_covariances(refined.pose, refined.X, K, dist, refined.w, sigma_px, axes[2:4])
    out = jax.vmap(finish_fn, in_axes=(0, axes[2], axes[3], None, 0))(
        refined, K, dist, sigma_px, cov
    )
    return jax.tree.map(lambda leaf: leaf.reshape(*batch, *leaf.shape[1:]), out)


def _padded_count(count: int) -> int:
    """Problems a batch of ``count`` runs as: a power of two up to 64 (a tag tracker that
    sees 1-30 tags frame by frame meets six sizes), then :func:`jaxreg.core._sizes.bucket`'s
    steps of an eighth."""
    return power_of_two(count) if count <= 64 else bucket(count)


def solve_padded(program, arrays, sigma_px, batch, **static):
    """``program(arrays, sigma_px, batch=..., **static)`` (a jitted :func:`solve_batch`) on
    every problem of ``batch``, so that the batch's size is not the program's shape.

    With concrete arguments and batch axes, the batched arguments are flattened on the host
    and padded with copies of the last problem to :func:`_padded_count` problems: a process
    whose batch sizes change call by call compiles the solver a few times, not once per
    count (each compile takes seconds), and pays a small trimming program per count instead.
    A problem's answer never depends on the others; it depends on the compiled batch size by
    float rounding alone (XLA vectorises each size on its own). Traced arguments (the
    caller's ``jit`` or ``grad``), a single problem (``batch == ()``) and an empty batch run as
    given."""
    size = int(np.prod(batch))
    if not batch or size == 0 or any(isinstance(a, jax.core.Tracer) for a in (*arrays, sigma_px)):
        return program(arrays, sigma_px, batch=batch, **static)
    padded = _padded_count(size)
    flat = list(arrays)
    for i, (a, k) in enumerate(zip(arrays, _CORE_NDIMS, strict=True)):
        if a is not None and a.ndim > k:
            core = a.shape[a.ndim - k :]
            rows = np.broadcast_to(np.asarray(a), batch + core).reshape(size, *core)
            flat[i] = pad_rows(rows, padded)
    result = program(flat, sigma_px, batch=(padded,), **static)
    return result if (padded,) == batch else _trim(result, batch)


@functools.partial(jax.jit, static_argnames=("batch",))
def _trim(result, batch):
    """The first ``prod(batch)`` problems of a padded flat result, shaped ``batch + ...``."""
    size = int(np.prod(batch))
    return jax.tree.map(lambda leaf: leaf[:size].reshape(*batch, *leaf.shape[1:]), result)
