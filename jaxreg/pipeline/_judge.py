"""The depth image's evidence about a model pose, for the stages of :func:`jaxreg.estimate_pose`:
which model points the image confirms, contradicts or cannot judge (:func:`visibility`), how
much of a segment the model explains, how far a segment reaches below the model
(:func:`underneath`) and how far a pose sinks the model into the table (:func:`sunk`). The
model comes prepared by :mod:`jaxreg.pipeline._model`.

Conventions of :mod:`jaxreg.pipeline.estimate`: the segment (source, base frame) is registered
into the model (target, object frame), so ICP's poses are ``object_T_base``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, Float
from scipy.spatial.transform import Rotation

from jaxreg.camera.model import RGBDFrame
from jaxreg.core._program_cache import persistent_jit
from jaxreg.core._threads import lane_pieces, split_lanes
from jaxreg.pipeline._model import _Model
from jaxreg.pipeline.segment import TablePlane
from jaxreg.registration.solver import apply_pose as _apply
from jaxreg.search.neighbors import cell_codes, query_nearest

__all__ = ["visibility"]

NOISE_SIGMAS = 4  # a depth within this many sigma_z(z) of the model agrees (see visibility)
# depth agreement (metres) of the image's judgement of a pose; more where the depth noise's
# NOISE_SIGMAS sigma_z(z) is more (see visibility)
TOLERANCE = np.float32(0.01)


@eqx.filter_jit
def visibility(
    frame: RGBDFrame,
    base_T_object: SE3,
    model_points: Float[Array, "M 3"],
    tolerance: Float[Array, ""],
    plane: TablePlane | None = None,
    cell: int = 4,
    *,
    sigma_z: Float[Array, " C"] | None = None,
) -> Float[Array, " 5"]:
    """How the depth image judges the model at a pose: counts ``(confirmed, contradicted,
    occluded, unknown, self_hidden)`` of the model points (jittable).

    With a table ``plane``, every model point more than ``tolerance`` below it is
    contradicted, facing the camera or not: an object cannot stand in the table.

    The model points are moved into the camera and z-buffered among themselves on a grid of
    ``cell`` x ``cell`` pixels: a point more than ``tolerance`` behind the nearest model
    point of its cell is hidden by the model itself (its far side). Each point the camera
    could see is compared with the depth measured at its pixel: within ``tolerance``
    (metres) it is confirmed; measured farther, the camera sees through where the surface
    should be (contradicted, evidence against the pose or the object's presence); measured
    nearer, something else hides it (occluded); a hole or a pixel outside the image is
    unknown. NaN rows of ``model_points`` (a model padded to a bucketed size) count nowhere.

    With ``sigma_z`` (ascending polynomial coefficients of the depth noise's standard
    deviation in the camera depth ``z``, as :class:`~jaxreg.uncertainty.DepthNoise` holds
    them) each point's tolerance is ``tolerance`` or ``NOISE_SIGMAS`` times ``sigma_z`` at
    its depth, whichever is larger: the floor covers the model's own error (voxels,
    samples), the noise term a far or noisy view.
    """
    poses = SE3(base_T_object.wxyz_xyz[None])
    return _visibilities(frame, poses, model_points, tolerance, plane, cell, sigma_z)[0]


def _visibilities(frame, base_T_object: SE3, model_points, tolerance, plane, cell, sigma_z):
    """:func:`visibility` counts ``(S, 5)`` of a batch of poses ``base_T_object`` ``(S,)``
    (traced). The per-point geometry is vmapped over the poses, the points moved by rotation
    matrices (jaxlie's quaternion ``apply`` gathers its Hamilton products' terms: ~50x
    slower on XLA's CPU backend for a batch of poses); the z-buffer is one scatter into
    ``S`` cell grids laid end to end (a vmapped scatter is ~20x slower on a CPU)."""
    h, w = frame.depth.shape
    hc, wc = -(-h // cell), -(-w // cell)

    def place(pose):
        """Camera-frame points ``(M, 3)``, clipped pixel ``(row, col)``, whether each lies in
        front of the camera and inside the image, its tolerance and its cell ``(M,)``."""
        camera_T_object = frame.base_T_camera.inverse() @ pose
        cam = _apply(camera_T_object, jnp.asarray(model_points, frame.depth.dtype))
        pix = frame.intrinsics.project(cam)
        col = jnp.round(pix[:, 0]).astype(jnp.int32)
        row = jnp.round(pix[:, 1]).astype(jnp.int32)
        inside = (cam[:, 2] > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        limit = jnp.broadcast_to(tolerance, cam[:, 2].shape).astype(cam.dtype)
        if sigma_z is not None:
            powers = cam[:, 2:3] ** jnp.arange(sigma_z.shape[0], dtype=cam.dtype)
            limit = jnp.maximum(tolerance, NOISE_SIGMAS * (powers @ sigma_z.astype(cam.dtype)))
        row, col = jnp.clip(row, 0, h - 1), jnp.clip(col, 0, w - 1)
        code = (row // cell) * wc + col // cell
        below = jnp.zeros(cam.shape[0], bool)
        if plane is not None:
            height = plane.height(_apply(pose, jnp.asarray(model_points, cam.dtype)))
            below = height < -limit
        return cam, row, col, inside, limit, code, below

    cam, row, col, inside, limit, code, below = jax.vmap(place)(base_T_object)
    count = cam.shape[0]
    slot = code + (jnp.arange(count, dtype=code.dtype) * (hc * wc))[:, None]
    zbuf = (
        jnp.full(count * hc * wc, jnp.inf, cam.dtype)
        .at[slot.reshape(-1)]
        .min(jnp.where(inside, cam[..., 2], jnp.inf).reshape(-1))
    )
    facing = inside & (cam[..., 2] <= zbuf[slot] + limit)
    measured = frame.depth[row, col]
    known = facing & jnp.isfinite(measured)
    diff = measured - cam[..., 2]
    confirmed = known & (jnp.abs(diff) <= limit)
    # seen through only where every pixel within the sensor's lateral uncertainty looks past
    # the model: at a silhouette's edge (a thin part, a flying pixel) it is not judged
    contradicted = known & (_nearest_depth(frame.depth)[row, col] - cam[..., 2] > limit)
    if plane is not None:
        contradicted = contradicted | below  # seen or hidden, it cannot be there
        known = known | below
        confirmed = confirmed & ~below
    occluded = known & (diff < -limit) & ~contradicted
    unknown = ~known & (facing | ~inside) & jnp.all(jnp.isfinite(cam), -1)
    flags = [confirmed, contradicted, occluded, unknown, inside & ~facing]
    return jnp.stack([flag.sum(-1) for flag in flags], -1)


# Pixels (either side) within which a depth camera's measurement may come from a neighbouring
# ray: its lateral noise (0.8 pixel for the structured-light class) and the edge's mixed pixels.
LATERAL_PIXELS = 1


def _nearest_depth(depth: Float[Array, "H W"]) -> Float[Array, "H W"]:
    """The nearest finite depth (metres) within ``LATERAL_PIXELS`` of each pixel (``inf``
    where there is none): what the camera may have measured for a ray through that pixel."""
    side = 2 * LATERAL_PIXELS + 1
    finite = jnp.where(jnp.isfinite(depth), depth, jnp.inf)
    return jax.lax.reduce_window(finite, jnp.inf, jax.lax.min, (side, side), (1, 1), "SAME")


def _lowest(model: _Model, plane: TablePlane, object_T_base: np.ndarray) -> float:
    """The height (metres) of the model's lowest point above the table ``plane`` at the pose
    ``object_T_base`` ``(7,)`` (wxyz_xyz); NaN for a non-finite pose."""
    rotation = Rotation.from_quat(np.asarray(object_T_base[:4], np.float64), scalar_first=True)
    points = model.points[np.all(np.isfinite(model.points), axis=1)]
    placed = rotation.inv().apply(points - np.asarray(object_T_base[4:], np.float64))
    return float((placed @ np.asarray(plane.normal, np.float64)).min()) + float(plane.offset)


def sunk(model: _Model, plane: TablePlane | None, object_T_base: np.ndarray) -> float:
    """How far (metres) the pose ``object_T_base`` ``(7,)`` (wxyz_xyz) puts the model's lowest
    point below the table ``plane`` (0 when it stays above, or without a plane). No object
    reaches into the table: a pose sunk by more than the depth noise fits a shorter object
    (a can with a mug's top on it), or fits the object wrongly."""
    if plane is None:
        return 0.0
    return max(-_lowest(model, plane, object_T_base), 0.0)


def underneath(
    model: _Model, plane: TablePlane | None, object_T_base: np.ndarray, points: np.ndarray
) -> float:
    """How far (metres) a segment's ``points`` ``(N, 3)`` (base frame) reach below the
    model's lowest point at the pose ``object_T_base`` ``(7,)``, along the table ``plane``'s
    normal (their 2% quantile height; negative when they stay above it, 0 without a plane).
    An object's own points rise from its lowest point; points beneath the model say it sits
    on top of a taller object of a similar shape, or on a neighbour merged with the segment."""
    if plane is None:
        return 0.0
    heights = np.asarray(points, np.float64) @ np.asarray(plane.normal, np.float64)
    return _lowest(model, plane, object_T_base) - float(
        np.quantile(heights + float(plane.offset), 0.02)
    )


def _confirmed_share(counts: Array) -> Array:
    """Confirmed over judged (confirmed, contradicted, occluded) model points, ``(...)``, of
    numpy or JAX counts ``(..., 5)`` (array methods only: host counts stay on the host)."""
    return counts[..., 0] / counts[..., :3].sum(-1).clip(min=1)


def seen_share(counts: np.ndarray) -> np.ndarray:
    """Confirmed over the model points facing the camera that nothing nearer hides
    (confirmed, contradicted, unknown: outside the image or over a depth hole), ``(...)``,
    of counts ``(..., 5)`` (:func:`visibility`)."""
    counts = np.asarray(counts)
    return counts[..., 0] / (counts[..., :2].sum(-1) + counts[..., 3]).clip(min=1)


def judged_fits(frame, plane, poses, model_points, results, noise):
    """ICP ``results`` ``(S,)`` at ``poses`` ``(S, 7)`` (object_T_base: theirs, or moved
    since) as the register stage weighs fits: scores ``(S,)``, the share of source points
    within the last correspondence distance times the confirmed share of the judged model
    (:func:`_confirmed_share`); residuals ``(S,)`` (metres, ``inf`` without pairs); the
    image's counts ``(S, 5)`` (:func:`visibility`; many poses are judged in one concurrent
    call per core). ``noise``: the camera's ``DepthNoise``."""
    poses = np.asarray(poses, np.float32)
    seen = split_lanes(
        lambda part: _judge(frame, plane, part, model_points, TOLERANCE, noise.coefficients),
        poses, lane_pieces(len(poses)),
    )  # fmt: skip
    scores = np.asarray(results.inlier_fraction) * _confirmed_share(seen)
    rmses = np.nan_to_num(np.asarray(results.inlier_rmse), nan=np.inf)
    return scores, rmses, seen


def passes_gates(fractions, rmses, seen, max_rmse: float, register) -> np.ndarray:
    """``(S,)`` bool: which fits pass the gates an answer must pass: residual ``rmses`` within
    ``max_rmse`` (metres), explained ``fractions`` at least ``register.min_inlier_fraction``,
    and of the image's counts ``seen`` ``(S, 5)`` the confirmed share at least
    ``min_confirmed``, the contradicted share at most ``max_contradicted`` and the share
    seen (:func:`seen_share`) at least ``min_seen``."""
    seen = np.asarray(seen)
    return (
        (np.asarray(rmses) <= max_rmse)
        & (np.asarray(fractions) >= register.min_inlier_fraction)
        & (_confirmed_share(seen) >= register.min_confirmed)
        & (seen[:, 1] / seen[:, :3].sum(1).clip(min=1) <= register.max_contradicted)
        & (seen_share(seen) >= register.min_seen)
    )


def fit_order(scores: np.ndarray, rmses: np.ndarray) -> np.ndarray:
    """Indices of fits best first: the higher score to two decimals (fits closer than that
    are as good), then the smaller residual."""
    return np.lexsort((rmses, -np.round(scores, 2)))


def _support(counts: np.ndarray) -> tuple[float, float, int]:
    """(confirmed share, contradicted share, judged count) of the model points facing the
    camera that the image can judge (confirmed, contradicted or occluded). With nothing judged
    both shares are 0: no evidence is not agreement."""
    confirmed, contradicted, occluded = (float(c) for c in counts[:3])
    judged = confirmed + contradicted + occluded
    if judged == 0:
        return 0.0, 0.0, 0
    return confirmed / judged, contradicted / judged, int(judged)


@persistent_jit
def _near_model(grid, object_T_base, points, distance):
    """``(...)`` bool: which of ``points`` ``(..., 3)`` (base frame; NaN rows never) lie
    within ``distance`` of the model at a pose."""
    flat = points.reshape(-1, 3)
    ok = jnp.all(jnp.isfinite(flat), -1)
    moved = _apply(SE3(object_T_base), jnp.where(ok[:, None], flat, 0.0))
    _, _, near = query_nearest(grid, moved, distance)
    return (near & ok).reshape(points.shape[:-1])


@persistent_jit
def _judge(frame, plane, object_T_base, model_points, tolerance, sigma_z):
    """:func:`visibility` counts ``(S, 5)`` of a batch of object_T_base ``(S, 7)``."""
    return _visibilities(frame, SE3(object_T_base).inverse(), model_points, tolerance, plane, 4,
                         sigma_z)  # fmt: skip


# Edge (metres) of the cubic patches of a segment whose errors are independent of one
# another (neighbouring pixels share a stereo camera's matching window, a structured-light
# camera's pattern, the model's local mismatch); the error budget sums its fit term over them.
PATCH = 0.012


def patch_count(points: np.ndarray) -> int:
    """The number of ``PATCH`` cubes that base-frame ``points`` ``(N, 3)`` occupy."""
    return len(np.unique(cell_codes(np.floor(np.asarray(points, np.float64) / PATCH))))


# Two fits whose evidence differs by at most this many standard errors of the difference
# (:func:`evidence_gap`) are equally good: the frame cannot tell them apart.
EQUAL_WITHIN = 2.0
# A disjoint candidate whose coarse score is within this many standard errors of the winner's
# is refined beside it before the winner is claimed: a coarse pose a few degrees off sees
# through the model's edges and costs its score up to about EQUAL_WITHIN standard errors.
CONTESTED_WITHIN = 2 * EQUAL_WITHIN


def evidence_gap(scores, rmses, score: float, rmse: float, patches: int) -> np.ndarray:
    """``(S,)`` how much worse than the answer (``score``, ``rmse``) each fit is (``scores``:
    explained share times confirmed share, ``rmses``: inlier RMSE in metres, ``(S,)`` each),
    in standard errors of the difference, judged over ``patches`` independent patches: the
    larger of the score's shortfall over ``sqrt(2 score (1 - score) / patches)`` (at least
    that of a share of 0.1) and the mean squared residual's excess over ``2 / sqrt(patches)``
    of the answer's (two means of ``patches`` squares, each ``sqrt(2 / patches)`` relative).
    0 for a fit at least as good; NaN residuals count as infinitely worse."""
    n = max(int(patches), 1)
    scores, rmses = np.asarray(scores, np.float64), np.asarray(rmses, np.float64)
    share = (score - scores) / np.sqrt(2 * max(score * (1.0 - score), 0.09) / n)
    squares = (rmses**2 / max(rmse**2, 1e-12) - 1.0) * np.sqrt(n) / 2
    gap = np.maximum(np.maximum(share, squares), 0.0)
    return np.where(np.isfinite(gap), gap, np.inf)
