"""Closed-form alignment of matched point sets: weighted Kabsch and Umeyama, batched.

Problem (``R`` a proper rotation, ``c`` a scale fixed to 1 for Kabsch)::

    min_{R, t, c}  sum_i w_i || c R src_i + t - dst_i ||^2

The translation is eliminated by the weighted centroids, ``t = mu_dst - c R mu_src``, and
the rotation maximises ``sum_i w_i b_i . (R a_i) = tr(R H)`` for the centred sets
``a = src - mu_src``, ``b = dst - mu_dst`` and ``H = sum_i w_i a_i b_i^T``.

Formulation. The rotation is found as Horn's unit quaternion: the top eigenvector of a 4x4
symmetric matrix ``N(H)`` built from the cross-covariance ``H``. This
is the same optimum as the SVD form (Kabsch/Umeyama), but

* a quaternion is always a proper rotation: no reflection guard is needed, and the result
  can never have det -1;
* its derivative involves only the gap between the top eigenvalue and the others. For
  ``H = U diag(s) V^T`` that gap is ``2 (s2 + s3)`` (``2 (s2 - s3)`` when ``det H < 0``),
  which is zero exactly when the optimal rotation is not unique. The SVD gradient instead
  divides by ``s_i^2 - s_j^2`` and is infinite on planar or symmetric clouds whose singular
  values repeat although the rotation is perfectly determined. A custom JVP rule
  (:func:`jaxreg.geometry.lie.top_eigenpair`) differentiates the top eigenvector alone, so the
  gradient is finite (and exact) whenever the solution is unique, and is set to zero with
  ``degenerate`` raised when it is not.

Batching: every array may carry leading batch axes ``(...)``; points are ``(..., N, 3)``
and weights ``(..., N)``. Rows with zero weight are padding: they take no part, whatever
their coordinates (NaN included). Rows with a non-finite coordinate are treated as
zero-weight (depth holes are masked, never propagated).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxlie import SE3, SO3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.core._result import AbstractResult, select_status
from jaxreg.geometry.lie import procrustes_quaternion_matrix, top_eigenpair

__all__ = ["Alignment", "AlignmentStatus", "align", "kabsch", "umeyama"]


class AlignmentStatus(eqx.Enumeration):
    """Outcome of :func:`align`; each member's value is the message a user needs."""

    success = "success: the rotation and translation are unique"
    too_few_correspondences = (
        "fewer than 3 correspondences with positive weight and finite coordinates: a rigid "
        "transform needs 3 non-collinear pairs (check the weights and NaN rows)"
    )
    degenerate = (
        "degenerate geometry: the source or target points are collinear or coincident, so the "
        "rotation about their line is unobservable"
    )
    ambiguous_rotation = (
        "the optimal rotation is not unique (Horn's top eigenvalue is repeated): a symmetric "
        "or reflected configuration; add points that break the symmetry"
    )


class Alignment(AbstractResult):
    """Result of :func:`align`; every field carries the problem's batch axes ``(...)``.

    Attributes:
        pose: ``SE3`` mapping source into target coordinates (``target ~ scale * R source + t``;
            with a scale, ``pose`` holds ``R`` and ``t``).
        status: :class:`AlignmentStatus` of each problem.
        converged: ``(...)`` ``status == success`` (a closed form has nothing else to converge).
        iterations: ``(...)`` always 0 (closed form); present so every result reads alike.
        scale: ``(...)`` similarity scale (exactly 1 for Kabsch).
        weight_sum: ``(...)`` total weight of the finite rows used.
        count: ``(...)`` number of rows with positive weight.
        rms: ``(...)`` weighted RMS residual of the aligned sets.
        eigengap: ``(...)`` relative gap between the top two eigenvalues of Horn's matrix, in
            ``[0, 2]``; 0 means the optimal rotation is not unique.
        collinear: ``(...)`` source or target points lie on a line (rotation about it
            is unobservable).
        planar: ``(...)`` source points lie on a plane. Informational: three non-collinear
            points fix a rotation, but planar scenes are where the SVD gradient fails.
        degenerate: ``(...)`` fewer than 3 weighted rows, collinear geometry, or a
            non-unique rotation (any status but ``success``). The pose is then not
            trustworthy (identity when there is no weight at all) and its gradient is cut to
            zero along the unobservable directions.
    """

    pose: SE3
    status: AlignmentStatus
    converged: Bool[Array, "..."]
    iterations: Int[Array, "..."]
    scale: Float[Array, "..."]
    weight_sum: Float[Array, "..."]
    count: Float[Array, "..."]
    rms: Float[Array, "..."]
    eigengap: Float[Array, "..."]
    collinear: Bool[Array, "..."]
    planar: Bool[Array, "..."]
    degenerate: Bool[Array, "..."]


def _eps(dtype) -> float:
    return float(jnp.finfo(dtype).eps)


def _shape_invariants(c: Float[Array, "... 3 3"]) -> tuple[Array, Array, Array]:
    """Trace, second invariant and determinant of a symmetric PSD 3x3 matrix."""
    tr = jnp.trace(c, axis1=-2, axis2=-1)
    i2 = 0.5 * (tr**2 - jnp.sum(c * c, axis=(-2, -1)))
    det = (
        c[..., 0, 0] * (c[..., 1, 1] * c[..., 2, 2] - c[..., 1, 2] * c[..., 2, 1])
        - c[..., 0, 1] * (c[..., 1, 0] * c[..., 2, 2] - c[..., 1, 2] * c[..., 2, 0])
        + c[..., 0, 2] * (c[..., 1, 0] * c[..., 2, 1] - c[..., 1, 1] * c[..., 2, 0])
    )  # closed form: one batched LAPACK call (the eigh) per alignment, never two at once
    return tr, i2, det


def _check_shapes(src, dst, weights):
    src = jnp.asarray(src)
    dst = jnp.asarray(dst)
    if src.ndim < 2 or src.shape[-1] != 3:
        raise ValueError(f"source must have shape (..., N, 3), got {src.shape}")
    if dst.shape[-2:] != src.shape[-2:]:
        raise ValueError(
            f"source and target must be matched row for row: got {src.shape} and {dst.shape}"
        )
    if src.shape[-2] < 3:
        raise ValueError(f"a rigid alignment needs at least 3 correspondences, got {src.shape[-2]}")
    dtype = jnp.result_type(src.dtype, dst.dtype, float)
    src, dst = src.astype(dtype), dst.astype(dtype)
    if weights is None:
        weights = jnp.ones(src.shape[:-1], dtype)
    weights = jnp.asarray(weights, dtype)
    if weights.shape[-1:] != src.shape[-2:-1]:
        raise ValueError(
            f"weights must have shape (..., N) with N = {src.shape[-2]}, got {weights.shape}"
        )
    return src, dst, weights


class _Fit(eqx.Module):
    """Horn's solution of matched rows (see :func:`_fit`); batch axes ``(...)`` throughout,
    and the fields of :class:`Alignment` of the same name mean the same."""

    weight_sum: Float[Array, "..."]
    count: Float[Array, "..."]
    mu_src: Float[Array, "... 3"]  # weighted centroids (0 without weight)
    mu_dst: Float[Array, "... 3"]
    var_src: Float[Array, "..."]  # weighted mean squared distance of src from mu_src
    rotation: SO3  # the identity without weight
    top: Float[Array, "..."]  # tr(R H) for the normalised cross-covariance H
    eigengap: Float[Array, "..."]
    collinear: Bool[Array, "..."]
    planar: Bool[Array, "..."]
    degenerate: Bool[Array, "..."]


def _row_sums(operands):
    """Sums over the last axis of equally shaped arrays, as one variadic reduction: the sums
    share one loop over memory, where as separate reductions XLA's CPU backend reads the rows
    once per sum (and its batched ``einsum`` of tiny matrices is slower still)."""
    zero = jnp.zeros((), operands[0].dtype)
    axis = operands[0].ndim - 1
    return jax.lax.reduce(
        operands,
        [zero] * len(operands),
        lambda a, b: [x + y for x, y in zip(a, b, strict=True)],
        (axis,),
    )


def _row_sums_reference(operands):
    """:func:`_row_sums` as separate sums: the same values, and differentiable."""
    return [jnp.sum(o, axis=-1) for o in operands]


def _centred(src, dst, w, row_sums):
    """Weighted centroids, then the centred second moments about them, normalised by the
    weight (two passes: nothing is lost to cancellation). Rows with ``w == 0`` take no part,
    whatever their values. Each pass computes its masked products from the raw rows (no
    masked copies of the coordinates are written to memory), and the cross-covariance and
    the two clouds' own covariances are separate reductions, so that a caller that needs
    the pose alone (:func:`kabsch` under ``jit``) pays for 9 products per row, not 21.
    Returns ``(weight_sum, count, mu (..., 6), h (..., 3, 3), cov_src, cov_dst)``."""
    used = w > 0
    x = [c[..., i] for c in (src, dst) for i in range(3)]
    first = row_sums([w] + [jnp.where(used, w * xi, 0.0) for xi in x])
    weight_sum = first[0]
    (count,) = row_sums([used.astype(w.dtype)])
    safe = jnp.where(weight_sum > 0, weight_sum, 1.0)
    mu = [m / safe for m in first[1:]]

    def block(pairs):
        sums = row_sums(
            [
                jnp.where(used, w * (x[i] - mu[i][..., None]) * (x[j] - mu[j][..., None]), 0.0)
                for i, j in pairs
            ]
        )
        m = {}
        for (i, j), value in zip(pairs, sums, strict=True):
            m[i, j] = m[j, i] = value / safe
        rows, cols = sorted({i for i, _ in pairs}), sorted({j for _, j in pairs})
        return jnp.stack([jnp.stack([m[i, j] for j in cols], -1) for i in rows], -2)

    h = block([(i, j) for i in range(3) for j in range(3, 6)])
    cov_src = block([(i, j) for i in range(3) for j in range(i, 3)])
    cov_dst = block([(i, j) for i in range(3, 6) for j in range(i, 6)])
    return weight_sum, count, jnp.stack(mu, -1), h, cov_src, cov_dst


@jax.custom_jvp
def _centred_moments(src, dst, w):
    """:func:`_centred` by variadic reductions; its derivative is that of the same sums
    written as separate reductions (``lax.reduce`` with several operands has no
    differentiation rule)."""
    return _centred(src, dst, w, _row_sums)


@_centred_moments.defjvp
def _centred_moments_jvp(primals, tangents):
    def reference(src, dst, w):
        # Padding rows zeroed first: a NaN there must not reach the reverse pass (0 * NaN).
        used = (w > 0)[..., None]
        src, dst = jnp.where(used, src, 0.0), jnp.where(used, dst, 0.0)
        return _centred(src, dst, w, _row_sums_reference)

    return jax.jvp(reference, primals, tangents)


def _fit(
    src: Float[Array, "... N 3"],
    dst: Float[Array, "... N 3"],
    w: Float[Array, "... N"],
    top_eigen=top_eigenpair,
) -> _Fit:
    """Weighted centroids, Horn's rotation and the degeneracy signals of :class:`Alignment`.

    ``src``, ``dst`` ``(..., N, 3)`` and ``w`` ``(..., N)`` share their batch axes; ``w >= 0``
    and rows with ``w == 0`` are padding, whatever their values. Shared by :func:`align` and
    the ICP loop, which skips :func:`align`'s input checks and passes its own ``top_eigen``
    (eigenvalues ascending, top eigenvector) for Horn's 4x4 matrix. Two passes over the rows
    (each one variadic reduction): the weighted centroids, then the centred second moments.
    """
    weight_sum, count, mu, h, cov_src, cov_dst = _centred_moments(src, dst, w)

    # q^T K(H^T) q = tr(R(q)^T H^T) = tr(R H): Horn's matrix is K of the transpose.
    horn = procrustes_quaternion_matrix(jnp.swapaxes(h, -1, -2))
    eig, q = top_eigen(horn)
    top = jnp.einsum("...i,...ij,...j->...", q, horn, q)  # = tr(R H)
    # No weight at all: the identity (the centroids are then 0, and so is the translation).
    q = jnp.where((weight_sum > 0)[..., None], q, jnp.array([1, 0, 0, 0], q.dtype))

    tol = 100 * _eps(w.dtype)
    scale_ref = jnp.abs(eig[..., -1]) + jnp.abs(eig[..., 0])
    eigengap = (eig[..., -1] - eig[..., -2]) / jnp.where(scale_ref > 0, scale_ref, 1.0) * 2

    def line_and_plane(c):
        tr, i2, det = _shape_invariants(c)
        tr = jnp.where(tr > 0, tr, 1.0)
        line = i2 <= tol * tr**2
        plane = line | (det <= tol * jnp.where(i2 > 0, i2, 1.0) * tr)
        return line, plane

    src_line, src_plane = line_and_plane(cov_src)
    dst_line, _ = line_and_plane(cov_dst)
    collinear = src_line | dst_line
    return _Fit(
        weight_sum=weight_sum,
        count=count,
        mu_src=mu[..., :3],
        mu_dst=mu[..., 3:],
        var_src=jnp.trace(cov_src, axis1=-2, axis2=-1),
        rotation=SO3(wxyz=q),
        top=top,
        eigengap=eigengap,
        collinear=collinear,
        planar=src_plane,
        degenerate=(count < 3) | collinear | (eigengap <= tol),
    )


@eqx.filter_jit
def align(
    source: Float[ArrayLike, "... N 3"],
    target: Float[ArrayLike, "... N 3"],
    weights: Float[ArrayLike, "... N"] | None = None,
    *,
    with_scale: bool = False,
) -> Alignment:
    """Weighted least-squares rigid (or similarity) transform from ``source`` to ``target``.

    Args:
        source: ``(..., N, 3)`` source points; row ``i`` corresponds to row ``i`` of ``target``.
        target: ``(..., N, 3)`` target points (batch axes broadcast against ``source``).
        weights: optional ``(..., N)`` non-negative weights (negative values count as 0).
            Zero-weight rows are padding. Defaults to 1.
        with_scale: also estimate a similarity scale (Umeyama).

    Returns:
        An :class:`Alignment` with the pose, scale, residual, status and degeneracy signals.

    Raises:
        ValueError: malformed shapes, or fewer than 3 rows (a static count; fewer than 3
            *weighted* rows is the status ``too_few_correspondences``).
    """
    source, target, weights = _check_shapes(source, target, weights)
    finite = jnp.all(jnp.isfinite(source) & jnp.isfinite(target), axis=-1)
    w = jnp.where(finite & (weights > 0), weights, 0.0)
    shape = jnp.broadcast_shapes(source.shape, target.shape, w[..., None].shape)
    source, target = jnp.broadcast_to(source, shape), jnp.broadcast_to(target, shape)
    w = jnp.broadcast_to(w, shape[:-1])
    fit = _fit(source, target, w)

    rotation = fit.rotation
    if with_scale:
        scale = fit.top / jnp.where(fit.var_src > 0, fit.var_src, 1.0)
    else:
        scale = jnp.ones_like(fit.top)
    translation = fit.mu_dst - scale[..., None] * rotation.apply(fit.mu_src)
    pose = SE3.from_rotation_and_translation(rotation, translation)
    used = (w > 0)[..., None]
    a = jnp.where(used, source - fit.mu_src[..., None, :], 0.0)
    b = jnp.where(used, target - fit.mu_dst[..., None, :], 0.0)
    rotated = jnp.einsum("...ij,...nj->...ni", rotation.as_matrix(), a)
    resid = scale[..., None, None] * rotated - b
    wn = w / jnp.where(fit.weight_sum > 0, fit.weight_sum, 1.0)[..., None]
    sq = jnp.einsum("...n,...nd->...", wn, resid * resid)
    rms = jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)
    status = _status(fit)
    return Alignment(
        pose=pose,
        status=status,
        converged=status == AlignmentStatus.success,
        iterations=jnp.zeros(fit.count.shape, jnp.int32),
        scale=scale,
        weight_sum=fit.weight_sum,
        count=fit.count,
        rms=rms,
        eigengap=fit.eigengap,
        collinear=fit.collinear,
        planar=fit.planar,
        degenerate=fit.degenerate,
    )


def _status(fit: _Fit) -> AlignmentStatus:
    """The first failure that applies, in the order: weight, collinearity, uniqueness."""
    return select_status(
        [
            (fit.count < 3, AlignmentStatus.too_few_correspondences),
            (fit.collinear, AlignmentStatus.degenerate),
            (fit.degenerate, AlignmentStatus.ambiguous_rotation),
        ],
        AlignmentStatus.success,
    )


def kabsch(
    source: Float[ArrayLike, "... N 3"],
    target: Float[ArrayLike, "... N 3"],
    weights: Float[ArrayLike, "... N"] | None = None,
) -> SE3:
    """Rigid transform minimising ``sum_i w_i ||R source_i + t - target_i||^2``.

    Args:
        source: ``(..., N, 3)`` source points, row-matched to ``target``.
        target: ``(..., N, 3)`` target points.
        weights: optional ``(..., N)`` non-negative weights; zero rows are padding.

    Returns:
        ``SE3`` with batch axes ``(...)`` mapping source into target coordinates, always a
        proper rotation. A problem with no weighted row (every weight zero, or every row
        non-finite) determines no pose: its pose is NaN, under ``jit`` too. Callers that need
        the status (collinear points, fewer than 3 weighted rows, non-unique rotation) use
        :func:`align`.
    """
    result = align(source, target, weights)
    return _nan_without_weight(result.pose, result)


def _nan_without_weight(x, result: Alignment):
    """``x`` (an ``SE3`` or an array with the batch axes ``(...)``) with NaN in the problems
    of ``result`` that have no weighted row: the flag of the entry points without a status."""
    empty = result.weight_sum <= 0
    if isinstance(x, SE3):
        return SE3(jnp.where(empty[..., None], jnp.nan, x.wxyz_xyz))
    return jnp.where(empty, jnp.nan, x)


def umeyama(
    source: Float[ArrayLike, "... N 3"],
    target: Float[ArrayLike, "... N 3"],
    weights: Float[ArrayLike, "... N"] | None = None,
) -> tuple[SE3, Float[Array, "..."]]:
    """Similarity transform minimising ``sum_i w_i ||c R source_i + t - target_i||^2``.

    Returns:
        ``(pose, scale)``: ``pose`` holds ``R`` and ``t`` (batch axes ``(...)``) and ``scale``
        is ``c`` with shape ``(...)``, so ``target ~ scale * pose.rotation() @ source + t``.
        Both are NaN for a problem with no weighted row, as in :func:`kabsch`; the status is
        :func:`align`'s (``with_scale=True``).
    """
    result = align(source, target, weights, with_scale=True)
    return _nan_without_weight(result.pose, result), _nan_without_weight(result.scale, result)
