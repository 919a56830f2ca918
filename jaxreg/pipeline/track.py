"""Tracking: the pose in the next frame of a stream, from the pose in the previous one.

:func:`track` needs no segmentation: the model at the ``previous`` pose, projected into the new
frame, says which pixels to look at (its footprint grown by the motion allowed between frames,
the depths near the model's, above the previous estimate's table if it found one, on one
surface: :func:`jaxreg.pipeline._surface.mask_surface`). ICP from the previous pose, trimmed to
its better pairs, follows the object there; where the image sees through the model at its
answer (perhaps a larger motion), so does ICP from four starts with pairs out to the motion
allowed (the previous pose, that pose moved by the shift of the looked-at pixels' centroid,
and that one turned by half the largest turn either way), and the best answer is kept. The
pixels whose depth agrees with the model's at the pose followed are the segment, and the
register stage refines that pose on them: no candidates, no coarse search. The same evidence
as :func:`jaxreg.estimate_pose` refuses an answer (the share of the segment the model
explains, the residual, the image seeing through the model, the segment reaching beyond it),
and the same error budget gives its covariance. A refusal says the object is lost (it moved
farther than ``max_motion``, left the view, or is hidden): re-detect it with
``estimate_pose``.

The budget's costly terms measure the view rather than the fit: the answer turned about the
model's axes and refined again (the poses that fit as well: the ambiguity term, the axes the
view leaves free, the equivalent poses) and the segment re-registered with its membership
perturbed (the segmentation term). From a previous track step's :class:`PoseEstimate` they
are carried (:class:`~jaxreg.pipeline.records.MeasuredView`, in the object's axes, which move
with it) while the camera's direction in the object's frame stays within :data:`CARRY_TURN_DEG` of
where they were measured and the segment keeps its size (:data:`CARRY_POINTS`); then they
are measured again. The first step after :func:`jaxreg.estimate_pose` measures its own: the
estimate registered another segment (a table cluster or the caller's mask), on which the
probes find other equally good turns. The depth, fit, mismatch and calibration terms are
measured on every frame. ``RegisterRecord.view_carried_deg`` says which it was.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np
from jaxlie import SE3, SO3
from jaxtyping import Float
from scipy import ndimage

from jaxreg.camera.model import RGBDFrame
from jaxreg.core._sizes import pad_rows, power_of_two
from jaxreg.geometry.metrics import Symmetry, pose_error
from jaxreg.pipeline._coarse import _register_starts
from jaxreg.pipeline._error_sources import Calibration
from jaxreg.pipeline._judge import (
    NOISE_SIGMAS,
    TOLERANCE,
    _near_model,
    fit_order,
    judged_fits,
)
from jaxreg.pipeline._lift_stage import lift_pixels, lift_stage, project_points
from jaxreg.pipeline._model import PROBE_ANGLES_DEG, _prepare_model, viewpoint
from jaxreg.pipeline._register_stage import refine_stage, tolerances
from jaxreg.pipeline._stages import _Failed, _padded
from jaxreg.pipeline._surface import mask_surface
from jaxreg.pipeline.estimate import (
    PoseEstimate,
    _checked_model,
    _found,
    _noise,
    _refused,
    calibrated,
)
from jaxreg.pipeline.records import CoarseSearch, RegisterRecord, SegmentRecord
from jaxreg.pipeline.settings import PipelineSettings
from jaxreg.uncertainty import DepthNoise
from jaxreg.uncertainty.calibrated import BudgetCalibration

__all__ = ["track"]

# The view's terms are carried while the camera's direction in the object's frame has turned
# less than the smallest turn the answer is probed with (a smaller change of view is one the
# probes would not resolve) ...
CARRY_TURN_DEG = float(min(abs(a) for a in PROBE_ANGLES_DEG))
# ... and the segment holds at least this share of the points it held then (and at most its
# inverse): an occluder coming or going changes what the view shows.
CARRY_POINTS = 0.8


def track(
    frame: RGBDFrame,
    model_points: Float[Any, "M 3"],
    previous: SE3 | Float[Any, "4 4"] | PoseEstimate,
    *,
    max_motion: float = 0.05,
    max_turn_deg: float = 20.0,
    model_normals: Float[Any, "M 3"] | None = None,
    symmetry: Symmetry | None = None,
    depth_noise: DepthNoise | None = None,
    hand_eye_covariance: Float[Any, "6 6"] | None = None,
    intrinsics_sigma: Float[Any, " 4"] | None = None,
    depth_scale_sigma: float = 0.0,
    settings: PipelineSettings | None = None,
    calibration: BudgetCalibration | None = None,
    **keywords,
) -> PoseEstimate:
    """``base_T_object`` in ``frame`` starting from its pose in the previous frame.

    Args:
        frame: the new depth frame.
        model_points: ``(M, 3)`` the model's points (object frame, metres).
        previous: the previous ``base_T_object``: an ``SE3``, a ``(4, 4)`` matrix, or the
            previous :class:`PoseEstimate` (which must hold a pose). An estimate's ``table``
            is taken to stay where it was (base frame): pixels less than the lift's
            ``min_height`` above it are not the object, and the answer may rest on it.
        max_motion: the farthest (metres) the object's points may move between the frames:
            the footprint grows by it, the depths looked at reach it beyond the model's, and
            an answer farther from ``previous`` is refused as lost.
        max_turn_deg: the largest turn (degrees) between the frames; a larger one is
            refused as lost.
        model_normals: as for :func:`jaxreg.estimate_pose`, and so are ``symmetry``,
            ``depth_noise``, ``hand_eye_covariance``, ``intrinsics_sigma``,
            ``depth_scale_sigma``, ``settings``, ``calibration`` and ``**keywords`` (the
            settings' fields).

    Returns:
        A :class:`PoseEstimate`; its ``stages`` are ``segment`` (the projected footprint:
        ``mask_pixels`` the pixels looked at, ``mask_grid_points`` those on the surface),
        ``lift`` and ``register``. A refusal (``failed_stage``) means the object is lost.

    Raises:
        ValueError: bad input as for ``estimate_pose``, a ``previous`` that is not a pose or
            an estimate without one, or a non-positive ``max_motion`` / ``max_turn_deg``.
    """
    model_points, model_normals = _checked_model(frame, model_points, model_normals)
    base_T_object = _previous_pose(previous)
    table = previous.table if isinstance(previous, PoseEstimate) else None
    if not (max_motion > 0 and max_turn_deg > 0):
        raise ValueError(
            f"max_motion and max_turn_deg must be positive, got {max_motion}, {max_turn_deg}"
        )
    settings = (settings or PipelineSettings()).replace(**keywords)
    stated = Calibration(hand_eye_covariance, intrinsics_sigma, depth_scale_sigma)
    model = _prepare_model(
        model_points, model_normals, settings.voxel_size, float(settings.coarse_distances[0]),
        float(settings.fine_distances.max()),
    )  # fmt: skip
    noise = _noise(depth_noise, frame)
    records: dict[str, Any] = {}
    try:
        region, coarse, records["segment"] = _follow(
            frame, model, base_T_object, max_motion, max_turn_deg, noise, settings, table
        )
        lifted = lift_stage(frame, region, table, noise, settings.lift, settings.voxel_size)
        records["lift"] = lifted.record
        count = len(lifted.points)  # padded with NaN rows: one program for every count
        rows = pad_rows(lifted.points.astype(np.float32), power_of_two(count, 1024), np.nan)
        near = _near_model(model.fine_grid, coarse.poses[0], rows, np.float32(0.01))
        explained = np.asarray(near)
        coarse = dataclasses.replace(coarse, explained=float(explained[:count].mean()))
        carried, turn = _carry(previous, frame, model, coarse.poses[0], len(lifted.points))
        found = refine_stage(
            frame, model, coarse, lifted, table, settings, noise, symmetry, stated,
            np.random.default_rng(0), carried,
        )  # fmt: skip
        found = dataclasses.replace(
            found, record=dataclasses.replace(found.record, view_carried_deg=turn),
            view=carried or dataclasses.replace(found.view, followed=True),
        )  # fmt: skip
        records["register"] = found.record
        _check_motion(base_T_object, found, max_motion, max_turn_deg, lifted, symmetry)
        return calibrated(_found(found, lifted, records, table), calibration)
    except _Failed as failure:
        failure.reason += "; re-detect with estimate_pose"
        return _refused(frame, failure, records, table, prefix="lost: ")


def _previous_pose(previous) -> SE3:
    """``previous`` as an ``SE3`` (float64 host values), or ``ValueError``."""
    if isinstance(previous, PoseEstimate):
        if previous.pose is None:
            raise ValueError(
                "the previous estimate holds no pose (it failed at "
                f"{previous.failed_stage}): re-detect with estimate_pose"
            )
        previous = previous.pose
    if isinstance(previous, SE3):
        wxyz_xyz = np.asarray(previous.wxyz_xyz, np.float64)
        if wxyz_xyz.shape != (7,) or not np.all(np.isfinite(wxyz_xyz)):
            raise ValueError("previous must be one finite pose, without batch axes")
        return SE3(wxyz_xyz)
    matrix = np.asarray(previous, np.float64)
    if matrix.shape != (4, 4) or not np.all(np.isfinite(matrix)):
        raise ValueError(
            f"previous must be an SE3, a finite (4, 4) matrix or a PoseEstimate, got shape "
            f"{matrix.shape}"
        )
    if not np.allclose(matrix[:3, :3] @ matrix[:3, :3].T, np.eye(3), atol=1e-4):
        raise ValueError("previous's (4, 4) matrix must hold a rotation")
    return SE3.from_matrix(matrix)


def _projected(frame, model, base_T_object: SE3):
    """The model's finite points at ``base_T_object`` in front of the camera: their camera
    coordinates ``(R, 3)`` (metres), their pixels ``(R, 2)`` (column, row; rounded), which of
    those lie in the image ``(R,)``, and the nearest camera depth per pixel ``(H, W)``
    (``inf`` where no point projects)."""
    h, w = np.asarray(frame.depth).shape
    points = model.points[np.all(np.isfinite(model.points), axis=1)].astype(np.float64)
    camera_T_object = np.asarray(
        (frame.base_T_camera.inverse() @ SE3(np.asarray(base_T_object.wxyz_xyz, np.float32)))
        .as_matrix(), np.float64,
    )  # fmt: skip
    cam = points @ camera_T_object[:3, :3].T + camera_T_object[:3, 3]
    cam = cam[cam[:, 2] > 1e-3]
    nearest = np.full((h, w), np.inf)
    pixels = np.zeros((0, 2), int)
    inside = np.zeros(0, bool)
    if len(cam):
        pixels = np.rint(project_points(frame, cam.astype(np.float32))).astype(int)
        inside = np.all((pixels >= 0) & (pixels < (w, h)), axis=1)
        np.minimum.at(nearest, (pixels[inside, 1], pixels[inside, 0]), cam[inside, 2])
    return cam, pixels, inside, nearest


def _box(pixels: np.ndarray, shape: tuple[int, int], margin: int):
    """The slices of the bounding box of ``pixels`` ``(P, 2)`` (column, row; at least one, in
    the ``(H, W)`` image) grown by ``margin`` pixels within the image."""
    low, high = pixels.min(0) - margin, pixels.max(0) + margin + 1
    return np.s_[max(low[1], 0) : min(high[1], shape[0]), max(low[0], 0) : min(high[0], shape[1])]


def _around(frame, projected, reach: float, noise, table, low):
    """The model's footprint (``projected``: :func:`_projected` at the previous pose) grown
    by ``reach`` metres (at its nearest depth), the pixels with depth within ``reach`` of the
    model's depths and, with a ``table``, ``low`` metres or more above it, on one surface
    with the largest piece (:func:`~jaxreg.pipeline._surface.mask_surface`). Returns them
    ``(H, W)`` bool, the slices of a box that holds them all, and the base-frame points of
    that box's pixels ``(h, w, 3)`` (NaN where none is lifted)."""
    _, pixels, inside, nearest = projected
    footprint = np.isfinite(nearest)
    if not inside.any():
        return footprint, np.s_[0:0, 0:0], np.zeros((0, 0, 3), np.float32)
    z = nearest[pixels[inside, 1], pixels[inside, 0]]
    fx = float(frame.intrinsics.fx)
    grow = int(np.clip(np.ceil(reach * fx / max(float(z.min()), 1e-3)), 1, 200))
    # ``grow`` 4-connected dilations: every pixel within that taxicab distance (all of them
    # in the footprint's box grown by ``grow``)
    box = _box(pixels[inside], footprint.shape, grow)
    depth = np.asarray(frame.depth)[box]
    near = ndimage.distance_transform_cdt(~footprint[box], metric="taxicab") <= grow
    near &= np.isfinite(depth) & (depth >= z.min() - reach) & (depth <= z.max() + reach)
    rows, cols = np.nonzero(near)
    lifted = lift_pixels(frame, rows + box[0].start, cols + box[1].start)
    points = np.full((*near.shape, 3), np.nan, np.float32)
    points[rows, cols] = lifted
    if table is not None:
        height = lifted @ np.asarray(table.normal, np.float64)
        near[rows, cols] = height + float(table.offset) >= low
    looked = np.zeros_like(footprint)
    looked[box] = mask_surface(depth, near, noise, fx)
    return looked, box, points


def _on_model(frame, model, base_T_object: SE3, noise) -> np.ndarray:
    """``(H, W)`` bool: the pixels whose depth agrees with the model's own at
    ``base_T_object`` (its points' nearest depth per pixel, spread over 5 x 5 pixels to
    close the gaps between a sparse model's points; within 1 cm or 4 sigma_z, as the image's
    judgement allows): the object's surface, without the table or background beside it."""
    _, pixels, inside, nearest = _projected(frame, model, base_T_object)
    agree = np.zeros(nearest.shape, bool)
    if not inside.any():
        return agree
    box = _box(pixels[inside], nearest.shape, 2)  # the model's pixels and the erosion's reach
    nearest = ndimage.grey_erosion(nearest[box], size=5)
    depth = np.asarray(frame.depth)[box]
    sigma = noise.axial_sigma(np.where(np.isfinite(nearest), nearest, 0.0))
    limit = np.maximum(float(TOLERANCE), NOISE_SIGMAS * sigma)
    agree[box] = np.isfinite(nearest) & np.isfinite(depth) & (np.abs(depth - nearest) <= limit)
    return agree


def _follow(frame, model, base_T_object: SE3, max_motion, max_turn_deg, noise, settings, table):
    """The object followed from the previous pose, in the pixels around the previous
    footprint (:func:`_around`, within ``max_motion``, above the ``table`` by the lift
    stage's ``min_height`` if one is given): ICP from the previous pose with pairs within the
    refinement's distances, trimmed to the better 60% of its pairs; where the image sees
    through more than half ``max_contradicted`` of the model at its answer (:func:`_ranked`),
    also ICP from four starts (:func:`_starts`) with pairs out to ``max_motion``, and the
    best of all.
    The pixels whose depth agrees with the model's at the pose followed are the segment to
    judge (:func:`_on_model`). Returns that segment ``(H, W)``, the followed pose as a
    coarse search result, and the segment record; ``_Failed`` when too few pixels are
    found."""
    start = time.perf_counter()
    projected = _projected(frame, model, base_T_object)
    looked, box, lifted = _around(
        frame, projected, max_motion, noise, table, settings.lift.min_height
    )
    need = settings.lift.min_segment_points
    record = SegmentRecord(
        ms=0.0, valid_grid_points=int(np.isfinite(np.asarray(frame.depth)).sum()),
        mask_pixels=int(looked[box].sum()),
    )  # fmt: skip
    if record.mask_pixels < need:
        raise _Failed(
            "segment",
            f"the model at the previous pose meets {record.mask_pixels} pixels with depth "
            f"within {max_motion * 1e3:.0f} mm of it (need {need}): it moved farther, left "
            "the view or is hidden",
            record.with_ms(start),
        )
    rows, cols = np.nonzero(looked[box])
    points = lifted[rows, cols]
    rows, cols = rows + box[0].start, cols + box[1].start
    depth = np.asarray(frame.depth)
    gates = tolerances(model, noise, float(np.median(depth[rows, cols])), settings)
    source = _padded(points, settings.register.max_points, np.random.default_rng(0))
    previous = np.asarray(base_T_object.inverse().wxyz_xyz, np.float32)[None]
    # a small motion: the previous pose, pairs within the refinement's distances (clutter
    # near the object stays out of reach)
    eye = viewpoint(model, frame)
    near = _register_starts(
        source, model.points, model.normals, model.fine_grid, SE3(previous), gates.distances,
        np.float32(0.6), 30, eye,
    )  # fmt: skip
    poses, scores, seen_through = _ranked(frame, model, table, near, noise, settings)
    if seen_through[0] > 0.5 * settings.register.max_contradicted:
        # perhaps a larger motion: four starts (:func:`_starts`), pairs as far apart as the
        # motion allowed at first (at most the coarse grid's exact reach), down to the same
        # last distance; the best of these and the first
        first = min(max(max_motion, float(gates.distances[0])), float(model.grid.max_distance))
        reach = np.geomspace(first, gates.distances[-1], 30).astype(np.float32)
        starts = _starts(frame, projected, base_T_object, points, table, max_turn_deg)
        far = _register_starts(
            source, model.points, model.normals, model.grid, SE3(starts), reach,
            np.float32(0.6), 30, eye,
        )  # fmt: skip
        wide, wide_scores, _ = _ranked(frame, model, table, far, noise, settings)
        if wide_scores[0] > scores[0]:
            poses = wide
    object_T_base = poses[:1]
    if not np.all(np.isfinite(object_T_base)):
        object_T_base = previous
    pose = SE3(object_T_base[0].astype(np.float64)).inverse()
    region = _on_model(frame, model, pose, noise)
    record = dataclasses.replace(record, surface_pixels=int(region.sum()))
    register = RegisterRecord(ms=0.0, starts=1, candidates=[], coarse_kept_starts=1)
    coarse = CoarseSearch(region, object_T_base, 1.0, gates, register)
    return region, coarse, record.with_ms(start)


def _ranked(frame, model, table, results, noise, settings):
    """ICP ``results`` ``(S,)`` best first: object_T_base ``(S, 7)``, scores ``(S,)`` and the
    share of the model's seen surface the image sees through ``(S,)``. Ranked as the register
    stage ranks its refined starts (the share of pairs within the last distance times the
    share of the model's seen surface the image confirms, then the residual); a pose seen
    through on more than ``max_contradicted`` scores -1 (the register stage would refuse it)."""
    poses = np.asarray(results.pose.wxyz_xyz, np.float32)
    scores, rmses, seen = judged_fits(frame, table, poses, model.points, results, noise)
    seen_through = seen[:, 1] / np.maximum(seen[:, :3].sum(1), 1)
    scores = np.where(seen_through > settings.register.max_contradicted, -1.0, scores)
    scores = np.nan_to_num(scores, nan=-1)
    order = fit_order(scores, rmses)
    return poses[order], scores[order], seen_through[order]


def _starts(frame, projected, base_T_object: SE3, points, table, max_turn_deg) -> np.ndarray:
    """``(4, 7)`` float32 object_T_base starts of the follow: the previous pose, the previous
    pose moved by the offset between the centroid of the pixels looked at (``points``
    ``(P, 3)``, base frame) and that of the model's points the camera saw at the previous pose
    (``projected``: :func:`_projected` there), and that one turned by half ``max_turn_deg``
    either way (about the ``table``'s normal through the moved centroid; without a table,
    about the camera's optical axis)."""
    cam, pixels, inside, nearest = projected
    seen = np.zeros(len(cam), bool)
    seen[inside] = cam[inside, 2] <= nearest[pixels[inside, 1], pixels[inside, 0]] + 0.005
    base_T_camera = frame.base_T_camera
    was = np.asarray(base_T_camera @ cam[seen]).mean(0) if seen.any() else None
    now = np.nanmean(points, axis=0)
    shift = np.zeros(3) if was is None or not np.all(np.isfinite(now)) else now - was
    if table is not None:
        axis = np.asarray(table.normal, np.float64)
    else:
        axis = np.asarray(base_T_camera.rotation() @ np.array([0.0, 0.0, 1.0]), np.float64)
    centre = now if np.all(np.isfinite(now)) else np.asarray(base_T_object.translation())
    moved = SE3.from_translation(shift) @ base_T_object
    poses = [base_T_object, moved]
    for sign in (1.0, -1.0):
        turn = SO3.exp(axis * sign * np.radians(max_turn_deg / 2))
        about = (
            SE3.from_translation(centre) @ SE3.from_rotation(turn) @ SE3.from_translation(-centre)
        )
        poses.append(about @ moved)
    return np.stack([np.asarray(p.inverse().wxyz_xyz, np.float32) for p in poses])


def _carry(previous, frame, model, object_T_base: np.ndarray, points: int):
    """What ``previous`` (a track step's :class:`PoseEstimate`, or a bare pose) measured of
    the view, and how far (degrees) the camera's direction from the model's centroid, in the
    object's frame, has turned since, at the followed pose ``object_T_base`` ``(7,)``: carried
    for the same ``model`` while that turn stays within :data:`CARRY_TURN_DEG` and the segment's
    ``points`` within :data:`CARRY_POINTS` of the count measured (an occluder coming or going
    changes what the view shows); else ``(None, None)``: measure them again."""
    view = previous.measured_view if isinstance(previous, PoseEstimate) else None
    if (
        view is None
        or not view.followed
        or view.model != model.key
        or not CARRY_POINTS <= points / max(view.points, 1) <= 1 / CARRY_POINTS
    ):
        return None, None
    then = np.asarray(view.camera_T_object.inverse().as_matrix(), np.float64)
    object_T_camera = np.asarray(
        (SE3(np.asarray(object_T_base, np.float64)) @ frame.base_T_camera).as_matrix()
    )  # fmt: skip
    rays = [m[:3, 3] - np.asarray(model.centroid, np.float64) for m in (then, object_T_camera)]
    cosine = rays[0] @ rays[1] / max(np.linalg.norm(rays[0]) * np.linalg.norm(rays[1]), 1e-12)
    turn = float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
    return (view, round(turn, 2)) if turn <= CARRY_TURN_DEG else (None, None)


def _check_motion(previous: SE3, found, max_motion, max_turn_deg, lifted, symmetry) -> None:
    """``_Failed`` (register) when the answer moved more than ``max_motion`` metres or
    turned more than ``max_turn_deg`` degrees from ``previous`` (a ``symmetry``'s turns are
    no motion)."""
    moved, turned = (
        float(x) for x in pose_error(found.pose, SE3(np.asarray(previous.wxyz_xyz, np.float32)),
                                     symmetry=symmetry)
    )  # fmt: skip
    turned = float(np.degrees(turned))
    if moved > max_motion or turned > max_turn_deg:
        raise _Failed(
            "register",
            f"the answer moved {moved * 1e3:.0f} mm and turned {turned:.0f} deg from the previous "
            f"pose (at most {max_motion * 1e3:.0f} mm and {max_turn_deg:g} deg)",
            found.record, mask=lifted.mask, points=lifted.points,
        )  # fmt: skip
