"""Global registration by RANSAC over descriptor correspondences, reproducible by key.

ICP needs a start inside its basin; RANSAC needs none. Source and target descriptors (e.g.
:func:`jaxreg.fpfh`) are matched (:func:`jaxreg.search.features.match_features`), and hypotheses
are drawn from the matches: three distinct correspondences, a cheap edge-length check (a
rigid motion keeps the triangle's sides), a rigid fit by Kabsch, a distance check (the three
must land within ``max_correspondence_distance``), then a score: the number of
correspondences the pose brings within that distance (inliers), ties broken by their RMSE,
then by draw order. The best pose is refit by Kabsch on its inliers.

Hypotheses are drawn and scored in vmapped batches inside one compiled ``while_loop``.
Batch ``b`` draws from ``fold_in(key, b)``, so the answer is a function of ``key`` and the
inputs alone: repeated calls, and runs with one or several devices, give bit-identical
poses (the loop runs on one device; nothing depends on thread or device counts, unlike
Open3D's). The loop stops when the hypotheses drawn reach :func:`ransac_iterations` for the
best inlier ratio so far and ``confidence`` (the chance that an all-inlier sample was among
them), or ``max_iterations``.

A pose explained by fewer than ``min_inliers`` correspondences is never reported as a
success: three sampled correspondences always explain themselves, so an all-outlier set
still yields some hypothesis, and only inliers beyond the sample are evidence. Wrong
matches also land near each other by chance, the more often the more of them there are, so
the default bar rises with the number of correspondences (``MIN_INLIER_SHARE`` of them,
at least ``MIN_INLIERS``).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3, SO3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.core._result import AbstractResult, select_status
from jaxreg.geometry.alignment import _fit
from jaxreg.search.features import match_features

__all__ = ["RansacResult", "RansacStatus", "ransac_iterations", "ransac_registration"]

SAMPLE_SIZE = 3
# The default min_inliers: this share of the usable correspondences, and at least this many.
MIN_INLIER_SHARE = 0.02
MIN_INLIERS = 6
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])  # wxyz_xyz


class RansacStatus(eqx.Enumeration):
    """Outcome of :func:`ransac_registration`; each member's value is the message a user
    needs."""

    success = "success: a pose with enough inliers was found at the requested confidence"
    max_iterations = (
        "reached max_iterations before the requested confidence: the pose is the best found "
        "but an all-inlier sample may not have been drawn; raise max_iterations, or improve "
        "the matches (larger feature radius, ratio test)"
    )
    too_few_features = (
        "fewer than 3 usable descriptors in the source or the target (all-zero or non-finite "
        "rows, masked points): check the normals and the feature radius"
    )
    too_few_matches = (
        "fewer than 3 descriptor correspondences survived matching (mutual filter, ratio "
        "test): try mutual=False, a looser ratio, or a larger feature radius"
    )
    no_consensus = (
        "no hypothesis gathered min_inliers inliers: the matches look like outliers only "
        "(wrong object, features that do not repeat), or max_correspondence_distance is too "
        "small for the noise; the identity is returned"
    )


class RansacResult(AbstractResult):
    """Result of :func:`ransac_registration`, measured over the descriptor correspondences
    (not, as ICP's :class:`~jaxreg.registration.icp.RegistrationResult`, over nearest
    neighbours).

    Attributes:
        pose: ``SE3`` source -> target; the identity when no hypothesis was found (see
            ``status``).
        status: :class:`RansacStatus` member.
        converged: ``()`` the confidence was reached with enough inliers (status
            ``success``).
        iterations: ``()`` hypotheses drawn.
        inlier_rmse: ``()`` RMS distance of the inlier correspondences (metres; NaN
            without a pose).
        inlier_fraction: ``()`` inlier correspondences over the usable correspondences.
        num_inliers: ``()`` correspondences within ``max_correspondence_distance``.
        correspondences: ``(N,)`` each source point's matched target row if that match is an
            inlier, else ``M``.
        weights: ``(N,)`` 1 for those inliers, else 0.
    """

    pose: SE3
    status: RansacStatus
    converged: Bool[Array, ""]
    iterations: Int[Array, ""]
    inlier_rmse: Float[Array, ""]
    inlier_fraction: Float[Array, ""]
    num_inliers: Int[Array, ""]
    correspondences: Int[Array, " N"]
    weights: Float[Array, " N"]


def _budget(inlier_ratio, sample_size: int, confidence, xp):
    """Samples needed so that one is all-inlier with probability ``confidence``
    (``inf`` for a zero ratio); ``xp`` is ``numpy`` or ``jax.numpy``."""
    p_good = xp.asarray(inlier_ratio) ** sample_size
    live, certain = p_good > 0, p_good >= 1
    safe = xp.where(live & ~certain, p_good, 0.5)
    k = xp.maximum(1.0, xp.ceil(xp.log1p(-xp.asarray(confidence)) / xp.log1p(-safe)))
    return xp.where(certain, 1.0, xp.where(live, k, xp.inf))


def ransac_iterations(inlier_ratio: float, sample_size: int = 3, confidence: float = 0.99) -> int:
    """RANSAC's budget: the least ``k`` with ``(1 - w^s)^k <= 1 - p``, i.e.
    ``k = ceil(log(1 - p) / log(1 - w^s))`` (at least 1).

    Args:
        inlier_ratio: ``w`` in ``(0, 1]``, the fraction of correct correspondences.
        sample_size: ``s``, correspondences per hypothesis (3 for a rigid pose).
        confidence: ``p`` in ``(0, 1)``, the wanted probability that at least one sample
            is all-inlier.

    Raises:
        ValueError: an argument outside its range (a zero inlier ratio has no finite
            budget).
    """
    if not 0 < inlier_ratio <= 1:
        raise ValueError(
            f"inlier_ratio must lie in (0, 1] (with none no sample count suffices), got "
            f"{inlier_ratio}"
        )
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    if sample_size < 1:
        raise ValueError(f"sample_size must be a positive integer, got {sample_size}")
    return int(_budget(np.float64(inlier_ratio), sample_size, np.float64(confidence), np))


class _Best(eqx.Module):
    """The loop's state: batches run, hypotheses drawn, and the best hypothesis so far."""

    batch: Int[Array, ""]
    drawn: Int[Array, ""]
    count: Int[Array, ""]  # its inliers (0: none yet)
    rmse: Float[Array, ""]
    pose: Float[Array, " 7"]


def _distinct_triples(key, size: int, count) -> Int[Array, "size 3"]:
    """``(size, 3)`` uniform triples of distinct indices in ``[0, count)`` (``count >= 3``)."""
    k0, k1, k2 = jax.random.split(key, 3)
    i = jax.random.randint(k0, (size,), 0, count)
    j = jax.random.randint(k1, (size,), 0, count - 1)
    j = j + (j >= i)
    lo, hi = jnp.minimum(i, j), jnp.maximum(i, j)
    k = jax.random.randint(k2, (size,), 0, count - 2)
    k = k + (k >= lo)
    k = k + (k >= hi)
    return jnp.stack([i, j, k], axis=-1).astype(jnp.int32)


def _edges_agree(src: Array, dst: Array, ratio) -> Array:
    """Every side of the source triangle is within ``ratio`` of its target side, both ways
    (Open3D's edge-length checker); ``src``, ``dst`` are ``(..., 3, 3)``."""
    a = jnp.linalg.norm(src - jnp.roll(src, 1, axis=-2), axis=-1)
    b = jnp.linalg.norm(dst - jnp.roll(dst, 1, axis=-2), axis=-1)
    return jnp.all((a >= ratio * b) & (b >= ratio * a), axis=-1)


def _pose(fit) -> Float[Array, "... 7"]:
    """``wxyz_xyz`` of the rigid fit: ``t = mu_dst - R mu_src``."""
    t = fit.mu_dst - fit.rotation.apply(fit.mu_src)
    return jnp.concatenate([fit.rotation.wxyz, t], axis=-1)


def _residual_sq(pose: Array, src: Array, dst: Array) -> Array:
    """``|pose @ src - dst|^2`` ``(..., C)`` for poses ``(..., 7)`` and rows ``(..., C, 3)``,
    by the rotation matrix's entries, written out per coordinate: XLA's CPU backend fuses
    these multiply-adds, where jaxlie's batched quaternion ``apply`` gathers the terms of its
    Hamilton products and a sum over a minor axis of 3 runs as a kernel of its own."""
    r = SO3(pose[..., :4]).as_matrix()
    total = 0.0
    for i in range(3):
        row = r[..., i, None, :]
        moved = row[..., 0] * src[..., 0] + row[..., 1] * src[..., 1] + row[..., 2] * src[..., 2]
        diff = moved + pose[..., 4 + i, None] - dst[..., i]
        total = total + diff * diff
    return total


def _score(pose: Array, src: Array, dst: Array, valid: Array, d2_max) -> tuple[Array, Array]:
    """Inlier count and RMSE of poses ``(..., 7)`` over the correspondences ``(C, 3)``."""
    r2 = _residual_sq(pose, src, dst)
    inlier = valid & (r2 <= d2_max)
    count = inlier.sum(-1)
    rmse = jnp.sqrt(jnp.where(inlier, r2, 0).sum(-1) / jnp.maximum(count, 1))
    return count.astype(jnp.int32), rmse


def _better(count, rmse, best_count, best_rmse):
    return (count > best_count) | ((count == best_count) & (rmse < best_rmse))


@eqx.filter_jit
def _search(src, dst, valid, key, distance, confidence, max_iterations, edge_ratio, batch: int):
    """The compiled loop over batches of ``batch`` hypotheses; correspondences ``src``,
    ``dst`` ``(C, 3)`` with the ``valid`` ones first."""
    count = valid.sum()
    d2_max = distance**2
    pool = 4 * batch  # samples drawn per batch; the first `batch` that pass the edge check run

    def needed(best: _Best):
        ratio = best.count / jnp.maximum(count, 1)
        return _budget(ratio, SAMPLE_SIZE, confidence, jnp)

    def cond(best: _Best):
        return (count >= SAMPLE_SIZE) & (best.drawn < max_iterations) & (best.drawn < needed(best))

    def body(best: _Best) -> _Best:
        triples = _distinct_triples(jax.random.fold_in(key, best.batch), pool, count)
        s, d = src[triples], dst[triples]
        position = jnp.arange(pool)
        passed = _edges_agree(s, d, edge_ratio) & (position < max_iterations - best.drawn)
        order = jnp.argsort(~passed, stable=True)[:batch]
        # The samples considered: up to the last one run, or the whole pool.
        full = passed.sum() >= batch
        considered = jnp.where(full, order[-1] + 1, jnp.minimum(pool, max_iterations - best.drawn))
        s, d, run = s[order], d[order], passed[order]
        fit = _fit(s, d, jnp.ones(s.shape[:-1], s.dtype))
        pose = _pose(fit)
        landed = _residual_sq(pose, s, d) <= d2_max
        run = run & ~fit.collinear & jnp.all(landed, axis=-1)
        inliers, rmse = _score(pose, src, dst, valid, d2_max)
        inliers = jnp.where(run, inliers, 0)
        top = jnp.max(inliers)
        pick = jnp.argmin(jnp.where(inliers == top, rmse, jnp.inf))
        take = (top > 0) & _better(top, rmse[pick], best.count, best.rmse)
        return _Best(
            batch=best.batch + 1,
            drawn=best.drawn + considered.astype(jnp.int32),
            count=jnp.where(take, top, best.count),
            rmse=jnp.where(take, rmse[pick], best.rmse),
            pose=jnp.where(take, pose[pick], best.pose),
        )

    dtype = src.dtype
    start = _Best(
        batch=jnp.zeros((), jnp.int32),
        drawn=jnp.zeros((), jnp.int32),
        count=jnp.zeros((), jnp.int32),
        rmse=jnp.asarray(jnp.inf, dtype),
        pose=jnp.asarray(_IDENTITY, dtype),
    )
    best = jax.lax.while_loop(cond, body, start)
    # Refit on the inliers; keep the refit unless it explains fewer correspondences.
    r2 = _residual_sq(best.pose, src, dst)
    weights = (valid & (r2 <= d2_max)).astype(dtype)
    refit = _pose(_fit(src, dst, weights))
    refit_count, refit_rmse = _score(refit, src, dst, valid, d2_max)
    use = (best.count > 0) & ~_better(best.count, best.rmse, refit_count, refit_rmse)
    best = eqx.tree_at(
        lambda b: (b.count, b.rmse, b.pose),
        best,
        (
            jnp.where(use, refit_count, best.count),
            jnp.where(use, refit_rmse, best.rmse),
            jnp.where(use, refit, best.pose),
        ),
    )
    return best, best.drawn >= needed(best)


def ransac_registration(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    source_features: Float[ArrayLike, "N D"],
    target_features: Float[ArrayLike, "M D"],
    *,
    max_correspondence_distance: float,
    confidence: float = 0.999,
    max_iterations: int = 100_000,
    key: Array,
    mutual: bool = True,
    ratio: float | None = None,
    edge_length_ratio: float = 0.9,
    min_inliers: int | None = None,
    batch_size: int = 256,
) -> RansacResult:
    """Pose of ``source`` in ``target`` from descriptor matches by RANSAC (see the module
    docstring for the algorithm).

    Args:
        source: ``(N, 3)`` source (model) points.
        target: ``(M, 3)`` target (scene) points.
        source_features, target_features: ``(N, D)``, ``(M, D)`` descriptors of those
            points (:func:`jaxreg.fpfh`); all-zero or non-finite rows take no part.
        max_correspondence_distance: a correspondence is an inlier of a pose that brings
            its points this close (metres; 1-2 voxel sizes of the clouds).
        confidence: wanted probability in ``(0, 1)`` that an all-inlier sample was drawn;
            the loop stops once :func:`ransac_iterations` of the best inlier ratio is met.
        max_iterations: bound on the hypotheses drawn.
        key: ``jax.random`` key; the result is a function of it and the inputs alone.
        mutual, ratio: matching filters of :func:`jaxreg.search.features.match_features`.
        edge_length_ratio: a sample runs only if each side of its source triangle is
            within this factor of the target side, both ways (Open3D's 0.9).
        min_inliers: fewest inlier correspondences (the 3 sampled included) for a pose to
            count as found; default ``max(6, ceil(0.02 * C))`` for ``C`` usable
            correspondences (``MIN_INLIERS``, ``MIN_INLIER_SHARE``): among thousands of
            wrong matches, a few agree with some pose by chance.
        batch_size: hypotheses fitted and scored per step (static; larger suits GPUs).

    Returns:
        :class:`RansacResult`.

    Raises:
        ValueError: mis-shaped inputs or a setting outside its range.
    """
    source, target = jnp.asarray(source), jnp.asarray(target)
    dtype = jnp.result_type(source.dtype, target.dtype, jnp.float32)
    source, target = source.astype(dtype), target.astype(dtype)
    n, m = source.shape[0], target.shape[0]
    if source.ndim != 2 or target.ndim != 2 or source.shape[1] != 3 or target.shape[1] != 3:
        raise ValueError(f"source and target must be (N, 3), got {source.shape}, {target.shape}")
    sf, tf = jnp.asarray(source_features), jnp.asarray(target_features)
    if sf.shape[0] != n or tf.shape[0] != m:
        raise ValueError(
            f"one descriptor row per point: source {source.shape} has features {sf.shape}, "
            f"target {target.shape} has {tf.shape}"
        )
    if not max_correspondence_distance > 0:
        raise ValueError(
            f"max_correspondence_distance must be positive, got {max_correspondence_distance}"
        )
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence}")
    if max_iterations < 1 or (min_inliers is not None and min_inliers < SAMPLE_SIZE) or (
        batch_size < 1
    ):
        raise ValueError(
            "max_iterations and batch_size must be positive and min_inliers at least 3, got "
            f"{max_iterations}, {batch_size}, {min_inliers}"
        )
    if not 0 < edge_length_ratio <= 1:
        raise ValueError(f"edge_length_ratio must lie in (0, 1], got {edge_length_ratio}")

    source_ok = jnp.all(jnp.isfinite(source), axis=-1)
    target_ok = jnp.all(jnp.isfinite(target), axis=-1)
    matches = match_features(
        sf, tf, mutual=mutual, ratio=ratio, source_mask=source_ok, target_mask=target_ok
    )
    usable = (
        jnp.minimum(
            (jnp.any(sf != 0, -1) & jnp.all(jnp.isfinite(sf), -1) & source_ok).sum(),
            (jnp.any(tf != 0, -1) & jnp.all(jnp.isfinite(tf), -1) & target_ok).sum(),
        )
        >= SAMPLE_SIZE
    )
    # Correspondences, valid ones first (stable: the order of the source rows).
    order = jnp.argsort(~matches.mask, stable=True)
    valid = matches.mask[order]
    src = jnp.where(valid[:, None], source[order], 0)
    dst = jnp.where(valid[:, None], target.at[matches.target_index[order]].get(mode="clip"), 0)
    count = valid.sum()
    best, reached = _search(
        src, dst, valid, key,
        jnp.asarray(max_correspondence_distance, dtype), jnp.asarray(confidence, dtype),
        jnp.asarray(max_iterations, jnp.int32), jnp.asarray(edge_length_ratio, dtype),
        batch_size,
    )  # fmt: skip
    if min_inliers is None:
        min_inliers = jnp.maximum(MIN_INLIERS, jnp.ceil(MIN_INLIER_SHARE * count))
    found = best.count >= min_inliers
    status = select_status(
        [
            (~usable, RansacStatus.too_few_features),
            (count < SAMPLE_SIZE, RansacStatus.too_few_matches),
            (~found, RansacStatus.no_consensus),
            (~reached, RansacStatus.max_iterations),
        ],
        RansacStatus.success,
    )
    ok = usable & (count >= SAMPLE_SIZE) & found
    pose = SE3(jnp.where(ok, best.pose, jnp.asarray(_IDENTITY, dtype)))
    r2 = _residual_sq(pose.wxyz_xyz, src, dst)
    inlier = ok & valid & (r2 <= max_correspondence_distance**2)
    target_rows = jnp.where(inlier, matches.target_index[order], m)
    rmse = jnp.where(ok, best.rmse, jnp.nan)
    return RansacResult(
        pose=pose,
        status=status,
        converged=ok & reached,
        iterations=jnp.where(count >= SAMPLE_SIZE, best.drawn, 0),
        inlier_rmse=rmse,
        inlier_fraction=jnp.where(ok, best.count / jnp.maximum(count, 1), 0.0).astype(dtype),
        num_inliers=jnp.where(ok, best.count, 0),
        correspondences=jnp.full(n, m, jnp.int32).at[order].set(target_rows),
        weights=jnp.zeros(n, dtype).at[order].set(inlier.astype(dtype)),
    )
