"""Iterative Closest Point: point-to-point and point-to-plane, with rejection, trimming and
robust IRLS kernels; multi-start over a batch of initial poses in one compiled call.

Conventions:

* ``pose`` maps source coordinates into target coordinates (``target ~ pose @ source``);
  ``init`` is a ``jaxlie.SE3`` or a ``(4, 4)`` matrix in the same sense.
* Every iteration moves the source by the current pose, takes each moved point's nearest
  target point, keeps the pairs within the correspondence distance (and, with trimming, the
  best ``trim_fraction`` of them), weights them by the kernel's IRLS weight of the squared
  residual, and solves for an increment applied on the left (in the target frame):

  - point-to-point: weighted Kabsch of the moved source onto its matches (the closed form
    and degeneracy signal of :func:`jaxreg.align.align`); residual ``r = |T p - q|``.
  - point-to-plane: one Gauss-Newton step on the residual ``r = n_q . (T p - q)`` with the
    small-angle linearisation ``exp(d) p ~ p + w x p + v`` about the weighted centroid of
    the moved source, then the exact update ``T <- exp(d) T`` (:func:`jaxreg.lie.se3_exp`:
    jaxlie 1.5's ``SE3.exp`` is inaccurate for small rotations). Tangent order is jaxlie's
    ``(vx, vy, vz, wx, wy, wz)`` (Open3D's twist is ``(w, t)``: see :mod:`jaxreg.lie`).

* ``inlier_rmse`` is the RMS of the full 3D distance over the pairs kept in the last
  correspondence pass (for both methods, like Open3D), and ``inlier_fraction`` is the number
  of source points with a match within the correspondence distance over the number of valid
  source points (Open3D's ``fitness``), counted before trimming so that it stays a quality
  signal when ``trim_fraction`` fixes how many pairs are used.
* Convergence: the increment's translation norm and rotation angle both fall below
  ``tolerance`` (metres, radians), or the inlier RMSE changes by less than
  ``tolerance`` relative to itself while the inlier count is unchanged.

Failure is data: the result's ``status`` (:class:`ICPStatus`) says what went wrong, the
pose is never NaN and never silently reset: when a step cannot be taken the last good pose
is kept and the status says why.

Gradients: the returned pose is differentiable with respect to the source and target
points, target normals, source weights and the kernel scale by the implicit function
theorem at the converged fixed point with correspondences held fixed, not by unrolling
the iterations, and computed only when something differentiates (a custom JVP rule,
:func:`_converged_jvp`).

Nearest neighbours come from a :class:`jaxreg.neighbors.NeighborGrid` built once per target
on the host (pass ``neighbors=`` to reuse one across calls). When the target is traced (under
``jit`` or ``grad`` with respect to the target) exact blocked brute force is used instead.
"""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3, SO3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.align import _fit
from jaxreg.kernels import L2, AbstractRobustKernel, trim_mask
from jaxreg.lie import rotation_grid, rotation_grid_around, se3_exp, se3_from_matrix
from jaxreg.neighbors import NeighborGrid, build_grid, knn, query_nearest

__all__ = [
    "ICPStatus",
    "RegistrationResult",
    "icp",
    "multistart_icp",
    "pca_inits",
    "perturbed_inits",
    "rotation_inits",
    "select_best",
]

Method = Literal["point_to_point", "point_to_plane"]


class ICPStatus(eqx.Enumeration):
    """Why ICP stopped; each member's value is the message a user needs."""

    success = "converged: the update fell below tolerance"
    max_iterations = (
        "reached max_iterations before the update fell below tolerance: raise max_iterations "
        "or start closer"
    )
    too_few_correspondences = (
        "fewer than 3 correspondences within max_correspondence_distance: the start may be "
        "far outside the target, a cloud may be empty or all-NaN, or the distance too small"
    )
    degenerate = (
        "degenerate geometry: the correspondences do not constrain all 6 degrees of freedom "
        "(collinear points; a plane or cylinder for point-to-plane); the pose is not unique"
    )
    non_finite = "a non-finite update (NaN or inf in the inputs?): the last finite pose is kept"


class RegistrationResult(eqx.Module):
    """Result of :func:`icp`; :func:`multistart_icp` adds a leading start axis to every leaf.

    Attributes:
        pose: ``SE3`` source -> target.
        inlier_rmse: ``()`` RMS 3D distance of the kept pairs at the final pose (metres).
        inlier_fraction: ``()`` valid source points with a match within the correspondence
            distance at the final pose, over all valid source points (before trimming).
        num_inliers: ``()`` pairs kept (after rejection and trimming) at the final pose.
        iterations: ``()`` increments taken.
        converged: ``()`` the tolerance test passed.
        status: :class:`ICPStatus` member.
        rmse_history: ``(max_iterations,)`` inlier RMSE before each increment; NaN after the
            last iteration.
        correspondences: ``(N,)`` index of each source point's target match at the final
            pose, ``M`` (one past the last target row) when it has none.
        weights: ``(N,)`` final IRLS weight of each pair, 0 for rejected pairs.
    """

    pose: SE3
    inlier_rmse: Float[Array, ""]
    inlier_fraction: Float[Array, ""]
    num_inliers: Int[Array, ""]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]
    status: ICPStatus
    rmse_history: Float[Array, " max_iterations"]
    correspondences: Int[Array, " N"]
    weights: Float[Array, " N"]

    def status_message(self) -> str | np.ndarray:
        """The status as text, on the host: a string, or an array of strings for a batch."""
        codes = np.asarray(self.status._value)
        messages = np.asarray(ICPStatus._index_to_message, dtype=object)
        return str(messages[codes]) if codes.ndim == 0 else messages[codes]


class _Problem(eqx.Module):
    """The data of one registration (unbatched arrays)."""

    source: Float[Array, "N 3"]
    source_weights: Float[Array, " N"]
    target: Float[Array, "M 3"]
    target_valid: Bool[Array, " M"]  # False for NaN input and padding rows
    target_normals: Float[Array, "M 3"] | None
    grid: NeighborGrid | None


class _Options(eqx.Module):
    method: str = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    distances: Float[Array, " max_iterations"]
    tolerance: Float[Array, ""]
    kernel: AbstractRobustKernel
    trim_fraction: Float[Array, ""] | None


class _Pairs(eqx.Module):
    index: Int[Array, " N"]
    weight: Float[Array, " N"]
    kept: Bool[Array, " N"]
    count: Int[Array, ""]
    rmse: Float[Array, ""]
    fraction: Float[Array, ""]


def _apply(pose: SE3, points: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
    """``pose @ points`` in the loop: three broadcast multiply-adds with the rotation
    matrix's columns, which XLA fuses into their consumers (the neighbour query, the Kabsch
    sums). On XLA's CPU backend ``points @ R.T`` is a separate kernel ~20x slower than that,
    and jaxlie's quaternion ``apply`` batched over poses is slower still. Differentiated
    code uses the matmul instead (see :func:`_objective`)."""
    r = pose.rotation().as_matrix()
    rotated = points[:, :1] * r[:, 0] + points[:, 1:2] * r[:, 1] + points[:, 2:] * r[:, 2]
    return rotated + pose.translation()


def _fill_gather(values: Array, index: Array) -> Array:
    """``values[index]`` with out-of-range (sentinel) rows read as zeros, never a real row."""
    return values.at[index].get(mode="fill", fill_value=0.0)


def _dot3(a: Float[Array, "N 3"], b: Float[Array, "N 3"]) -> Float[Array, " N"]:
    """Row-wise dot product, written out: XLA's CPU backend runs a sum over a minor axis of
    length 3 as a separate kernel ~10x slower than the products it would fuse with."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _residual_sq(problem: _Problem, moved: Array, index: Array, method: str) -> Array:
    """Squared residual of each pair: 3D distance or distance along the target normal."""
    diff = moved - _fill_gather(problem.target, index)
    if method == "point_to_plane":
        r = _dot3(_fill_gather(problem.target_normals, index), diff)
        return r * r
    return _dot3(diff, diff)


def _match(problem: _Problem, moved: Float[Array, "N 3"], distance: Array) -> Int[Array, " N"]:
    """Index of the nearest target point of each moved source point within ``distance``;
    a row that is not a valid target point (padding, or one past the last row) when none.

    Only the index is used: the squared distance and the found flag are recomputed from it
    (:func:`_pairs`), so the query's candidate scan has a single consumer."""
    if problem.grid is not None:
        return query_nearest(problem.grid, moved, distance)[0]
    index, _, _ = knn(moved, problem.target, 1, max_distance=distance, mask=problem.target_valid)
    return index[:, 0]


def _correspond(problem: _Problem, opts: _Options, pose: SE3, distance: Array) -> _Pairs:
    """Nearest-neighbour pairs of the source moved by ``pose``, rejected and weighted."""
    moved = _apply(pose, problem.source)
    return _pairs(problem, opts, moved, _match(problem, moved, distance))


def _pairs(problem: _Problem, opts: _Options, moved: Array, index: Array) -> _Pairs:
    """Rejection, trimming and IRLS weights of the pairs ``(moved[i], target[index[i]])``,
    with ``index`` from :func:`_match`."""
    found = problem.target_valid.at[index].get(mode="fill", fill_value=False)
    usable = problem.source_weights > 0
    kept = found & usable
    d2 = _residual_sq(problem, moved, index, "point_to_point")
    s = d2 if opts.method == "point_to_point" else _residual_sq(problem, moved, index, opts.method)
    if opts.trim_fraction is not None:
        kept = trim_mask(s, opts.trim_fraction, kept)
    s_safe = jnp.where(kept, s, 0.0)
    weight = jnp.where(kept, problem.source_weights * opts.kernel.weight(s_safe), 0.0)
    count = jnp.sum(kept, dtype=jnp.int32)
    d2_kept = jnp.where(kept, d2, 0.0)
    mean_sq = jnp.sum(d2_kept) / jnp.maximum(count, 1)
    rmse = jnp.where(count > 0, jnp.sqrt(jnp.where(count > 0, mean_sq, 1.0)), jnp.inf)
    within = jnp.sum(found & usable, dtype=jnp.int32)
    fraction = within / jnp.maximum(jnp.sum(usable), 1)
    return _Pairs(index, weight, kept, count, rmse, fraction)


def _plane_step(problem: _Problem, moved: Array, pairs: _Pairs) -> tuple[SE3, Array]:
    """Gauss-Newton increment (left, target frame) for point-to-plane; and a degeneracy flag."""
    w = pairs.weight
    q = _fill_gather(problem.target, pairs.index)
    n = _fill_gather(problem.target_normals, pairs.index)
    centroid = jnp.sum(w[:, None] * moved, 0) / jnp.maximum(jnp.sum(w), 1e-30)
    p = jnp.where(pairs.kept[:, None], moved - centroid, 0.0)
    radius = jnp.sqrt(jnp.sum(w * _dot3(p, p)) / jnp.maximum(jnp.sum(w), 1e-30))
    radius = jnp.where(radius > 0, radius, 1.0)
    # Rotation columns scaled by the cloud radius so both blocks share units (conditioning).
    jac = jnp.concatenate([n, jnp.cross(p, n) / radius], axis=-1)
    r = _dot3(n, moved - q)
    a = jnp.einsum("n,ni,nj->ij", w, jac, jac)
    b = -jnp.einsum("n,ni,n->i", w, jac, r)
    delta, degenerate = _pinv_solve(a, b)
    delta = delta.at[3:].divide(radius)
    to_centroid = SE3.from_translation(centroid)
    return to_centroid @ se3_exp(delta) @ to_centroid.inverse(), degenerate


def _pinv_solve(a: Float[Array, "6 6"], b: Float[Array, " 6"]) -> tuple[Array, Array]:
    """Minimum-norm solution of the symmetric PSD system ``a x = b``; flags rank loss."""
    lam, vec = jnp.linalg.eigh(a)
    rel = 1e-6 if a.dtype == jnp.float64 else 1e-5
    ok = lam > rel * jnp.maximum(lam[-1], 1e-30)
    inv = jnp.where(ok, 1.0 / jnp.where(ok, lam, 1.0), 0.0)
    return vec @ (inv * (vec.T @ b)), ~jnp.all(ok)


def _increment(problem: _Problem, opts: _Options, moved: Array, pairs: _Pairs):
    """Increment (left, target frame) from the ``pairs`` of the ``moved`` source; and
    :func:`jaxreg.align.align`'s degeneracy flag (point-to-point) or rank loss (plane)."""
    if opts.method == "point_to_plane":
        return _plane_step(problem, moved, pairs)
    # align()'s closed form without its input checks: the weighted rows are finite by
    # construction, and _fit ignores the others (unmatched, or matched to target padding).
    fit = _fit(moved, _fill_gather(problem.target, pairs.index), pairs.weight)
    translation = fit.mu_dst - fit.rotation @ fit.mu_src
    return SE3.from_rotation_and_translation(fit.rotation, translation), fit.degenerate


def _run(problem: _Problem, opts: _Options, init: SE3) -> RegistrationResult:
    """The ICP loop for one start (unbatched; vmap for many).

    Each trip of the loop weighs the pairs of the current pose, then either finishes (the
    previous increment passed the tolerance test, the iteration bound is reached, or there
    are too few pairs) or takes one increment; it ends by matching the source at the pose it
    leaves. The first trip only matches the initial pose, so the matching code appears once
    in the compiled graph, and the last leaves the match of the final pose.

    The match crosses the trip boundary as loop state, which XLA materialises. Consumed
    within the trip, its candidate scan would be fused into each consumer and repeated
    (several times over under ``vmap``); ``optimization_barrier`` does not prevent that, as
    XLA removes it before fusion.
    """
    dtype = problem.source.dtype
    tol = opts.tolerance.astype(dtype)

    # Derivatives come from _implicit_pose; nothing is differentiated through the loop.
    frozen, fopts = jax.lax.stop_gradient((problem, opts))

    def body(state):
        pose, it, primed = state["pose"], state["iteration"], state["primed"]
        # Before the first match (primed False) the pairs are empty: that trip only matches.
        moved = _apply(pose, frozen.source)
        pairs = _pairs(frozen, fopts, moved, state["match"])
        too_few = primed & (pairs.count < 3)
        flat_rmse = (jnp.abs(state["rmse"] - pairs.rmse) < tol * pairs.rmse) & (
            pairs.count == state["count"]
        )
        converged = state["small_step"] | flat_rmse
        finish = converged | too_few | (it >= opts.max_iterations)
        inc, degenerate = _increment(frozen, fopts, moved, pairs)
        new_pose = inc @ pose
        finite = jnp.all(jnp.isfinite(new_pose.wxyz_xyz))
        step = primed & ~finish
        take = step & finite
        status = ICPStatus.where(too_few, ICPStatus.too_few_correspondences, state["status"])
        status = ICPStatus.where(step & ~finite, ICPStatus.non_finite, status)
        step_t = jnp.linalg.norm(inc.translation())
        step_r = jnp.linalg.norm(inc.rotation().log())
        next_pose = jax.tree.map(lambda a, b: jnp.where(take, a, b), new_pose, pose)
        next_it = it + take.astype(it.dtype)
        distance = fopts.distances[jnp.minimum(next_it, opts.max_iterations - 1)]
        return dict(
            pose=next_pose,
            iteration=next_it,
            primed=jnp.array(True),
            match=_match(frozen, _apply(next_pose, frozen.source), distance),
            finished=primed & ~take,
            small_step=take & (step_t < tol) & (step_r < tol),
            converged=converged & ~too_few,
            degenerate=jnp.where(take, degenerate, state["degenerate"]),
            rmse=pairs.rmse,
            count=pairs.count,
            status=status,
            history=state["history"].at[it].set(jnp.where(take, pairs.rmse, jnp.nan)),
        )

    state = dict(
        pose=init,
        iteration=jnp.array(0, jnp.int32),
        primed=jnp.array(False),  # the first trip only matches the initial pose
        match=jnp.full(problem.source.shape[:1], problem.target.shape[0], jnp.int32),
        finished=jnp.array(False),
        small_step=jnp.array(False),
        converged=jnp.array(False),
        degenerate=jnp.array(False),
        rmse=jnp.array(jnp.inf, dtype),
        count=jnp.array(-1, jnp.int32),
        status=ICPStatus.success,
        history=jnp.full((opts.max_iterations,), jnp.nan, dtype),
    )
    state = jax.lax.while_loop(lambda st: ~st["finished"], body, jax.lax.stop_gradient(state))
    # The last trip took no step and re-matched the final pose: form its pairs once more
    # rather than carry (N,) arrays through every trip.
    pairs = _pairs(frozen, fopts, _apply(state["pose"], frozen.source), state["match"])
    status = state["status"]
    ok = status == ICPStatus.success
    status = ICPStatus.where(ok & state["degenerate"], ICPStatus.degenerate, status)
    ok = status == ICPStatus.success
    status = ICPStatus.where(ok & ~state["converged"], ICPStatus.max_iterations, status)
    return RegistrationResult(
        pose=_implicit_pose(problem, opts, state["pose"], pairs),
        inlier_rmse=pairs.rmse,
        inlier_fraction=pairs.fraction,
        num_inliers=pairs.count,
        iterations=state["iteration"],
        converged=state["converged"],
        status=status,
        rmse_history=state["history"],
        correspondences=pairs.index,
        weights=pairs.weight,
    )


def _chart(delta: Float[Array, " 6"]) -> SE3:
    """A cheap smooth chart of SE(3) at the identity that agrees with ``SE3.exp`` to first
    order: rotation from the unnormalised quaternion ``(1, w/2)``, translation ``v``."""
    q = jnp.concatenate([jnp.ones_like(delta[:1]), delta[3:] / 2])
    rotation = SO3(q / jnp.linalg.norm(q))
    return SE3.from_rotation_and_translation(rotation, delta[:3])


def _objective(problem: _Problem, opts: _Options, pose: SE3, pairs: _Pairs) -> Array:
    """Robust ICP objective with the correspondences (and the kept set) frozen."""
    # A matmul, unlike _apply: its derivatives are matmuls too, where those of _apply's
    # broadcasts are reductions that make the implicit-function Hessian ~5x slower.
    moved = problem.source @ pose.rotation().as_matrix().T + pose.translation()
    s = _residual_sq(problem, moved, pairs.index, opts.method)
    rho = opts.kernel.rho(jnp.where(pairs.kept, s, 0.0))
    return jnp.sum(jnp.where(pairs.kept, problem.source_weights * rho, 0.0))


def _implicit_pose(problem: _Problem, opts: _Options, pose: SE3, pairs: _Pairs) -> SE3:
    """The converged ``pose``, carrying implicit-function-theorem derivatives with respect to
    the problem's data and the options (see :func:`_converged`); its value is ``pose``."""
    params = jax.lax.stop_gradient(pose.wxyz_xyz)
    return SE3(_converged(problem, opts, params=params, pairs=jax.lax.stop_gradient(pairs)))


@eqx.filter_custom_jvp
def _converged(problem: _Problem, opts: _Options, *, params: Array, pairs: _Pairs) -> Array:
    """``params`` (the converged pose's ``wxyz_xyz``) unchanged; differentiable in ``problem``
    and ``opts`` through the rule below, so the forward pass pays nothing for derivatives."""
    return params


@_converged.def_jvp
def _converged_jvp(primals, tangents, *, params, pairs):
    """Implicit-function-theorem tangent of the converged pose.

    At the fixed point the gradient ``g(theta)`` of the frozen-correspondence objective in a
    right perturbation ``pose @ chart(d)`` vanishes, so ``d theta -> -H^-1 dg/dtheta`` is the
    derivative of the solution. ``H`` is held constant (its own derivative multiplies
    ``g = 0``), and any chart that agrees with ``exp`` to first order gives the same ``H``
    at a stationary point. Rank-deficient ``H`` (degenerate geometry) gets the minimum-norm
    derivative.
    """
    pose = SE3(params)
    zero = jnp.zeros(6, params.dtype)
    diff, static = eqx.partition(primals, eqx.is_inexact_array)
    # Symbolic-zero (None) tangents of differentiable leaves become explicit zeros.
    t_diff = jax.tree.map(
        lambda p, t: None if p is None else (jnp.zeros_like(p) if t is None else t),
        diff,
        tangents,
        is_leaf=lambda x: x is None,
    )

    def objective(delta, data):
        problem, opts = eqx.combine(data, static)
        return _objective(problem, opts, pose @ _chart(delta), pairs)

    _, d_grad = jax.jvp(lambda data: jax.grad(objective)(zero, data), (diff,), (t_diff,))
    hess = jax.hessian(objective)(zero, diff)
    step, _ = _pinv_solve(hess, -d_grad)
    _, d_params = jax.jvp(lambda d: (pose @ _chart(d)).wxyz_xyz, (zero,), (step,))
    return params, d_params


def _as_pose(init, dtype) -> SE3:
    """``init`` (``None`` for the identity, an ``SE3``, or ``(..., 4, 4)``) as an ``SE3``."""
    if init is None:
        return SE3(jnp.array([1, 0, 0, 0, 0, 0, 0], dtype))
    if isinstance(init, SE3):
        return SE3(jnp.asarray(init.wxyz_xyz, dtype))
    m = jnp.asarray(init, dtype)
    if m.shape[-2:] != (4, 4):
        raise ValueError(f"init must be a jaxlie.SE3 or a (..., 4, 4) matrix, got shape {m.shape}")
    return se3_from_matrix(m)


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _prepare(
    source,
    target,
    *,
    method,
    target_normals,
    source_weights,
    max_correspondence_distance,
    max_iterations,
    tolerance,
    kernel,
    trim_fraction,
    neighbors,
    grid_capacity=None,
) -> tuple[_Problem, _Options, tuple[int, int]]:
    """Host-side checks and set-up shared by :func:`icp` and :func:`multistart_icp`.

    Returns the problem (clouds padded to bucketed sizes), the options, and the caller's
    ``(N, M)``. ``grid_capacity`` asks for shorter candidate lists (cheaper queries, slower
    build), falling back to the default when a leaf cannot fit them."""
    if method not in ("point_to_point", "point_to_plane"):
        raise ValueError(f"method must be 'point_to_point' or 'point_to_plane', got {method!r}")
    source = jnp.asarray(source)
    dtype = jnp.result_type(source.dtype, float)
    source = source.astype(dtype)
    target = jnp.asarray(target, dtype)
    for name, cloud in (("source", source), ("target", target)):
        if cloud.ndim != 2 or cloud.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (N, 3), got {cloud.shape}")
        if cloud.shape[0] == 0:
            raise ValueError(f"{name} is empty: ICP needs points in both clouds")
    n = source.shape[0]
    if n < 3:
        raise ValueError(f"ICP needs at least 3 source points, got {n}")
    if method == "point_to_plane":
        if target_normals is None:
            raise ValueError(
                "point_to_plane needs target_normals (M, 3): see jaxreg.estimate_normals"
            )
        target_normals = jnp.asarray(target_normals, dtype)
        if target_normals.shape != target.shape:
            raise ValueError(
                f"target_normals must match target {target.shape}, got {target_normals.shape}"
            )
    else:
        target_normals = None
    if source_weights is None:
        source_weights = jnp.ones(n, dtype)
    source_weights = jnp.asarray(source_weights, dtype)
    if source_weights.shape != (n,):
        raise ValueError(f"source_weights must have shape ({n},), got {source_weights.shape}")
    m = target.shape[0]
    source, source_weights, target, target_ok, target_normals = _clean(
        source, source_weights, target, target_normals, _bucket(n) - n, _bucket(m) - m
    )

    distances = jnp.asarray(max_correspondence_distance, dtype)
    if distances.ndim == 0:
        distances = jnp.full((max_iterations,), distances, dtype)
    elif distances.shape != (max_iterations,):
        raise ValueError(
            "max_correspondence_distance is a scalar or a schedule with one distance per "
            f"iteration: shape ({max_iterations},), got {distances.shape}"
        )
    if neighbors is None and _is_concrete(target) and _is_concrete(distances):
        points, ok = np.asarray(target), np.asarray(target_ok)
        if ok.any():  # else nothing to index: every query is invalid
            radius = float(np.max(np.asarray(distances)))
            neighbors = build_grid(points, radius, mask=ok, capacity=grid_capacity)
            if grid_capacity is not None and bool(neighbors.overflow):
                neighbors = build_grid(points, radius, mask=ok)
    problem = _Problem(source, source_weights, target, target_ok, target_normals, neighbors)
    opts = _Options(
        method=method,
        max_iterations=int(max_iterations),
        distances=distances,
        tolerance=jnp.asarray(tolerance, dtype),
        kernel=L2() if kernel is None else kernel,
        trim_fraction=None if trim_fraction is None else jnp.asarray(trim_fraction, dtype),
    )
    return problem, opts, (n, m)


@eqx.filter_jit
def _clean(source, source_weights, target, target_normals, n_pad: int, m_pad: int):
    """Masks non-finite rows and pads both clouds to bucketed sizes, in one compiled call.

    NaN rows (depth holes) take no part and the arithmetic never sees them: a source row
    gets weight 0 and coordinates 0; a target row (or one with a non-finite normal) is moved
    far away and marked invalid. Padding rows are zero-weight source rows and far, invalid
    target rows, so clouds of similar size share one compiled loop. Returns the source, its
    weights, the target, its validity mask and its normals (``None`` stays ``None``).
    """
    dtype = source.dtype
    source_ok = jnp.all(jnp.isfinite(source), -1)
    source_weights = jnp.where(source_ok, source_weights, 0.0)
    source = jnp.where(source_ok[:, None], source, 0.0)
    target_ok = jnp.all(jnp.isfinite(target), -1)
    if target_normals is not None:
        target_ok &= jnp.all(jnp.isfinite(target_normals), -1)
        target_normals = jnp.where(target_ok[:, None], target_normals, 0.0)
        target_normals = jnp.pad(target_normals, ((0, m_pad), (0, 0)))
    far = jnp.asarray(jnp.finfo(dtype).max / 4, dtype)  # never within any distance
    target = jnp.where(target_ok[:, None], target, far)
    return (
        jnp.pad(source, ((0, n_pad), (0, 0))),
        jnp.pad(source_weights, (0, n_pad)),
        jnp.pad(target, ((0, m_pad), (0, 0)), constant_values=far),
        jnp.pad(target_ok, (0, m_pad)),
        target_normals,
    )


def _bucket(rows: int) -> int:
    """``rows`` rounded up to a multiple of a quarter of its leading power of two (at most
    25% padding, and at least 32 rows)."""
    if rows <= 32:
        return 32
    step = 1 << (rows.bit_length() - 3)
    return -(-rows // step) * step


def _unpad(result: RegistrationResult, n: int, m: int) -> RegistrationResult:
    """Drops the padding rows of :func:`_prepare` from a (possibly batched) result; the
    no-match sentinel becomes ``m``, the caller's target size."""
    index = result.correspondences[..., :n]
    return eqx.tree_at(
        lambda r: (r.correspondences, r.weights),
        result,
        (jnp.where(index >= m, m, index), result.weights[..., :n]),
    )


_run_jit = eqx.filter_jit(_run)


@eqx.filter_jit
def _run_many(problem: _Problem, opts: _Options, inits: SE3) -> RegistrationResult:
    return jax.vmap(_run, in_axes=(None, None, 0))(problem, opts, inits)


def icp(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    init: SE3 | Float[ArrayLike, "4 4"] | None = None,
    *,
    method: Method = "point_to_point",
    target_normals: Float[ArrayLike, "M 3"] | None = None,
    max_correspondence_distance: Float[ArrayLike, ""] | Float[ArrayLike, " I"] = 0.02,
    max_iterations: int = 40,
    tolerance: float = 1e-6,
    kernel: AbstractRobustKernel | None = None,
    trim_fraction: float | None = None,
    source_weights: Float[ArrayLike, " N"] | None = None,
    neighbors: NeighborGrid | None = None,
) -> RegistrationResult:
    """Register ``source`` to ``target`` by ICP from ``init``.

    Args:
        source: ``(N, 3)`` model / source points (NaN rows are ignored).
        target: ``(M, 3)`` scene / target points (NaN rows are ignored).
        init: initial source -> target pose, ``SE3`` or ``(4, 4)``; identity by default.
        method: ``"point_to_point"`` or ``"point_to_plane"`` (needs ``target_normals``).
        target_normals: ``(M, 3)`` unit normals of the target.
        max_correspondence_distance: pairs farther apart (metres) are rejected. A scalar, or a
            schedule ``(max_iterations,)`` giving the distance at each iteration (start wide,
            tighten).
        max_iterations: iteration bound (static: it sizes ``rmse_history``).
        tolerance: convergence threshold on the increment (metres and radians) and on the
            relative change of the inlier RMSE.
        kernel: robust kernel from :mod:`jaxreg.kernels` for IRLS; least squares by default.
        trim_fraction: keep only this best fraction of the accepted pairs each iteration
            (trimmed ICP); match it to the expected overlap.
        source_weights: ``(N,)`` non-negative per-point weights; 0 marks padding.
        neighbors: a prebuilt :class:`~jaxreg.neighbors.NeighborGrid` of ``target`` whose
            ``max_distance`` covers the largest correspondence distance.

    Returns:
        :class:`RegistrationResult`.
    """
    problem, opts, (n, m) = _prepare(
        source,
        target,
        method=method,
        target_normals=target_normals,
        source_weights=source_weights,
        max_correspondence_distance=max_correspondence_distance,
        max_iterations=max_iterations,
        tolerance=tolerance,
        kernel=kernel,
        trim_fraction=trim_fraction,
        neighbors=neighbors,
    )
    result = _run_jit(problem, opts, _as_pose(init, problem.source.dtype))
    return _unpad(result, n, m)


def multistart_icp(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    inits: SE3 | Float[ArrayLike, "S 4 4"],
    **options,
) -> RegistrationResult:
    """ICP from every pose in ``inits`` in one compiled call.

    ``inits`` has one batch axis ``(S,)`` (an ``SE3`` batch or ``(S, 4, 4)``); every leaf of
    the result gains a leading axis ``S``. Each start has its own status; one failed start
    never fails the batch. The neighbour structure is built once and shared. With more than
    one device in ``jax.devices()`` the starts are sharded over them (the problem is
    replicated). Options are those of :func:`icp`. Use :func:`select_best` to pick a start.
    """
    # Many starts query the grid many times: shorter candidate lists pay for a longer build.
    problem, opts, (n, m) = _prepare(source, target, **_icp_options(options), grid_capacity=24)
    dtype = problem.source.dtype
    starts = _as_pose(inits, dtype)
    if len(starts.get_batch_axes()) != 1:
        raise ValueError(
            f"inits must have exactly one batch axis (S,), got {starts.get_batch_axes()}"
        )
    count = starts.wxyz_xyz.shape[0]
    results = _run_many(problem, opts, _shard_starts(starts))
    if results.pose.wxyz_xyz.shape[0] != count:
        results = jax.tree.map(lambda leaf: leaf[:count], results)
    return _unpad(results, n, m)


def _shard_starts(starts: SE3) -> SE3:
    """Splits the start axis over ``jax.devices()`` when there is more than one device,
    padding it (with copies of the last start) to a multiple of the device count."""
    devices = jax.devices()
    if len(devices) < 2:
        return starts
    params = starts.wxyz_xyz
    pad = -params.shape[0] % len(devices)
    params = jnp.concatenate([params, jnp.repeat(params[-1:], pad, axis=0)])
    mesh = jax.sharding.Mesh(np.array(devices), ("starts",))
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("starts"))
    return SE3(jax.device_put(params, spec))


def _icp_options(options: dict) -> dict:
    defaults = dict(
        method="point_to_point",
        target_normals=None,
        source_weights=None,
        max_correspondence_distance=0.02,
        max_iterations=40,
        tolerance=1e-6,
        kernel=None,
        trim_fraction=None,
        neighbors=None,
    )
    unknown = set(options) - set(defaults)
    if unknown:
        raise TypeError(f"unknown ICP options: {sorted(unknown)}")
    return defaults | options


def select_best(results: RegistrationResult) -> Int[Array, ""]:
    """Index of the best start: highest inlier fraction, then lowest inlier RMSE.

    Starts whose status is a failure (too few correspondences, non-finite) never win while
    another start succeeded or stopped at the iteration bound.
    """
    usable = (results.status != ICPStatus.too_few_correspondences) & (
        results.status != ICPStatus.non_finite
    )
    frac = jnp.where(usable, results.inlier_fraction, -1.0)
    rmse = jnp.where(usable, results.inlier_rmse, jnp.inf)
    order = jnp.lexsort((rmse, -frac))
    return order[0]


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

    Without ``around`` the rotations are :func:`jaxreg.lie.rotation_grid` (near-uniform over
    SO(3)) applied about the source centroid, which each start places on the target
    centroid. With ``around`` (a prior pose) and ``max_angle`` (radians) the rotations are
    :func:`jaxreg.lie.rotation_grid_around` the prior's rotation, again about the source
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
