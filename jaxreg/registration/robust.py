"""Outlier-robust alignment of matched point sets: graduated non-convexity over a truncated
least-squares cost (GNC-TLS, as in TEASER++), differentiable at its solution.

Problem, for correspondences ``(src_i, dst_i)`` with prior weights ``w_i`` and a noise bound
``c`` (the largest residual an inlier can have)::

    min_{R, t}  sum_i w_i min(|R src_i + t - dst_i|^2 / c^2, 1)

Correspondences farther than ``c`` from the solution cost a constant, so any fraction of them
may be wrong. The truncated cost is not convex; GNC solves a sequence of smoothed surrogates
(controlled by ``mu``, from nearly convex to the TLS cost itself), each by weighted Kabsch
(:func:`jaxreg.geometry.alignment.kabsch`) with the surrogate's weights::

    w(r^2) = 1                                  if r^2 <= mu / (mu + 1) c^2
             0                                  if r^2 >= (mu + 1) / mu c^2
             c sqrt(mu (mu + 1)) / |r| - mu     otherwise

and ``mu`` grows by 1.4 each step, until the weights stop changing. Beyond ~80% outliers
GNC alone can lock onto a wrong pose, so its start comes from a cheap consistency check
first: a rigid motion keeps distances, so two inliers satisfy
``| |src_i - src_j| - |dst_i - dst_j| | <= 2c``; peeling the correspondence with the fewest
consistent partners until the rest are all mutually consistent leaves a clique that the
inliers dominate (TEASER++'s maximum clique, approximated greedily). That needs an
``(N, N)`` table: a few thousand correspondences at most.

The returned pose is the weighted Kabsch solution on the final inliers, whose derivative
(the inlier set held fixed, as it is almost everywhere) flows through the closed form.

To use on descriptor matches instead of RANSAC (:func:`jaxreg.ransac_registration`)::

    m = match_features(source_features, target_features)
    result = robust_kabsch(source, target[jnp.minimum(m.target_index, M - 1)],
                           noise_bound=..., weights=m.mask)
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.core._result import AbstractResult, select_status
from jaxreg.geometry.alignment import _check_shapes, _fit

__all__ = ["RobustAlignment", "RobustStatus", "robust_kabsch"]

_MU_FACTOR = 1.4


class RobustStatus(eqx.Enumeration):
    """Outcome of :func:`robust_kabsch`; each member's value is the message a user needs."""

    success = "success: GNC converged with at least min_inliers non-collinear inliers"
    too_few_inliers = (
        "fewer than min_inliers correspondences lie within noise_bound of the solution: the "
        "set may be all outliers (any 3 random matches can agree by chance), or noise_bound "
        "too small for the noise; the identity is returned"
    )
    degenerate = (
        "the inliers are collinear or coincident: the rotation about their line is unobservable"
    )
    ambiguous_rotation = (
        "the optimal rotation of the inliers is not unique (a symmetric or reflected "
        "configuration): the pose is one of a family that fits equally well; add "
        "correspondences that break the symmetry"
    )
    max_iterations = (
        "GNC's weights were still changing at max_iterations: the pose is the last estimate; "
        "raise max_iterations"
    )


class RobustAlignment(AbstractResult):
    """Result of :func:`robust_kabsch` (unbatched; ``vmap`` for batches).

    Attributes:
        pose: ``SE3`` source -> target (the identity with fewer than ``min_inliers``).
        status: :class:`RobustStatus` member.
        converged: ``()`` ``status == success``.
        iterations: ``()`` GNC steps taken.
        inliers: ``(N,)`` correspondences with positive weight within ``noise_bound`` of
            the pose.
        num_inliers: ``()`` their number.
        rms: ``()`` RMS residual of the inliers.
    """

    pose: SE3
    status: RobustStatus
    converged: Bool[Array, ""]
    iterations: Int[Array, ""]
    inliers: Bool[Array, " N"]
    num_inliers: Int[Array, ""]
    rms: Float[Array, ""]


def _residuals(fit, src: Array, dst: Array) -> Float[Array, " N"]:
    """Squared residuals ``|R src + t - dst|^2`` of a :func:`jaxreg.geometry.alignment._fit`."""
    moved = fit.rotation.apply(src - fit.mu_src) + fit.mu_dst
    return jnp.sum((moved - dst) ** 2, axis=-1)


def _tls_weights(r2: Array, mu: Array, c2: Array) -> Array:
    """GNC's weights of the TLS surrogate at ``mu`` (see the module docstring)."""
    lo, hi = mu / (mu + 1) * c2, (mu + 1) / mu * c2
    between = jnp.sqrt(c2 * mu * (mu + 1) / jnp.maximum(r2, lo)) - mu
    return jnp.where(r2 <= lo, 1.0, jnp.where(r2 >= hi, 0.0, between))


def _consistent_clique(src: Array, dst: Array, prior: Array, c: Array) -> Bool[Array, " N"]:
    """Greedy clique of pairwise distance-consistent correspondences (peeling the least
    consistent until the rest agree pairwise)."""
    n = src.shape[0]

    def distances(x):
        d = x[:, None, :] - x[None, :, :]
        return jnp.sqrt(jnp.sum(d * d, axis=-1) + jnp.eye(n, dtype=x.dtype))

    used = prior > 0
    agree = (jnp.abs(distances(src) - distances(dst)) <= 2 * c) & used[:, None] & used[None, :]
    agree = agree & ~jnp.eye(n, dtype=bool)
    degree = agree.sum(-1)

    def peel(_, state):
        alive, degree, done = state
        size = alive.sum()
        low = jnp.where(alive, degree, n + 1)
        clique = jnp.min(low) >= size - 1
        done = done | clique
        drop = jnp.argmin(low)
        remove = ~done & alive[drop]
        alive = alive.at[drop].set(alive[drop] & ~remove)
        degree = degree - jnp.where(remove, agree[drop], False)
        return alive, degree, done

    alive, _, _ = jax.lax.fori_loop(0, n, peel, (used, degree, jnp.zeros((), bool)))
    return alive


@eqx.filter_jit
def _solve(src, dst, prior, c, max_iterations):
    c2 = c * c
    clique = _consistent_clique(src, dst, prior, c)
    start = _fit(src, dst, prior * clique)
    r2 = _residuals(start, src, dst)
    mu0 = 1.0 / jnp.maximum(2.0 * jnp.max(jnp.where(prior > 0, r2, 0.0)) / c2 - 1.0, 1e-6)

    def cond(state):
        step, _, _, change = state
        return (step < max_iterations) & (change > 1e-6)

    def body(state):
        step, mu, weights, _ = state
        fit = _fit(src, dst, prior * weights)
        new = _tls_weights(_residuals(fit, src, dst), mu, c2)
        change = jnp.max(jnp.abs(new - weights) * (prior > 0))
        return step + 1, mu * _MU_FACTOR, new, change

    weights = _tls_weights(r2, mu0, c2)
    state = (jnp.zeros((), jnp.int32), mu0 * _MU_FACTOR, weights, jnp.asarray(jnp.inf, c.dtype))
    steps, _, weights, change = jax.lax.while_loop(cond, body, state)
    fit = _fit(src, dst, prior * weights)
    inliers = (prior > 0) & (_residuals(fit, src, dst) <= c2)
    # The solution as a closed form of the data, the inlier set held fixed.
    final = _fit(src, dst, prior * jax.lax.stop_gradient(inliers.astype(src.dtype)))
    return final, inliers, steps, change <= 1e-6


def robust_kabsch(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "N 3"],
    *,
    noise_bound: float,
    weights: Float[ArrayLike, " N"] | None = None,
    max_iterations: int = 100,
    min_inliers: int = 6,
) -> RobustAlignment:
    """Rigid transform of row-matched points, robust to any fraction of wrong matches
    (GNC-TLS; see the module docstring).

    Args:
        source: ``(N, 3)`` source points, row-matched to ``target``.
        target: ``(N, 3)`` target points.
        noise_bound: ``c``, the largest distance an inlier may have from its match at the
            true pose (metres; about 3 sigma of the noise).
        weights: optional ``(N,)`` non-negative prior weights; zero rows are padding (a
            mask), non-finite rows are ignored.
        max_iterations: bound on the GNC steps.
        min_inliers: fewest inliers for a pose to count as found (at least 3; a few random
            wrong matches agree with some pose by chance, so a margin above 3 keeps an
            all-outlier set from being reported as a success).

    Returns:
        :class:`RobustAlignment`.

    Raises:
        ValueError: mis-shaped inputs, a non-positive ``noise_bound`` or ``min_inliers < 3``.
    """
    src, dst, prior = _check_shapes(source, target, weights)
    if src.ndim != 2:
        raise ValueError(
            f"robust_kabsch takes one (N, 3) problem (vmap for batches), got {src.shape}"
        )
    if min_inliers < 3:
        raise ValueError(f"min_inliers must be at least 3, got {min_inliers}")
    if not noise_bound > 0:
        raise ValueError(f"noise_bound must be positive, got {noise_bound}")
    finite = jnp.all(jnp.isfinite(src), -1) & jnp.all(jnp.isfinite(dst), -1)
    prior = jnp.where(finite, prior, 0.0)
    src, dst = jnp.where(finite[:, None], src, 0.0), jnp.where(finite[:, None], dst, 0.0)
    c = jnp.asarray(noise_bound, src.dtype)
    fit, inliers, steps, settled = _solve(src, dst, prior, c, jnp.asarray(max_iterations))
    count = inliers.sum()
    status = select_status(
        [
            (count < min_inliers, RobustStatus.too_few_inliers),
            (fit.collinear, RobustStatus.degenerate),
            (fit.degenerate, RobustStatus.ambiguous_rotation),
            (~settled, RobustStatus.max_iterations),
        ],
        RobustStatus.success,
    )
    ok = count >= min_inliers
    rotation = jnp.where(ok, fit.rotation.wxyz, jnp.array([1.0, 0.0, 0.0, 0.0], src.dtype))
    translation = jnp.where(ok, fit.mu_dst - fit.rotation.apply(fit.mu_src), 0.0)
    r2 = _residuals(fit, src, dst)
    rms = jnp.sqrt(jnp.sum(jnp.where(inliers, r2, 0.0)) / jnp.maximum(count, 1))
    return RobustAlignment(
        pose=SE3(jnp.concatenate([rotation, translation])),
        status=status,
        converged=status == RobustStatus.success,
        iterations=steps,
        inliers=inliers & ok,
        num_inliers=jnp.where(ok, count, 0).astype(jnp.int32),
        rms=jnp.where(ok, rms, jnp.nan),
    )
