"""The register stage's compiled search programs: multi-start ICP of every candidate segment
into the model in one call (:func:`_score_candidates`: its starts, the rounds that thin them,
their evidence) and the refinement's multi-start ICP (:func:`_register_starts`).

Conventions of :mod:`jaxreg.pipeline.estimate`: the segment (source, base frame) is registered
into the model (target, object frame), so ICP's poses are ``object_T_base``; tangents are
jaxlie's.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3, SO3
from jaxtyping import Array

from jaxreg.core._program_cache import persistent_jit
from jaxreg.core._threads import lane_pieces, split_lanes
from jaxreg.pipeline._judge import _confirmed_share, _visibilities
from jaxreg.pipeline._model import _Model
from jaxreg.registration.icp import multistart_icp, pca_inits, rotation_inits
from jaxreg.registration.solver import ICPOptions, apply_pose as _apply, prepare, run
from jaxreg.search.neighbors import query_nearest


class _Coarse(eqx.Module):
    """Coarse registration of every candidate, its refined starts ranked best first (by the
    fraction of the cloud the model explains times the confirmed share of the model's
    visible surface): ``poses`` ``(C, K, 7)`` object_T_base wxyz_xyz, ``explained``
    ``(C, K)``, ``visibility`` ``(C, K, 5)``."""

    poses: Array
    explained: Array
    visibility: Array


def _coarse_problem(model: _Model, size: int, distances: np.ndarray, splits: tuple[int, ...]):
    """ICP's problem for ``size``-point sources against the model (the source rows are
    replaced per candidate) and the options of its rounds: the correspondence ``distances``
    cut at ``splits`` (e.g. ``(2, 6)``: the first two for every start, the next four for the
    starts kept after them, the rest for the starts kept after those). Built once per model
    and schedule."""
    key = (size, distances.tobytes(), splits)
    if key not in model.coarse:
        rounds = []
        for part in np.split(distances, splits):
            options = ICPOptions(
                method="point_to_plane", target_normals=model.normals,
                max_correspondence_distance=part, max_iterations=len(part), tolerance=1e-5,
                neighbors=model.grid,
            )  # fmt: skip
            problem, opts, _ = prepare(np.zeros((size, 3), np.float32), model.points, options)
            rounds.append(opts)
        model.coarse[key] = (problem, *rounds)
    return model.coarse[key]


def _front_aligned(inits: SE3, cloud, ok, model_points, eye) -> SE3:
    """Starts (object_T_base) slid along the line of sight so that the model's nearest
    point to the camera lies as near as the cloud's (its 5th percentile): a partial view's
    centroid sits on the visible surface, in front of the object's centre. NaN model rows
    (padding) are ignored."""
    centroid = jnp.sum(jnp.where(ok[:, None], cloud, 0.0), 0) / jnp.maximum(ok.sum(), 1)
    view = (centroid - eye) / jnp.linalg.norm(centroid - eye)
    depth = jnp.where(ok, jnp.where(ok[:, None], cloud, 0.0) @ view, jnp.nan)
    front = jnp.nanpercentile(depth, 5.0)
    placed = inits.inverse()  # base_T_object
    model_front = (
        jnp.nanmin(
            jnp.einsum("sij,mj->smi", placed.rotation().as_matrix(), model_points) @ view, axis=1
        )
        + placed.translation() @ view
    )
    moved = SE3.from_rotation_and_translation(
        placed.rotation(), placed.translation() + (front - model_front)[:, None] * view
    )
    return moved.inverse()


def _resting_starts(cloud, ok, model_points, model_axes, plane, eye, yaws: int) -> SE3:
    """Starts (object_T_base) of the model resting on the table: each of the model's six
    principal half-axes ``model_axes`` ``(3, 3)`` (columns, object frame) pointing down the
    plane's normal, turned to ``yaws`` headings about it, the lowest model point on the
    plane, and the model slid horizontally toward the camera until its front meets the
    cloud's (5th percentile along the horizontal line of sight; a partial view's centroid
    lies on its visible side). NaN rows of ``model_points`` (padding) are ignored. Batch
    ``(6 * yaws,)``."""
    n = plane.normal
    dtype = cloud.dtype
    downs = jnp.concatenate([model_axes.T, -model_axes.T])  # (6, 3) object frame
    helper = jnp.where(jnp.abs(downs[:, :1]) < 0.9, jnp.eye(3, dtype=dtype)[0], jnp.eye(3)[1])
    b = jnp.cross(downs, helper)
    b = b / jnp.linalg.norm(b, axis=-1, keepdims=True)
    object_frames = jnp.stack([downs, b, jnp.cross(downs, b)], -1)  # (6, 3, 3) columns
    u = jnp.cross(-n, jnp.where(jnp.abs(n[0]) < 0.9, jnp.eye(3, dtype=dtype)[0], jnp.eye(3)[1]))
    u = u / jnp.linalg.norm(u)
    base_frame = jnp.stack([-n, u, jnp.cross(-n, u)], -1)  # (3, 3) columns
    base_R = jnp.einsum("ij,fkj->fik", base_frame, object_frames)  # (6, 3, 3): down -> -n
    angles = jnp.arange(yaws, dtype=dtype) * (2 * jnp.pi / yaws)
    turns = SO3.exp(angles[:, None] * n[None, :]).as_matrix()  # (Y, 3, 3)
    rotations = jnp.einsum("yij,fjk->fyik", turns, base_R).reshape(-1, 3, 3)
    moved = jnp.einsum("sij,mj->smi", rotations, model_points)  # (S, M, 3) about the origin
    centroid = jnp.sum(jnp.where(ok[:, None], cloud, 0.0), 0) / jnp.maximum(ok.sum(), 1)
    along = (centroid - eye) - ((centroid - eye) @ n) * n
    along = along / jnp.maximum(jnp.linalg.norm(along), 1e-9)
    front = jnp.nanpercentile(jnp.where(ok, cloud @ along, jnp.nan), 5.0)
    real = jnp.all(jnp.isfinite(model_points), -1)  # NaN rows pad the model
    model_mid = jnp.sum(jnp.where(real[:, None], moved, 0.0), 1) / real.sum()  # (S, 3)
    # horizontal: the model's centre over the cloud's centroid, then slid along `along`
    horizontal = centroid - (centroid @ n) * n - (model_mid - (model_mid @ n)[:, None] * n)
    horizontal = horizontal - (horizontal @ along)[:, None] * along
    model_front = jnp.nanmin(moved @ along, axis=1)
    horizontal = horizontal + (front - model_front)[:, None] * along
    lift = -plane.offset - jnp.nanmin(moved @ n, axis=1)  # lowest point on the plane
    translations = horizontal + lift[:, None] * n
    placed = SE3.from_rotation_and_translation(SO3.from_matrix(rotations), translations)
    return placed.inverse()


# Two poses are distinct answers when their translations differ by more than DISTINCT_DISTANCE
# (metres) or their rotations by more than DISTINCT_ANGLE (radians, ~11 degrees): farther apart
# than the refinement's basin, so refining both is not refining one answer twice.
DISTINCT_DISTANCE = 0.01
DISTINCT_ANGLE = 0.2


def _spread_best(poses: Array, score: Array, count: int) -> Array:
    """Indices ``(count,)`` of the best-scoring rows of ``poses`` ``(S, 7)`` (wxyz_xyz) that
    are distinct from every earlier pick (``DISTINCT_DISTANCE`` or ``DISTINCT_ANGLE``); when
    fewer rows are that distinct, the best remaining ones fill the rest (jittable)."""
    quats, trans = poses[:, :4], poses[:, 4:]
    gap = jnp.linalg.norm(trans[:, None] - trans[None], axis=-1)
    cos = jnp.abs(quats @ quats.T)  # cos of half the angle between two rotations
    near = (gap <= DISTINCT_DISTANCE) & (cos >= jnp.cos(DISTINCT_ANGLE / 2))
    rank = jnp.where(jnp.isfinite(score), score, -1.0)

    def pick(carry, _):
        distinct, free = carry
        i = jnp.argmax(jnp.where(distinct, rank + 3.0, jnp.where(free, rank, -jnp.inf)))
        return (distinct & ~near[i], free.at[i].set(False)), i

    ones = jnp.ones(len(score), bool)
    _, chosen = jax.lax.scan(pick, (ones, ones), None, length=count)
    return chosen


@persistent_jit
def _score_candidates(
    frame, plane, problem, rounds, fine_grid, clouds, used, model_points, screen_points,
    model_axes, tolerance, sigma_z, explained_distance, num_starts, yaws, survivors, keep,
):  # fmt: skip
    """Multi-start ICP of every candidate cloud ``(C, N, 3)`` (NaN padding) into the model,
    its ranked starts, and the evidence for each; slots where ``used`` ``(C,)`` is False are
    skipped (zeros), so one compiled shape serves any number of candidates up to C. Starts:
    ``num_starts`` rotations of a grid over SO(3) and the 4 PCA frames, slid along the line
    of sight to the cloud's front, and ``6 * yaws`` resting on the table
    (:func:`_resting_starts`); without a table (``plane`` is ``None``) their share goes to
    the rotation grid (``num_starts + 6 * yaws`` rotations), and nothing is judged against a
    plane. ICP runs in three ``rounds`` (options of
    :func:`_coarse_problem`), each on fewer starts: every start takes the first; the
    ``survivors`` whose model then explains most of the cloud (1 cm; not thinned to
    distinct poses: a start that will win may still sit near a better-fitting one) take the
    second and are scored as below with the sparse ``screen_points``
    ``(M1, 3)`` (the model voxelled at 3 voxels; :func:`visibility` on 16-pixel cells: the
    z-buffer's scatter dominates the scoring on a CPU); the ``keep`` best distinct ones
    take the third and are scored with ``model_points`` (4-pixel cells; the sparse
    judgement is too coarse to rank near-equal candidates). The score is the share of the
    cloud within ``explained_distance`` of the model times the confirmed share
    (:func:`visibility` with ``tolerance`` and ``sigma_z``). Those shares are counted on
    ``fine_grid`` (the model's grid exact to the refinement's largest distance, 15 mm or
    more: the same neighbours within 1 cm as ICP's coarse grid, in lists an eighth as
    long)."""
    screen_opts, first_opts, rest_opts = rounds

    def one(cloud):
        ok = jnp.all(jnp.isfinite(cloud), -1)
        eye = frame.base_T_camera.translation()
        rotations = num_starts if plane is not None else num_starts + 6 * yaws
        grid = rotation_inits(cloud, model_points, rotations)
        inits = SE3(jnp.concatenate([grid.wxyz_xyz, pca_inits(cloud, model_points).wxyz_xyz]))
        inits = _front_aligned(inits, cloud, ok, model_points, eye)
        if plane is not None:
            resting = _resting_starts(cloud, ok, model_points, model_axes, plane, eye, yaws)
            inits = SE3(jnp.concatenate([inits.wxyz_xyz, resting.wxyz_xyz]))
        source = (
            jnp.zeros_like(problem.source)
            .at[: cloud.shape[0]]
            .set(jnp.where(ok[:, None], cloud, 0.0))
        )
        weights = jnp.zeros_like(problem.source_weights).at[: cloud.shape[0]].set(ok)
        p = eqx.tree_at(lambda q: (q.source, q.source_weights), problem, (source, weights))
        cloud0 = jnp.where(ok[:, None], cloud, 0.0)

        def explains(pose, distance):
            _, _, near = query_nearest(fine_grid, _apply(pose, cloud0), distance)
            return jnp.sum(near & ok) / jnp.maximum(ok.sum(), 1)

        def evidence(poses, points, cell):
            explained = jax.vmap(explains, in_axes=(0, None))(poses, explained_distance)
            seen = _visibilities(
                frame, poses.inverse(), points, tolerance, plane, cell, sigma_z
            )  # fmt: skip
            return explained, seen

        icp = jax.vmap(run, in_axes=(None, None, 0))
        screened = icp(p, screen_opts, inits).pose
        near = jax.vmap(explains, in_axes=(0, None))(screened, 0.01)
        alive = jnp.argsort(-near)[:survivors]
        first = icp(p, first_opts, SE3(screened.wxyz_xyz[alive]))
        explained, seen = evidence(first.pose, screen_points, 16)
        kept = _spread_best(first.pose.wxyz_xyz, explained * _confirmed_share(seen), keep)
        results = icp(p, rest_opts, SE3(first.pose.wxyz_xyz[kept]))
        explained, seen = evidence(results.pose, model_points, 4)
        score = explained * _confirmed_share(seen)
        order = jnp.argsort(-score)
        return results.pose.wxyz_xyz[order], explained[order], seen[order]

    dtype = clouds.dtype

    def skip(cloud):
        return (
            jnp.zeros((keep, 7), dtype), jnp.zeros(keep, dtype), jnp.zeros((keep, 5), jnp.int32),
        )  # fmt: skip

    def slot(args):
        cloud, live = args
        return jax.lax.cond(live, one, skip, cloud)

    poses, explained, seen = jax.lax.map(slot, (clouds, used))
    return _Coarse(poses, explained, seen)


@persistent_jit
def _register_starts(
    source, points, normals, grid, inits, distances, trim, iterations, viewpoint
):  # fmt: skip
    """Point-to-plane multi-start ICP of ``source`` into the model (its points, normals and
    grid as arguments, not constants of the stored program: a model's arrays closed into it
    made a ~30 MB executable to load in every process); ``viewpoint`` the camera's centre
    (base frame) for an oriented model (:func:`jaxreg.pipeline._model.viewpoint`), else
    ``None``."""
    return multistart_icp(
        source, points, inits, method="point_to_plane", target_normals=normals,
        max_correspondence_distance=distances, max_iterations=iterations, trim_fraction=trim,
        neighbors=grid, tolerance=1e-5, viewpoint=viewpoint,
    )  # fmt: skip


def _starts_in_pieces(
    source, points, normals, grid, inits, distances, trim, iterations, viewpoint, per_piece=8
):  # fmt: skip
    """:func:`_register_starts` from every start of ``inits`` ``(S, 7)`` (object_T_base), run
    as one concurrent call per core on a piece of at least ``per_piece`` starts
    (:func:`jaxreg.core._threads.split_lanes`): on a CPU, XLA runs a registration's many
    small steps on one core, so two pieces fill each other's gaps. Numpy results, the start
    axis leading."""
    lanes = np.asarray(inits, np.float32)
    return split_lanes(
        lambda part: _register_starts(
            source, points, normals, grid, SE3(part), distances, trim, iterations, viewpoint
        ),
        lanes, lane_pieces(len(lanes), per_piece),
    )  # fmt: skip
