"""Surface normals and curvature by PCA over each point's nearest neighbours.

For each point, the covariance of its ``k`` nearest neighbours (the point itself included,
as Open3D does) has eigenvalues ``l0 <= l1 <= l2``. The normal is the eigenvector of ``l0``
(the direction the neighbourhood varies least along), flipped to face the viewpoint:
``n . (viewpoint - p) >= 0``, so it points toward the sensor that saw the surface. The
*surface variation* ``l0 / (l0 + l1 + l2)`` in ``[0, 1/3]`` is reported as curvature (0 on
a plane; PCL and Open3D use the same quantity).

Every point gets a status; points that are masked or not finite, that have fewer than 3
valid neighbours, or whose neighbours are collinear or coincident (``l1`` negligible next to
``l2``: the normal is undefined) get a zero normal and zero curvature, never NaN.

Neighbours are the exact ``k`` nearest: from compiled host loops over a hash grid when the
cloud is a concrete array, from blocked brute force :func:`jaxreg.neighbors.knn` when it is
traced (under ``jit``, ``vmap`` or ``grad``), or passed in. The PCA is one compiled
function. Timings: ``benchmarks/bench_neighbors.py``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._octree import self_knn
from .neighbors import knn, valid_rows

__all__ = ["NormalEstimate", "NormalStatus", "estimate_normals", "estimate_normals_with_curvature"]


class NormalStatus(eqx.Enumeration):
    """Per-point outcome of normal estimation."""

    success = "normal estimated"
    invalid_point = "the point is masked out or not finite"
    too_few_neighbors = "fewer than 3 valid neighbours: increase k or check the mask"
    degenerate = "the neighbours are collinear or coincident: the normal is undefined"


class NormalEstimate(eqx.Module):
    """Result of :func:`estimate_normals_with_curvature` for ``N`` points.

    Attributes:
        normals: ``(N, 3)`` unit normals facing the viewpoint; zero where not ``valid``.
        curvature: ``(N,)`` surface variation ``l0 / (l0 + l1 + l2)`` in ``[0, 1/3]``;
            zero where not ``valid``.
        valid: ``(N,)`` the normal is defined (``status == success``).
        status: ``(N,)`` :class:`NormalStatus` of each point.
        num_neighbors: ``(N,)`` valid neighbours used (the point itself included; 0 for
            invalid points).
    """

    normals: Float[Array, "N 3"]
    curvature: Float[Array, " N"]
    valid: Bool[Array, " N"]
    status: NormalStatus
    num_neighbors: Int[Array, " N"]


def _one(point, point_ok, nbrs, nbr_ok, viewpoint):
    """Normal, curvature and status of one point from its ``(k, 3)`` neighbours."""
    dtype = nbrs.dtype
    w = nbr_ok.astype(dtype)
    count = nbr_ok.sum()
    # Centre at the point first (no cancellation far from the origin), then at the mean.
    rel = jnp.where(nbr_ok[:, None], nbrs - point, 0)
    mean = (w[:, None] * rel).sum(0) / jnp.maximum(w.sum(), 1)
    dev = jnp.where(nbr_ok[:, None], rel - mean, 0)
    cov = dev.T @ dev / jnp.maximum(w.sum(), 1)
    evals, evecs = jnp.linalg.eigh(cov)
    evals = jnp.maximum(evals, 0)
    total = evals.sum()
    enough = count >= 3
    # Collinear or coincident neighbours: the middle eigenvalue vanishes next to the largest.
    tol = 100 * jnp.finfo(dtype).eps
    flat = evals[1] <= tol * evals[2]
    ok = point_ok & enough & ~flat
    normal = evecs[:, 0]
    normal = jnp.where(jnp.dot(normal, viewpoint - point) < 0, -normal, normal)
    normal = jnp.where(ok, normal, 0)
    safe_total = jnp.where(ok, total, 1)
    curvature = jnp.where(ok, evals[0] / safe_total, 0)
    status = NormalStatus.where(
        point_ok,
        NormalStatus.where(
            enough,
            NormalStatus.where(flat, NormalStatus.degenerate, NormalStatus.success),
            NormalStatus.too_few_neighbors,
        ),
        NormalStatus.invalid_point,
    )
    return normal, curvature, ok, status, count


@jax.jit
def _pca(points, ok, idx, nbr_ok, viewpoint) -> NormalEstimate:
    """Per-point PCA from neighbour indices (one compiled function per shape)."""
    # Invalid points have no neighbourhood; invalid neighbours do not count.
    nbr_ok = nbr_ok & ok[:, None] & ok.at[idx].get(mode="fill", fill_value=False)
    nbrs = points.at[idx].get(mode="fill", fill_value=0)
    safe = jnp.where(ok[:, None], points, 0)
    normal, curvature, valid, status, count = jax.vmap(_one, in_axes=(0, 0, 0, 0, None))(
        safe, ok, nbrs, nbr_ok, viewpoint
    )
    return NormalEstimate(normal, curvature, valid, status, count.astype(jnp.int32))


def _is_concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


def _host_knn(points: np.ndarray, ok: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact ``k`` nearest valid points of every valid point of a concrete cloud, by compiled
    host loops (:func:`jaxreg._octree.self_knn`). Returns ``(indices (N, k), valid (N, k))``
    with the sentinel ``N``."""
    n = len(points)
    rows = np.flatnonzero(ok)
    idx, sq = self_knn(points[rows].astype(np.float64), k)
    valid = np.isfinite(sq)
    out = np.full((n, k), n, np.int64)
    out[rows] = np.where(valid, rows[np.minimum(idx, len(rows) - 1)], n)
    out_valid = np.zeros((n, k), bool)
    out_valid[rows] = valid
    return out, out_valid


def estimate_normals_with_curvature(
    points: ArrayLike,
    k: int = 20,
    viewpoint: ArrayLike | None = None,
    *,
    mask: ArrayLike | None = None,
    neighbors: tuple[ArrayLike, ArrayLike] | None = None,
) -> NormalEstimate:
    """Normals, curvature and per-point status by PCA over ``k`` nearest neighbours (jittable).

    Args:
        points: ``(N, 3)`` cloud, in the frame of ``viewpoint`` (e.g. the camera frame).
        k: static neighbourhood size, the point itself included (Open3D's KNN search).
        viewpoint: ``(3,)`` sensor position the normals should face; default the origin
            (the sensor of a camera-frame cloud).
        mask: ``(N,)`` optional validity; masked and non-finite points are neither given
            a normal nor used as anyone's neighbour.
        neighbors: optional precomputed ``(indices (N, K), valid (N, K))`` into ``points``
            (sentinel ``N`` where invalid), e.g. from ``query_knn`` on a grid of ``points``;
            ``k`` is then ignored. Default: the exact ``k`` nearest, found on the host
            when ``points`` (and ``mask``) are concrete arrays, from
            blocked brute force :func:`~jaxreg.neighbors.knn` when traced (under ``jit``,
            ``vmap`` or ``grad``).

    Returns:
        A :class:`NormalEstimate`.
    """
    concrete = _is_concrete(points, mask)
    points = jnp.asarray(points)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must be (N, 3) (vmap for batches), got {points.shape}")
    if not jnp.issubdtype(points.dtype, jnp.floating):
        points = points.astype(jnp.result_type(float))
    n = points.shape[0]
    ok = valid_rows(points, mask)
    if neighbors is None:
        if k < 1:
            raise ValueError(f"k must be positive, got {k}")
        if concrete:
            idx, nbr_ok = _host_knn(np.asarray(points), np.asarray(ok), k)
        else:
            idx, _, nbr_ok = knn(points, points, k, mask=ok)
    else:
        idx, nbr_ok = (jnp.asarray(a) for a in neighbors)
        if idx.ndim != 2 or idx.shape[0] != n or nbr_ok.shape != idx.shape:
            raise ValueError(
                f"neighbors must be (indices, valid) of shape ({n}, K), got "
                f"{idx.shape} and {nbr_ok.shape}"
            )
    vp = jnp.zeros(3, points.dtype) if viewpoint is None else jnp.asarray(viewpoint, points.dtype)
    return _pca(points, ok, jnp.asarray(idx), jnp.asarray(nbr_ok), vp)


def estimate_normals(
    points: ArrayLike,
    k: int = 20,
    viewpoint: ArrayLike | None = None,
    *,
    mask: ArrayLike | None = None,
    neighbors: tuple[ArrayLike, ArrayLike] | None = None,
) -> Float[Array, "N 3"]:
    """``(N, 3)`` unit normals facing ``viewpoint`` (zero where undefined); see
    :func:`estimate_normals_with_curvature` for the arguments, curvature and status."""
    return estimate_normals_with_curvature(
        points, k, viewpoint, mask=mask, neighbors=neighbors
    ).normals
