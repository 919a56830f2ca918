"""The ICP solver itself: the problem's data, correspondences, increments, the loop, and the
one objective whose gradient and Hessian both the implicit derivative and
:func:`jaxreg.icp_covariance` use.

Everything here takes a problem already checked, masked and padded by
:func:`jaxreg.registration.solver.prepare` and runs under ``jit`` and ``vmap``; the public entry
points are in :mod:`jaxreg.registration.icp` (the building blocks that the pipeline and the
studies run in :mod:`jaxreg.registration.solver`), whose conventions these are: a pose maps
source into target coordinates, increments are applied on the left (target frame),
perturbations of the solution on the right (source frame), and tangents are
``(vx, vy, vz, wx, wy, wz)``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxlie import SE3, SO3
from jaxtyping import Array, Bool, Float, Int

from jaxreg.core._program_cache import persistent_jit
from jaxreg.core._result import AbstractResult
from jaxreg.geometry.alignment import _fit
from jaxreg.geometry.eigen import jacobi_eigh
from jaxreg.geometry.kernels import AbstractRobustKernel, trim_mask
from jaxreg.geometry.lie import se3_exp
from jaxreg.registration.projective import ProjectiveAssociation, projective_match
from jaxreg.search.neighbors import NeighborGrid, knn, query_nearest


class ICPStatus(eqx.Enumeration):
    """Why ICP stopped; each member's value is the message a user needs."""

    success = "converged: the update fell below tolerance"
    max_iterations = (
        "reached max_iterations before the update fell below tolerance: raise max_iterations "
        "or start closer"
    )
    too_few_correspondences = (
        "fewer than 3 correspondences within max_correspondence_distance: the start may be "
        "far outside the target, a cloud may be empty or all-NaN (for point-to-plane: the "
        "target may lack finite unit normals), or the distance too small"
    )
    too_few_weighted_pairs = (
        "fewer than 3 correspondences have a positive weight: the robust kernel gave the "
        "others zero weight; its scale may be too small for the residuals, or the start too "
        "far from the solution"
    )
    degenerate = (
        "degenerate geometry: the correspondences do not constrain all 6 degrees of freedom "
        "(collinear points; a plane or cylinder for point-to-plane); the pose is not unique"
    )
    non_finite = "a non-finite update (NaN or inf in the inputs?): the last finite pose is kept"


class RegistrationResult(AbstractResult):
    """Result of :func:`jaxreg.icp`; :func:`jaxreg.multistart_icp` adds a leading start axis
    ``(S,)`` to every leaf, and ``result[i]`` is start ``i``'s result.

    Attributes:
        pose: ``SE3`` source -> target.
        inlier_rmse: ``()`` RMS 3D distance of the kept pairs at the final pose (metres).
        inlier_fraction: ``()`` valid source points with a match within the correspondence
            distance at the final pose, over all valid source points (before trimming). A
            target point is a match only if it is finite and, for point-to-plane, has a
            finite unit normal.
        num_inliers: ``()`` pairs kept (after rejection and trimming) at the final pose.
        iterations: ``()`` increments taken.
        converged: ``()`` the tolerance test passed on a well-posed problem: true exactly
            when ``status`` is ``ICPStatus.success``.
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


class Problem(eqx.Module):
    """The data of one registration as :func:`jaxreg.registration.solver.prepare` leaves it:
    unbatched arrays, unusable rows masked, both clouds padded to bucketed sizes, and the
    target's neighbour grid (``None``: brute force, or the projective ``association``)."""

    source: Float[Array, "N 3"]
    source_weights: Float[Array, " N"]  # 0 for NaN input and padding rows
    target: Float[Array, "M 3"]
    target_valid: Bool[Array, " M"]  # False for NaN input, unusable normals and padding
    target_normals: Float[Array, "M 3"] | None
    grid: NeighborGrid | None
    # the sensor in source coordinates: the rows of viewpoint_rows match only target points
    # whose normal faces it
    viewpoint: Float[Array, " 3"] | None = None
    viewpoint_rows: Bool[Array, " N"] | None = None
    # an organized target's camera: matches by projection, not by the grid
    association: ProjectiveAssociation | None = None


class LoopSettings(eqx.Module):
    """ICP's options as the loop uses them, made from an ``ICPOptions`` by
    :func:`jaxreg.registration.solver.prepare`: the method and the iteration bound are static
    (a new value compiles a new loop); the correspondence distance of every iteration
    ``(max_iterations,)``, the tolerance, the kernel (:class:`~jaxreg.geometry.kernels.L2` for
    least squares) and the trim fraction are arrays (a new value does not recompile)."""

    method: str = eqx.field(static=True)
    max_iterations: int = eqx.field(static=True)
    distances: Float[Array, " max_iterations"]
    tolerance: Float[Array, ""]
    kernel: AbstractRobustKernel
    trim_fraction: Float[Array, ""] | None


class Pairs(eqx.Module):
    """Correspondences of the source at one pose: the target row of each source row, its
    IRLS weight, whether it is kept, and the counts and RMSE that the loop tests."""

    index: Int[Array, " N"]
    weight: Float[Array, " N"]
    kept: Bool[Array, " N"]
    count: Int[Array, ""]  # kept pairs
    weighted: Int[Array, ""]  # kept pairs with a positive weight
    rmse: Float[Array, ""]
    fraction: Float[Array, ""]


def apply_pose(pose: SE3, points: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
    """``pose @ points`` ``(N, 3)`` for one unbatched ``pose`` (vmap for many), as the loop
    computes it: three broadcast multiply-adds with the rotation matrix's columns, which XLA
    fuses into their consumers (the neighbour query, the Kabsch sums). On XLA's CPU backend
    ``points @ R.T`` is a separate kernel ~20x slower than that, and jaxlie's quaternion
    ``apply`` batched over poses is slower still. Differentiated code uses the matmul instead
    (see :func:`objective`)."""
    r = pose.rotation().as_matrix()
    rotated = points[:, :1] * r[:, 0] + points[:, 1:2] * r[:, 1] + points[:, 2:] * r[:, 2]
    return rotated + pose.translation()


def fill_gather(values: Array, index: Array) -> Array:
    """``values[index]`` with out-of-range (sentinel) rows read as zeros, never a real row."""
    return values.at[index].get(mode="fill", fill_value=0.0)


def _dot3(a: Float[Array, "N 3"], b: Float[Array, "N 3"]) -> Float[Array, " N"]:
    """Row-wise dot product, written out: XLA's CPU backend runs a sum over a minor axis of
    length 3 as a separate kernel ~10x slower than the products it would fuse with."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def _residual_sq(problem: Problem, moved: Array, index: Array, method: str) -> Array:
    """Squared residual of each pair: 3D distance or distance along the target normal."""
    diff = moved - fill_gather(problem.target, index)
    if method == "point_to_plane":
        r = _dot3(fill_gather(problem.target_normals, index), diff)
        return r * r
    return _dot3(diff, diff)


def _facing(problem: Problem, pose: SE3) -> Bool[Array, " M"] | None:
    """The valid target points whose normal faces the viewpoint (``problem.viewpoint`` moved
    by ``pose`` into the target frame: ``n . (eye - q) > 0``); ``None`` without a viewpoint."""
    if problem.viewpoint is None:
        return None
    eye = apply_pose(pose, problem.viewpoint[None])
    return problem.target_valid & (_dot3(problem.target_normals, eye - problem.target) > 0)


def _match(problem: Problem, pose: SE3, distance: Array) -> Int[Array, " N"]:
    """Index of the nearest target point of each source point moved by ``pose``, within
    ``distance`` (from a viewpoint's rows: the nearest facing it; with a projective
    association: the nearest in the window around its pixel); a row that is not a valid
    target point (padding, or one past the last row) when none.

    Only the index is used: the squared distance and the found flag are recomputed from it
    (:func:`pairs_at`), so the query's candidate scan has a single consumer."""
    moved = apply_pose(pose, problem.source)
    facing, rows = _facing(problem, pose), problem.viewpoint_rows
    if problem.association is not None:
        return projective_match(
            problem.association, moved, problem.target, problem.target_valid, distance,
            None if facing is None else (rows, facing),
        )  # fmt: skip
    if problem.grid is not None:
        return query_nearest(problem.grid, moved, distance, mask=facing, mask_queries=rows)[0]
    index = knn(moved, problem.target, 1, max_distance=distance, mask=problem.target_valid)[0]
    if facing is None:
        return index[:, 0]
    seen = knn(moved, problem.target, 1, max_distance=distance, mask=facing)[0]
    return jnp.where(rows, seen[:, 0], index[:, 0])


def correspond(problem: Problem, opts: LoopSettings, pose: SE3, distance: Array) -> Pairs:
    """Nearest-neighbour pairs of the source moved by ``pose``, rejected and weighted."""
    moved = apply_pose(pose, problem.source)
    return pairs_at(problem, opts, moved, _match(problem, pose, distance))


def pairs_at(problem: Problem, opts: LoopSettings, moved: Array, index: Array) -> Pairs:
    """Rejection, trimming and IRLS weights of the pairs ``(moved[i], target[index[i]])``,
    with ``index`` from :func:`_match`. A pair with an invalid target row (no match,
    padding, a non-finite point or an unusable normal) is neither kept nor counted."""
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
    weighted = jnp.sum(weight > 0, dtype=jnp.int32)
    return Pairs(index, weight, kept, count, weighted, rmse, fraction)


def _plane_step(problem: Problem, moved: Array, pairs: Pairs) -> tuple[SE3, Array]:
    """Gauss-Newton increment (left, target frame) for point-to-plane; and a degeneracy flag."""
    w = pairs.weight
    q = fill_gather(problem.target, pairs.index)
    n = fill_gather(problem.target_normals, pairs.index)
    centroid = jnp.sum(w[:, None] * moved, 0) / jnp.maximum(jnp.sum(w), 1e-30)
    p = jnp.where(pairs.kept[:, None], moved - centroid, 0.0)
    radius = jnp.sqrt(jnp.sum(w * _dot3(p, p)) / jnp.maximum(jnp.sum(w), 1e-30))
    radius = jnp.where(radius > 0, radius, 1.0)
    # Rotation columns scaled by the cloud radius so both blocks share units (conditioning).
    jac = jnp.concatenate([n, jnp.cross(p, n) / radius], axis=-1)
    r = _dot3(n, moved - q)
    a = jnp.einsum("n,ni,nj->ij", w, jac, jac)
    b = -jnp.einsum("n,ni,n->i", w, jac, r)
    inverse, _, degenerate = pseudo_inverse(a)
    delta = (inverse @ b).at[3:].divide(radius)
    to_centroid = SE3.from_translation(centroid)
    return to_centroid @ se3_exp(delta) @ to_centroid.inverse(), degenerate


def pseudo_inverse(a: Float[Array, "6 6"]) -> tuple[Array, Array, Array]:
    """Pseudo-inverse of the symmetric PSD ``a`` by its eigendecomposition
    (:func:`jaxreg.geometry.eigen.jacobi_eigh`: no LAPACK call in the loop), eigenvalues below
    ``1e-5`` (float32; ``1e-6`` float64) of the largest counted as zero.

    Returns the ``(6, 6)`` pseudo-inverse, the ``(6, 6)`` projector onto the discarded
    (unconstrained) directions, and a flag: some direction was discarded."""
    lam, vec = jacobi_eigh(a)
    rel = 1e-6 if a.dtype == jnp.float64 else 1e-5
    ok = lam > rel * jnp.maximum(lam[-1], jnp.finfo(lam.dtype).tiny)
    inv = jnp.where(ok, 1.0 / jnp.where(ok, lam, 1.0), 0.0)
    null = (vec * jnp.where(ok, 0.0, 1.0)) @ vec.T
    return (vec * inv) @ vec.T, null, ~jnp.all(ok)


def _jacobi_top(a: Float[Array, "4 4"]) -> tuple[Array, Array]:
    eig, vectors = jacobi_eigh(a)
    return eig, vectors[..., -1]


def _horn_step(moved: Array, matched: Array, w: Array) -> tuple[SE3, Array]:
    """Weighted Kabsch of ``moved`` onto ``matched`` and its degeneracy flag: the closed
    form and tests of :func:`jaxreg.geometry.alignment.align` (its ``_fit``), with Horn's quaternion
    eigenproblem solved by :func:`jaxreg.geometry.eigen.jacobi_eigh` rather than LAPACK, whose
    batched CPU kernel deadlocks on several host devices (see :mod:`jaxreg.geometry.eigen`). Rows
    with ``w == 0`` are ignored whatever their values."""
    fit = _fit(moved, matched, w, top_eigen=_jacobi_top)
    translation = fit.mu_dst - fit.rotation @ fit.mu_src
    return SE3.from_rotation_and_translation(fit.rotation, translation), fit.degenerate


def _increment(problem: Problem, opts: LoopSettings, moved: Array, pairs: Pairs):
    """Increment (left, target frame) from the ``pairs`` of the ``moved`` source; and
    :func:`jaxreg.geometry.alignment.align`'s degeneracy flag (point-to-point) or rank loss
    (plane)."""
    if opts.method == "point_to_plane":
        return _plane_step(problem, moved, pairs)
    # The weighted rows are finite by construction; the others (unmatched, or matched to
    # target padding) are ignored.
    return _horn_step(moved, fill_gather(problem.target, pairs.index), pairs.weight)


def run(problem: Problem, opts: LoopSettings, init: SE3) -> RegistrationResult:
    """The ICP loop for one start ``init`` (unbatched; vmap for many) on a prepared
    ``problem``: the result's per-point fields keep the padding rows, which
    :func:`jaxreg.registration.solver.unpad` drops.

    Each trip of the loop weighs the pairs of the current pose, then either finishes (the
    previous increment passed the tolerance test, the iteration bound is reached, or there
    are fewer than 3 kept or weighted pairs) or takes one increment; it ends by matching the
    source at the pose it leaves. The first trip only matches the initial pose, so the
    matching code appears once in the compiled graph, and the last leaves the match of the
    final pose.

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
        moved = apply_pose(pose, frozen.source)
        pairs = pairs_at(frozen, fopts, moved, state["match"])
        too_few = primed & (pairs.count < 3)
        unweighted = primed & ~too_few & (pairs.weighted < 3)
        flat_rmse = (jnp.abs(state["rmse"] - pairs.rmse) < tol * pairs.rmse) & (
            pairs.count == state["count"]
        )
        converged = state["small_step"] | flat_rmse
        finish = converged | too_few | unweighted | (it >= opts.max_iterations)
        inc, degenerate = _increment(frozen, fopts, moved, pairs)
        new_pose = inc @ pose
        finite = jnp.all(jnp.isfinite(new_pose.wxyz_xyz))
        step = primed & ~finish
        take = step & finite
        status = ICPStatus.where(too_few, ICPStatus.too_few_correspondences, state["status"])
        status = ICPStatus.where(unweighted, ICPStatus.too_few_weighted_pairs, status)
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
            match=_match(frozen, next_pose, distance),
            finished=primed & ~take,
            small_step=take & (step_t < tol) & (step_r < tol),
            converged=converged,
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
    # rather than carry (N,) arrays through every trip. A status set in the loop (too few
    # pairs, non-finite) stands; else degenerate geometry, else the iteration bound.
    pairs = pairs_at(frozen, fopts, apply_pose(state["pose"], frozen.source), state["match"])
    status = state["status"]
    clean = status == ICPStatus.success
    status = ICPStatus.where(clean & state["degenerate"], ICPStatus.degenerate, status)
    clean = status == ICPStatus.success
    status = ICPStatus.where(clean & ~state["converged"], ICPStatus.max_iterations, status)
    return RegistrationResult(
        pose=_implicit_pose(problem, opts, state["pose"], pairs),
        inlier_rmse=pairs.rmse,
        inlier_fraction=pairs.fraction,
        num_inliers=pairs.count,
        iterations=state["iteration"],
        converged=status == ICPStatus.success,
        status=status,
        rmse_history=state["history"],
        correspondences=pairs.index,
        weights=pairs.weight,
    )


# Compiled calls whose programs a fresh process loads from jaxreg.enable_compilation_cache's
# folder, when the caller has enabled it (jaxreg.core._program_cache).
run_one = persistent_jit(run)


@persistent_jit
def run_many(problem: Problem, opts: LoopSettings, inits: SE3) -> RegistrationResult:
    """:func:`run` from every start of the batch ``inits`` ``(S,)``, in one compiled call."""
    return jax.vmap(run, in_axes=(None, None, 0))(problem, opts, inits)


# --------------------------------------------------------------------------------------------
# The objective at the solution, its derivatives in the pose, and the implicit derivative.


def _chart(delta: Float[Array, " 6"]) -> SE3:
    """A cheap smooth chart of SE(3) at the identity that agrees with ``SE3.exp`` to first
    order: rotation from the unnormalised quaternion ``(1, w/2)``, translation ``v``."""
    q = jnp.concatenate([jnp.ones_like(delta[:1]), delta[3:] / 2])
    rotation = SO3(q / jnp.linalg.norm(q))
    return SE3.from_rotation_and_translation(rotation, delta[:3])


def objective(problem: Problem, opts: LoopSettings, pose: SE3, pairs: Pairs) -> Float[Array, ""]:
    """Robust ICP objective ``sum_i w_i rho(r_i^2)`` with the correspondences (and the kept
    set) frozen; differentiable in the problem's data, the kernel and ``pose``."""
    # A matmul, unlike apply_pose: its derivatives are matmuls too, where those of apply_pose's
    # broadcasts are reductions that make the implicit-function Hessian ~5x slower.
    moved = problem.source @ pose.rotation().as_matrix().T + pose.translation()
    s = _residual_sq(problem, moved, pairs.index, opts.method)
    rho = opts.kernel.rho(jnp.where(pairs.kept, s, 0.0))
    return jnp.sum(jnp.where(pairs.kept, problem.source_weights * rho, 0.0))


def _perturbed(
    delta: Array, problem: Problem, opts: LoopSettings, pose: SE3, pairs: Pairs
) -> Array:
    """:func:`objective` at the right perturbation ``pose @ chart(delta)``."""
    return objective(problem, opts, pose @ _chart(delta), pairs)


def pose_gradient(
    problem: Problem, opts: LoopSettings, pose: SE3, pairs: Pairs
) -> Float[Array, " 6"]:
    """``dF/d delta`` at ``delta = 0`` for the right perturbation ``pose @ exp(delta)``,
    ``(vx, vy, vz, wx, wy, wz)``: zero at a converged pose; differentiable in the data."""
    zero = jnp.zeros(6, pose.wxyz_xyz.dtype)
    return jax.grad(_perturbed)(zero, problem, opts, pose, pairs)


def pose_hessian(
    problem: Problem, opts: LoopSettings, pose: SE3, pairs: Pairs
) -> Float[Array, "6 6"]:
    """``d^2F/d delta^2`` at ``delta = 0`` (same perturbation and order as
    :func:`pose_gradient`). At a stationary point any chart that agrees with ``exp`` to first
    order gives the same Hessian."""
    zero = jnp.zeros(6, pose.wxyz_xyz.dtype)
    return jax.hessian(_perturbed)(zero, problem, opts, pose, pairs)


def _implicit_pose(problem: Problem, opts: LoopSettings, pose: SE3, pairs: Pairs) -> SE3:
    """The converged ``pose``, carrying implicit-function-theorem derivatives with respect to
    the problem's data and the options (see :func:`_converged`); its value is ``pose``."""
    params = jax.lax.stop_gradient(pose.wxyz_xyz)
    return SE3(_converged(problem, opts, params=params, pairs=jax.lax.stop_gradient(pairs)))


@eqx.filter_custom_jvp
def _converged(problem: Problem, opts: LoopSettings, *, params: Array, pairs: Pairs) -> Array:
    """``params`` (the converged pose's ``wxyz_xyz``) unchanged; differentiable in ``problem``
    and ``opts`` through the rule below, so the forward pass pays nothing for derivatives."""
    return params


@_converged.def_jvp
def _converged_jvp(primals, tangents, *, params, pairs):
    """Implicit-function-theorem tangent of the converged pose.

    At the fixed point the gradient ``g(theta)`` (:func:`pose_gradient`) of the
    frozen-correspondence objective vanishes, so ``d theta -> -H^-1 dg/dtheta`` is the
    derivative of the solution, with ``H`` from :func:`pose_hessian` held constant (its own
    derivative multiplies ``g = 0``). Rank-deficient ``H`` (degenerate geometry) gets the
    minimum-norm derivative.
    """
    pose = SE3(params)
    diff, static = eqx.partition(primals, eqx.is_inexact_array)
    # Symbolic-zero (None) tangents of differentiable leaves become explicit zeros.
    t_diff = jax.tree.map(
        lambda p, t: None if p is None else (jnp.zeros_like(p) if t is None else t),
        diff,
        tangents,
        is_leaf=lambda x: x is None,
    )

    def gradient(data):
        problem, opts = eqx.combine(data, static)
        return pose_gradient(problem, opts, pose, pairs)

    _, d_grad = jax.jvp(gradient, (diff,), (t_diff,))
    inverse, _, _ = pseudo_inverse(pose_hessian(*primals, pose, pairs))
    zero = jnp.zeros(6, params.dtype)
    _, d_params = jax.jvp(lambda d: (pose @ _chart(d)).wxyz_xyz, (zero,), (-inverse @ d_grad,))
    return params, d_params
