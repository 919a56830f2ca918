"""Iterative Closest Point: point-to-point and point-to-plane, with rejection, trimming and
robust IRLS kernels; multi-start over a batch of initial poses in one compiled call; the
covariance of the result; and generators of initial poses.

Conventions:

* ``pose`` maps source coordinates into target coordinates (``target ~ pose @ source``);
  ``init`` is a ``jaxlie.SE3`` or a ``(4, 4)`` matrix in the same sense.
* Every iteration moves the source by the current pose, takes each moved point's nearest
  valid target point, keeps the pairs within the correspondence distance (and, with
  trimming, the best ``trim_fraction`` of them), weights them by the kernel's IRLS weight of
  the squared residual, and solves for an increment applied on the left (in the target
  frame):

  - point-to-point: weighted Kabsch of the moved source onto its matches (the closed form
    and degeneracy signal of :func:`jaxreg.geometry.alignment.align`); residual ``r = |T p - q|``.
  - point-to-plane: one Gauss-Newton step on the residual ``r = n_q . (T p - q)`` with the
    small-angle linearisation ``exp(d) p ~ p + w x p + v`` about the weighted centroid of
    the moved source, then the exact update ``T <- exp(d) T`` (:func:`jaxreg.geometry.lie.se3_exp`:
    jaxlie 1.5's ``SE3.exp`` is inaccurate for small rotations). Tangent order is jaxlie's
    ``(vx, vy, vz, wx, wy, wz)`` (Open3D's twist is ``(w, t)``: see :mod:`jaxreg.geometry.lie`).

* Valid target points: finite, and for point-to-plane with a finite unit normal
  (``| |n| - 1 | <= 1e-3``); the zero normals :func:`jaxreg.estimate_normals` returns where
  a normal is undefined, and unnormalised ones, make their point unusable: it is never a
  match and never counted.
* ``inlier_rmse`` is the RMS of the full 3D distance over the pairs kept in the last
  correspondence pass (for both methods, like Open3D), and ``inlier_fraction`` is the number
  of source points with a valid match within the correspondence distance over the number of
  valid source points (Open3D's ``fitness``), counted before trimming so that it stays a
  quality signal when ``trim_fraction`` fixes how many pairs are used.
* Convergence: the increment's translation norm and rotation angle both fall below
  ``tolerance`` (metres, radians), or the inlier RMSE changes by less than
  ``tolerance`` relative to itself while the inlier count is unchanged.

Failure is data: the result's ``status`` (:class:`ICPStatus`) says what went wrong (fewer
than 3 pairs within the distance, fewer than 3 with a positive weight, degenerate geometry,
the iteration bound, a non-finite update), ``converged`` is true only for ``success``, and
the pose is never NaN and never silently reset: when a step cannot be taken the last good
pose is kept and the status says why. Bad arguments (shapes, a ``neighbors=`` grid built on
another target, for a smaller distance, or overflowed) raise ``ValueError`` on the host.

Gradients: the returned pose is differentiable with respect to the source and target
points, target normals, source weights and the kernel scale by the implicit function
theorem at the converged fixed point with correspondences held fixed, not by unrolling
the iterations, and computed only when something differentiates. :func:`icp_covariance`
propagates point noise through the same objective, gradient and Hessian.

Options: every entry point takes ICP's options as one :class:`ICPOptions` (``options=``) or
field by field as keywords (``method=``, ``max_correspondence_distance=``, ...); given both,
the keywords replace those fields of ``options``. A keyword that is no field raises
``TypeError``.

Nearest neighbours come from a :class:`jaxreg.search.neighbors.NeighborGrid` built once per target
on the host (pass ``neighbors=`` to reuse one across calls). When the target is traced (under
``jit`` or ``grad`` with respect to the target) exact blocked brute force is used instead.

Layout: this module holds the public entry points and start generators;
:mod:`jaxreg.registration.solver` the steps they are made of (options, set-up, the loop), for
code that batches registrations its own way; the private ``_icp_setup`` (checks and padding),
``_icp_core`` (the loop and its derivatives) and ``_icp_covariance`` implement them.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from jaxlie import SE3, SO3
from jaxtyping import Array, ArrayLike, Float, Int

from jaxreg.geometry.lie import rotation_grid, rotation_grid_around, se3_exp
from jaxreg.registration._icp_core import (
    ICPStatus as ICPStatus,
    RegistrationResult as RegistrationResult,
    run_one,
)
from jaxreg.registration._icp_covariance import (
    icp_covariance as icp_covariance,
    init_spread as init_spread,
)
from jaxreg.registration._icp_setup import (
    ICPOptions as ICPOptions,
    as_pose,
    prepare,
    resolve_options,
    run_starts,
    unpad,
)

__all__ = [
    "ICPOptions",
    "ICPStatus",
    "RegistrationResult",
    "best_index",
    "icp",
    "icp_covariance",
    "init_spread",
    "multistart_icp",
    "pca_inits",
    "perturbed_inits",
    "rotation_inits",
    "select_best",
]


def icp(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    init: SE3 | Float[ArrayLike, "4 4"] | None = None,
    *,
    options: ICPOptions | None = None,
    **overrides: Any,
) -> RegistrationResult:
    """Register ``source`` to ``target`` by ICP from ``init``.

    Args:
        source: ``(N, 3)`` model / source points (NaN rows are ignored).
        target: ``(M, 3)`` scene / target points (NaN rows are ignored).
        init: initial source -> target pose, ``SE3`` or ``(4, 4)``; identity by default.
        options: ICP's options (:class:`ICPOptions`: method, target normals, correspondence
            distance or schedule, iteration bound, tolerance, kernel, trimming, source
            weights, neighbour grid); its defaults when ``None``.
        **overrides: fields of :class:`ICPOptions` by name (``method="point_to_plane"``,
            ``max_correspondence_distance=0.05``, ...), replacing those of ``options``.

    Returns:
        :class:`RegistrationResult` (batch ``()``).

    Raises:
        ValueError: bad shapes or method, point-to-plane without normals, or a
            ``neighbors`` grid built on another target, for a smaller distance, or
            overflowed (:func:`jaxreg.search.neighbors.validate_grid`).
        TypeError: a keyword that is not a field of :class:`ICPOptions`.
    """
    options = resolve_options(options, overrides, "icp")
    problem, opts, sizes = prepare(source, target, options)
    result = run_one(problem, opts, as_pose(init, problem.source.dtype))
    return unpad(result, *sizes)


def multistart_icp(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    inits: SE3 | Float[ArrayLike, "S 4 4"],
    *,
    options: ICPOptions | None = None,
    **overrides: Any,
) -> RegistrationResult:
    """ICP from every pose in ``inits`` in one compiled call.

    ``inits`` has one batch axis ``(S,)`` (an ``SE3`` batch or ``(S, 4, 4)``); every leaf of
    the result gains a leading axis ``S`` and ``result[i]`` is start ``i``'s result. Each
    start has its own status; one failed start never fails the batch. The neighbour
    structure is built once and shared. With more than one device in
    ``jax.local_devices()`` the starts are sharded over them (the problem is replicated).
    ``options`` and the keywords are those of :func:`icp`. :func:`select_best` picks the best
    start.
    """
    options = resolve_options(options, overrides, "multistart_icp")
    # Many starts query the grid many times: shorter candidate lists pay for a longer build.
    problem, opts, sizes = prepare(source, target, options, grid_capacity=24)
    return run_starts(problem, opts, sizes, inits)


def best_index(results: RegistrationResult) -> Int[Array, ""]:
    """Index of the best start of a batch ``(S,)`` of results: highest inlier fraction, then
    lowest inlier RMSE.

    Starts that failed for want of pairs (too few correspondences, too few weighted pairs)
    or with a non-finite update never win while another start succeeded, was degenerate or
    stopped at the iteration bound.
    """
    if len(results.batch_shape) != 1:
        raise ValueError(
            f"expected a batch of results with one axis (S,), got batch {results.batch_shape}"
        )
    failed = (
        (results.status == ICPStatus.too_few_correspondences)
        | (results.status == ICPStatus.too_few_weighted_pairs)
        | (results.status == ICPStatus.non_finite)
    )
    frac = jnp.where(failed, -1.0, results.inlier_fraction)
    rmse = jnp.where(failed, jnp.inf, results.inlier_rmse)
    return jnp.lexsort((rmse, -frac))[0]


def select_best(results: RegistrationResult) -> RegistrationResult:
    """The best start of a batch ``(S,)`` of results (from :func:`multistart_icp`) as one
    :class:`RegistrationResult` (batch ``()``); :func:`best_index` gives its index."""
    return results[best_index(results)]


def _centroid(points: Array) -> Array:
    ok = jnp.all(jnp.isfinite(points), -1, keepdims=True)
    return jnp.sum(jnp.where(ok, points, 0.0), 0) / jnp.maximum(jnp.sum(ok), 1)


def _principal_axes(points: Array) -> tuple[Array, Array]:
    """Centroid ``(3,)`` and principal axes as columns ``(3, 3)``, largest variance first."""
    c = _centroid(points)
    ok = jnp.all(jnp.isfinite(points), -1, keepdims=True)
    d = jnp.where(ok, points - c, 0.0)
    _, vec = jnp.linalg.eigh(d.T @ d)
    return c, vec[:, ::-1]


def pca_inits(source: Float[ArrayLike, "N 3"], target: Float[ArrayLike, "M 3"]) -> SE3:
    """The four proper poses that align the source's principal axes and centroid with the
    target's: batch ``(4,)``, one per sign choice of the axes (PCA fixes axes only up to sign).

    ``target`` is typically the segmented object's cloud. Its centroid is biased on partial
    views (the visible side only), so use these as starts for ICP, not as answers.
    """
    src = jnp.asarray(source)
    tgt = jnp.asarray(target, src.dtype)
    c_s, v_s = _principal_axes(src)
    c_t, v_t = _principal_axes(tgt)
    signs = jnp.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], src.dtype)
    # det(v_t diag(s) v_s^T) = det(v_t) det(v_s) prod(s): fix the third sign to make it +1.
    flip = jnp.linalg.det(v_t) * jnp.linalg.det(v_s)
    signs = signs.at[:, 2].multiply(flip)
    rotations = jnp.einsum("ij,sj,kj->sik", v_t, signs, v_s)
    translations = c_t - jnp.einsum("sij,j->si", rotations, c_s)
    return SE3.from_rotation_and_translation(SO3.from_matrix(rotations), translations)


def rotation_inits(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    n: int,
    *,
    around: SE3 | None = None,
    max_angle: float | None = None,
) -> SE3:
    """``n`` starts whose rotations cover SO(3) (or a ball around a prior), batch ``(n,)``.

    Without ``around`` the rotations are :func:`jaxreg.geometry.lie.rotation_grid` (near-uniform
    over SO(3)) applied about the source centroid, which each start places on the target
    centroid. With ``around`` (a prior pose) and ``max_angle`` (radians) the rotations are
    :func:`jaxreg.geometry.lie.rotation_grid_around` the prior's rotation, again about the source
    centroid, keeping the prior's placement of that centroid; sample 0 is the prior.
    """
    src = jnp.asarray(source)
    c_s = _centroid(src)
    if around is None:
        rotations = rotation_grid(n, dtype=src.dtype)
        anchor = _centroid(jnp.asarray(target, src.dtype))
    else:
        if max_angle is None:
            raise ValueError("rotation_inits(around=...) needs max_angle (radians)")
        rotations = rotation_grid_around(around.rotation(), n, max_angle)
        anchor = around @ c_s
    translations = anchor - rotations.apply(c_s)
    return SE3.from_rotation_and_translation(rotations, translations)


def perturbed_inits(
    pose: SE3,
    key: Array,
    n: int,
    *,
    rotation_sigma: float,
    translation_sigma: float,
) -> SE3:
    """``n`` random right perturbations ``pose @ exp(d)`` of a previous pose, batch ``(n,)``:
    ``d = (v, w)`` with ``v ~ N(0, translation_sigma^2 I)`` (metres, source frame) and
    ``w ~ N(0, rotation_sigma^2 I)`` (radians). Sample 0 is ``pose`` itself (tracking)."""
    dtype = pose.wxyz_xyz.dtype
    scale = jnp.array([translation_sigma] * 3 + [rotation_sigma] * 3, dtype)
    delta = jax.random.normal(key, (n, 6), dtype) * scale
    delta = delta.at[0].set(0.0)
    return SE3(pose.wxyz_xyz[None]) @ se3_exp(delta)
