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
cloud is a concrete array (which also sum each neighbourhood's covariance, in float64), from
blocked brute force :func:`jaxreg.search.neighbors.knn` when it is traced (under ``jit``, ``vmap``
or ``grad``), or passed in. The 3x3 eigenproblems are solved in closed form, elementwise
over the points (:func:`jaxreg.geometry.eigen.eigh3`), in one compiled function. Timings:
``benchmarks/bench_neighbors.py``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.core._brute import valid_rows
from jaxreg.core._result import select_status
from jaxreg.geometry.eigen import eigh3
from jaxreg.search._host_normals import host_normals
from jaxreg.search._knn import knn_moments, self_knn
from jaxreg.search.neighbors import knn

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


@jax.custom_jvp
def _smallest_eigenpair(c: Float[Array, "... 6"]) -> tuple[Array, Array]:
    """Eigenvalues ``(..., 3)`` and the unit eigenvector ``(..., 3)`` of the smallest, from
    :func:`~jaxreg.geometry.eigen.eigh3`, with a derivative that is finite where the larger two
    repeat (a round patch of a plane) and zero along a repeated smallest one (collinear
    neighbours)."""
    evals, vecs = eigh3(c)
    return evals, vecs[..., 0]


@_smallest_eigenpair.defjvp
def _smallest_eigenpair_jvp(primals, tangents):
    # d lambda_i = v_i^T dA v_i; d v_0 = sum_{j > 0} v_j (v_j^T dA v_0) / (lambda_0 - lambda_j).
    (c,), (dc,) = primals, tangents
    evals, vecs = eigh3(c)
    d00, d01, d02, d11, d12, d22 = (dc[..., i] for i in range(6))
    da = jnp.stack(
        [jnp.stack(r, -1) for r in ((d00, d01, d02), (d01, d11, d12), (d02, d12, d22))], -2
    )
    proj = jnp.einsum("...ji,...jk,...kl->...il", vecs, da, vecs)  # V^T dA V
    d_evals = jnp.diagonal(proj, axis1=-2, axis2=-1)
    gap = evals[..., :1] - evals
    tol = 100 * jnp.finfo(c.dtype).eps * jnp.abs(evals).max(-1, keepdims=True)
    live = (jnp.abs(gap) > tol) & (jnp.arange(3) > 0)
    coeff = jnp.where(live, proj[..., :, 0] / jnp.where(live, gap, 1), 0)
    d_normal = jnp.einsum("...ij,...j->...i", vecs, coeff)
    return (evals, vecs[..., 0]), (d_evals, d_normal)


def _from_moments(points, ok, cov, count, viewpoint) -> NormalEstimate:
    """Normals, curvature and status from each point's neighbourhood covariance ``(N, 6)``
    (entries ``xx, xy, xz, yy, yz, zz``) and valid neighbour count ``(N,)``."""
    dtype = points.dtype
    safe = jnp.where(ok[:, None], points, 0)
    evals, normal = _smallest_eigenpair(cov.astype(dtype))
    evals = jnp.maximum(evals, 0)
    enough = count >= 3
    # Collinear or coincident neighbours: the middle eigenvalue vanishes next to the largest.
    flat = evals[:, 1] <= 100 * jnp.finfo(dtype).eps * evals[:, 2]
    valid = ok & enough & ~flat
    facing = jnp.sum(normal * (viewpoint - safe), -1) >= 0
    normal = jnp.where((valid & facing)[:, None], normal, jnp.where(valid[:, None], -normal, 0))
    total = jnp.where(valid, evals.sum(-1), 1)
    curvature = jnp.where(valid, evals[:, 0] / total, 0)
    status = select_status(
        [
            (~ok, NormalStatus.invalid_point),
            (~enough, NormalStatus.too_few_neighbors),
            (flat, NormalStatus.degenerate),
        ],
        NormalStatus.success,
    )
    return NormalEstimate(normal, curvature, valid, status, count.astype(jnp.int32))


@jax.jit
def _pca(points, ok, idx, nbr_ok, viewpoint) -> NormalEstimate:
    """Per-point PCA from neighbour indices ``(N, K)`` (one compiled function per shape)."""
    dtype = points.dtype
    # Invalid points have no neighbourhood; invalid neighbours do not count.
    nbr_ok = nbr_ok & ok[:, None] & ok.at[idx].get(mode="fill", fill_value=False)
    safe = jnp.where(ok[:, None], points, 0)
    count = nbr_ok.sum(-1)
    inv_count = 1 / jnp.maximum(count, 1).astype(dtype)

    # Centre at the point first (no cancellation far from the origin), then at the mean.
    # Sums run over the neighbour slots in a fixed order (unrolled), so a cloud gets the
    # same bits alone and inside a vmapped batch: the normal of an elongated neighbourhood
    # amplifies rounding in the moments by l2 / l1.
    def slot_sum(x):
        total = x[..., 0]
        for j in range(1, x.shape[-1]):
            total = total + x[..., j]
        return total

    dev = []
    for i in range(3):
        rel = jnp.where(nbr_ok, safe[:, i].at[idx].get(mode="fill", fill_value=0), 0)
        rel = jnp.where(nbr_ok, rel - safe[:, i, None], 0)
        mean = slot_sum(rel) * inv_count
        dev.append(jnp.where(nbr_ok, rel - mean[:, None], 0))
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    cov = jnp.stack([slot_sum(dev[i] * dev[j]) * inv_count for i, j in pairs], -1)
    return _from_moments(points, ok, cov, count, viewpoint)


def _is_concrete(*arrays) -> bool:
    return not any(isinstance(a, jax.core.Tracer) for a in arrays)


def _host_knn(
    points: np.ndarray, ok: np.ndarray, k: int, max_distance: float = np.inf
) -> tuple[np.ndarray, np.ndarray]:
    """Exact ``k`` nearest valid points (closer than ``max_distance``) of every valid point of
    a concrete cloud, by compiled host loops (:func:`jaxreg.search._knn.self_knn`). Returns
    ``(indices (N, k), valid (N, k))`` with the sentinel ``N``."""
    n = len(points)
    rows = np.flatnonzero(ok)
    idx, sq = self_knn(points[rows].astype(np.float64), k, max_distance)
    valid = np.isfinite(sq)
    out = np.full((n, k), n, np.int64)
    out[rows] = np.where(valid, rows[np.minimum(idx, len(rows) - 1)], n)
    out_valid = np.zeros((n, k), bool)
    out_valid[rows] = valid
    return out, out_valid


def _host_pca(points: np.ndarray, mask, k: int, viewpoint) -> NormalEstimate:
    """:func:`estimate_normals_with_curvature` of a concrete float cloud: the exact kNN and
    each neighbourhood's covariance (float64) by compiled host loops, and the eigenproblems,
    orientation and status by more of them (:func:`jaxreg.search._host_normals.host_normals`,
    :func:`_from_moments`'s rules): no JAX program runs, the answer is moved to the device."""
    ok = np.all(np.isfinite(points), axis=-1)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != ok.shape:
            raise ValueError(f"mask must be ({ok.shape[0]},), got {mask.shape}")
        ok &= mask.astype(bool)
    dtype = points.dtype
    if ok.all():  # no copies of a clean cloud
        cov, count = knn_moments(np.ascontiguousarray(points, np.float64), k)
    else:
        rows = np.flatnonzero(ok)
        cov = np.zeros((len(points), 6))
        count = np.zeros(len(points), np.int32)
        cov[rows], count[rows] = knn_moments(np.ascontiguousarray(points[rows], np.float64), k)
    vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, np.float64)
    if vp.shape != (3,):
        raise ValueError(f"viewpoint must be (3,), got {vp.shape}")
    members = (
        NormalStatus.invalid_point,
        NormalStatus.too_few_neighbors,
        NormalStatus.degenerate,
        NormalStatus.success,
    )
    codes = np.array([int(m._value) for m in members], np.int64)
    flat_tol = 100 * float(np.finfo(dtype).eps)
    out = host_normals(points, ok, cov, count, vp.astype(dtype), flat_tol, codes)
    code = out[:, 4].astype(np.int32)
    success = int(NormalStatus.success._value)
    host = (out[:, :3].astype(dtype), out[:, 3].astype(dtype), code == success, code, count)
    normals, curvature, valid, code, count = jax.device_put(host)  # one transfer call
    status = NormalStatus.success.__class__(
        _value=code, _enumeration=NormalStatus.success._enumeration
    )
    return NormalEstimate(normals, curvature, valid, status, count)


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
            (sentinel ``N`` where invalid), e.g. from :func:`~jaxreg.search.neighbors.knn`
            on a grid of ``points``; ``k`` is then ignored. Default: the exact ``k``
            nearest, found on the host when ``points`` (and ``mask``) are concrete arrays,
            by blocked brute force (:func:`~jaxreg.search.neighbors.knn` on the points) when
            traced (under ``jit``, ``vmap`` or ``grad``).

    Returns:
        A :class:`NormalEstimate`.
    """
    if neighbors is None and k >= 1 and _is_concrete(points, mask):
        host = np.asarray(points)
        if host.ndim != 2 or host.shape[-1] != 3:
            raise ValueError(f"points must be (N, 3) (vmap for batches), got {host.shape}")
        dtype = host.dtype if np.issubdtype(host.dtype, np.floating) else jnp.result_type(float)
        return _host_pca(host.astype(jax.dtypes.canonicalize_dtype(dtype)), mask, k, viewpoint)
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
