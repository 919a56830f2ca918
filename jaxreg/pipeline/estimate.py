"""Pixels to pose: segment -> lift -> register, with the evidence for each stage and the stage
to blame when one fails.

:func:`estimate_pose` takes one :class:`~jaxreg.camera.RGBDFrame` and a model (points in the
object's own frame) and returns a :class:`PoseEstimate`: ``base_T_object``, the registration's
fit, the pose's error budget and its total covariance, and per-stage milliseconds and
diagnostics. The stages:

1. **Segment** (:func:`jaxreg.pipeline.segment.segment_frame`): the table plane by RANSAC and the
   clusters standing on it, on a strided grid. Each cluster, and each cluster together with
   the clusters within 1.2 model radii of it (one object split by a thin rim), is a
   candidate if its diameter (largest distance between two of its points) is at most the
   model's plus ``cluster_margin`` (a partial view's centroid lies off the object's centre,
   so its points can lie farther from it than the model's radius); the
   ``max_candidates`` largest are kept, or a ``pixel`` / ``box`` prompt names the seed
   cluster. Given the model's colours (``model_colors``) and a frame with RGB, a cluster whose
   pixels do not show them (by chromaticity, :mod:`jaxreg.pipeline._colour`) is no candidate.
2. **Register, coarse search**: every candidate is registered in one compiled call (the
   starts below, on its grid points) and scored: the fraction of its points the model
   explains (within the final correspondence distance of the segment's tolerances: 1.5
   voxels, or more where the depth noise or the model's sampling ask for it) times the share
   of the model's camera-facing surface that the depth image confirms (:func:`visibility`,
   within 1 cm or 4 sigma_z of the depth noise; seeing through the model, or the model below
   the table, counts against it), at its best coarse pose that keeps its points within the
   model's span (``max_overhang``: a larger object of a similar shape reaches beyond). The
   best candidate wins, those with no such pose last, and every cluster that its coarse pose
   explains (60% of its points within 1 cm) joins it.
3. **Lift**: the winning clusters' footprint at full resolution (their pixels and the depth
   holes between them), its valid-depth fraction, the pixels above the table band, flying
   pixels removed (a pixel needs ``min_consistent_neighbors`` of its 8 neighbours within the
   depth tolerance; a mixed-depth pixel floating between two surfaces has none), lifted
   through the intrinsics and ``base_T_camera`` into the base frame, voxel-downsampled, and
   isolated points removed (fewer than 2 occupied voxels among the 26 around theirs).
4. **Register, refinement**: the segment (source, base frame) is registered into the model (target,
   object frame), so the overlap is the whole segment less its strays, whatever part of the
   object is visible. Starts: the four PCA frames (their sign ambiguities) and a near-uniform
   grid of ``num_starts`` rotations about the centroids, each slid along the line of sight
   until the model's front meets the segment's (a partial view's centroid lies on its visible
   surface), and ``6 * resting_yaws`` starts of the model resting on the table on each of
   its principal half-axes at ``resting_yaws`` headings, slid horizontally to the segment's
   front; multi-start point-to-plane ICP on the grid points with a shrinking
   correspondence distance in three rounds, each on fewer starts (every start takes the
   first two iterations; the starts that then explain most of the segment take
   four more and are judged sparsely; the best few of those take the rest), those starts
   ranked by the score above; the best distinct ones refined
   on the lifted points, trimmed to the overlap the coarse fit measured, and chosen by
   inlier fraction times confirmed share (an upside-down tray fits the segment as well as
   the upright one; the image sees through its floor). Equally good refined poses are
   compared on one symmetry branch when a ``symmetry`` is given (the answer is reported on
   the branch nearest the base axes). An answer whose model has a flat face within
   ``rest_tolerance`` of the table rests on it: it is moved onto the table and settled by ICP
   with contact points on that face (a partial view pins an object's height poorly; the table
   pins it). FPFH + RANSAC starts are not used yet.
5. **Error budget** (:mod:`jaxreg.pipeline._error_sources`): one covariance per source of error, the
   right perturbation of ``base_T_object`` in the object's axes: the depth noise
   (:class:`~jaxreg.uncertainty.DepthNoise`), the fit (the residuals as they are, correlated
   between neighbouring points), the segmentation (the segment re-registered with its border
   eroded or grown and pieces of the visible part dropped, in one vmapped call), the
   calibration the user states (hand-eye, intrinsics, depth scale) and the ambiguity of
   equally good starts that disagree; a continuous symmetry's rotation is free (``inf``).
   Their sum is ``PoseEstimate.covariance``; ``jaxreg.studies.calibration_study`` measures
   how well it covers the real error.

With a ``mask`` from the caller's own segmenter (a learned detector, a mask drawn by hand),
the segment stage takes the mask instead of the clusters
(:func:`~jaxreg.pipeline._segment_stage.segment_stage`): the table plane is fitted outside it
and used when the object stands on it; without one, the coarse search has no resting starts
and the lift no band above a table. Lift and register are the same, and can still refuse.

Each stage is a function that takes what it needs and returns a frozen record of what it
found (:mod:`jaxreg.pipeline.records`); its evidence becomes ``PoseEstimate.stages``.

A stage fails on its own evidence, and the estimate then makes no pose claim (``pose`` is
``None``): no plane or nothing on it, no cluster of the model's size, a mask with too few
points with depth, or segments far smaller or larger than the model (segment; the message
names the units when the model's scale cannot fit the frame's metres); too few
pixels with depth in the footprint, or too few points left after filtering (lift); too small
a fraction of the segment explained by the model, too large a residual, a model that the
depth image contradicts (surface predicted where the camera sees through it), a segment
that spans beyond the model or whose span cannot be measured, a model sunk into the table
or with the segment reaching below it, or a final registration whose
ICP failed (non-finite, too few pairs, or degenerate geometry without a ``symmetry`` to
explain it) (register).

Host-side entry point: bad arguments raise ``ValueError``. The compiled pieces have static
shapes: the segment grid is fixed by the image size and stride, the clouds given to ICP
are padded (or subsampled) to ``max_points``, and the prepared model's arrays are padded to
a few fixed sizes and its symmetry to fixed-shape arrays (:mod:`jaxreg.pipeline._model`), so
a new model (another object, another sampling, another symmetry group) runs the programs
compiled for the one before; only a model that outgrows the first size compiles (once per
size).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, Bool, Float

from jaxreg.camera.model import RGBDFrame
from jaxreg.geometry.metrics import Symmetry
from jaxreg.pipeline._colour import model_palette
from jaxreg.pipeline._error_sources import Calibration
from jaxreg.pipeline._judge import visibility as visibility
from jaxreg.pipeline._lift_stage import lift_stage
from jaxreg.pipeline._model import _prepare_model
from jaxreg.pipeline._register_stage import coarse_search, refine_stage
from jaxreg.pipeline._segment_stage import height_ceiling, segment_stage
from jaxreg.pipeline._stages import _Failed
from jaxreg.pipeline.records import (
    EquivalentPose,
    LiftRecord,
    MeasuredView,
    RegisterRecord,
    SegmentRecord,
)
from jaxreg.pipeline.segment import TablePlane
from jaxreg.pipeline.settings import PipelineSettings
from jaxreg.uncertainty import DepthNoise
from jaxreg.uncertainty.budget import PoseBudget
from jaxreg.uncertainty.calibrated import BudgetCalibration

__all__ = ["PoseEstimate", "estimate_pose", "visibility"]

STAGES = ("segment", "lift", "register")


@dataclasses.dataclass(frozen=True)
class PoseEstimate:
    """The result of :func:`estimate_pose` (host values).

    Attributes:
        pose: ``SE3`` ``base_T_object`` (object/model frame -> base frame), or ``None`` when a
            stage failed (no pose claim).
        inlier_rmse: RMS distance (metres) of the segment points matched to the model at the
            final pose (NaN when registration did not run).
        inlier_fraction: fraction of the segment points within the final correspondence
            distance of the model.
        covariance: ``(6, 6)`` covariance of the right perturbation of ``pose``
            (``T_true = pose @ exp(delta)``, tangent ``(vx, vy, vz, wx, wy, wz)`` in the
            object frame; metres and radians): the total of ``budget``, ``inf`` on the
            diagonal of free axes (``0`` off it), never NaN with a pose; NaN without one.
        failed_stage: ``None``, ``"segment"``, ``"lift"`` or ``"register"``.
        reason: why that stage failed, or a one-line summary of a success.
        stages: ``{stage: record}`` for the stages that ran: a
            :class:`~jaxreg.pipeline.records.SegmentRecord`, ``LiftRecord`` or
            ``RegisterRecord`` (``ms`` and the stage's diagnostics as attributes;
            ``as_dict()`` for JSON).
        mask: ``(H, W)`` bool pixels of the lifted segment (all False if lift did not run).
        points: ``(K, 3)`` base-frame points that were registered (empty if none).
        budget: the :class:`~jaxreg.uncertainty.budget.PoseBudget` (one covariance per
            source of error: depth, fit, segmentation, calibration, ambiguity; the free
            axes), or ``None`` without a pose.
        table: the :class:`~jaxreg.pipeline.segment.TablePlane` the segment stage found
            (base frame), or ``None`` (no table, or the segment stage failed).
        equivalent_poses: turns of the model that fit the view as well as ``pose``
            (:class:`~jaxreg.pipeline.records.EquivalentPose`: a box's half turn, a can seen
            from its side), best first; empty when the view decides, or without a pose. A
            declared ``symmetry``'s copies are not listed (they are the same pose). The
            covariance's ambiguity term holds them, weighted by their evidence.
        measured_view: what the register stage measured of the view beyond the fit
            (:class:`~jaxreg.pipeline.records.MeasuredView`), which :func:`jaxreg.track`
            carries to the next frame while the view changes little; ``None`` without a pose.
    """

    pose: SE3 | None
    inlier_rmse: float
    inlier_fraction: float
    covariance: np.ndarray
    failed_stage: str | None
    reason: str
    stages: dict[str, SegmentRecord | LiftRecord | RegisterRecord]
    mask: np.ndarray
    points: np.ndarray
    budget: PoseBudget | None = None
    table: TablePlane | None = None
    equivalent_poses: tuple[EquivalentPose, ...] = ()
    measured_view: MeasuredView | None = None

    @property
    def success(self) -> bool:
        """True when every stage passed and ``pose`` is a claim."""
        return self.failed_stage is None


def estimate_pose(
    frame: RGBDFrame,
    model_points: Float[Any, "M 3"],
    *,
    mask: Bool[Any, "H W"] | None = None,
    model_normals: Float[Any, "M 3"] | None = None,
    model_colors: Any | None = None,
    symmetry: Symmetry | None = None,
    depth_noise: DepthNoise | None = None,
    hand_eye_covariance: Float[Any, "6 6"] | None = None,
    intrinsics_sigma: Float[Any, " 4"] | None = None,
    depth_scale_sigma: float = 0.0,
    key: Array | None = None,
    pixel: tuple[float, float] | None = None,
    box: tuple[float, float, float, float] | None = None,
    settings: PipelineSettings | None = None,
    progress: Callable[[str], object] | None = None,
    calibration: BudgetCalibration | None = None,
    **keywords,
) -> PoseEstimate:
    """Estimate ``base_T_object`` of a model in one depth frame (see the module docstring).

    Args:
        frame: the depth frame; points are expressed in its base frame.
        model_points: ``(M, 3)`` points on the model's surface in its own frame (metres),
            e.g. :func:`jaxreg.io.load_points` of a mesh or scan.
        mask: ``(H, W)`` bool (or integer, nonzero = object) image of the object's pixels
            from your own segmenter: the table plane and clusters are skipped and the
            object's surface inside the mask is the segment (see
            :func:`~jaxreg.pipeline._segment_stage.segment_stage`); the lift's filters and the
            registration's evidence, which can still refuse, are kept.
        model_normals: ``(M, 3)`` unit normals of the model points pointing out of the
            object (a mesh's face normals), used instead of normals estimated from the
            points; give them for thin-walled objects, whose two faces a point neighbourhood
            mixes. With them every registration pairs the segment's points only with model
            points facing the camera (ICP's ``viewpoint``): a cup's inner face behind the
            outer one the camera saw takes no pairs.
        model_colors: the model's sRGB colours, ``(M, 3)`` (a textured model's vertex
            colours, one per model point) or ``(3,)`` (one paint), floats in [0, 1] or uint8.
            With a frame that has ``rgb``, the table route sets aside the clusters whose
            pixels do not show them (``SegmentRecord.other_color``): a neighbour of the
            model's shape but another colour is then no rival (see
            :mod:`jaxreg.pipeline._colour` and the segment settings' ``color_tolerance``,
            ``min_color_share``).
        symmetry: the model's :class:`~jaxreg.Symmetry`, if any.
        depth_noise: the camera's noise as a :class:`~jaxreg.uncertainty.DepthNoise` in the
            camera frame (its ``base_T_camera`` is replaced by the frame's); default a
            structured-light / stereo camera with ``sigma_z = 2.5e-3 z^2`` (metres).
        hand_eye_covariance: ``(6, 6)`` covariance of the right perturbation of the frame's
            ``base_T_camera`` (camera axes, ``(v, w)``, metres and radians): the hand-eye
            calibration's uncertainty, propagated into the budget's calibration term.
        intrinsics_sigma: ``(4,)`` standard deviations of ``(fx, fy, cx, cy)`` (pixels).
        depth_scale_sigma: relative standard deviation of the depth scale (0.01 = 1%).
        calibration: a :class:`~jaxreg.uncertainty.calibrated.BudgetCalibration` fitted on
            frames of this object and camera (:func:`jaxreg.studies.calibrate`): the budget's
            terms and the covariance are calibrated by it; ``None``: as measured.
        key: PRNG key of the plane hypotheses (default ``PRNGKey(0)``).
        pixel, box: optional prompt ``(u, v)`` or ``(u0, v0, u1, v1)`` (pixels) naming the
            object's cluster instead of scoring every candidate.
        settings: every setting, by stage (:class:`~jaxreg.pipeline.settings.PipelineSettings`;
            default its defaults).
        progress: called with each stage's name as it starts (a command line's progress).
        **keywords: settings by name, changing ``settings`` (``voxel_size=0.003``,
            ``max_inlier_rmse=0.006``; ``lift_min_height`` is the lift's ``min_height``): the
            fields of :class:`~jaxreg.pipeline.settings.SegmentSettings`,
            :class:`~jaxreg.pipeline.settings.LiftSettings` and
            :class:`~jaxreg.pipeline.settings.RegisterSettings`, with their defaults and
            units there.

    Returns:
        :class:`PoseEstimate`.

    Raises:
        ValueError: a frame that is not an ``RGBDFrame`` or whose depth is not in metres, a
            model that is not ``(M, 3)`` finite points in metres, a mask that is not an
            ``(H, W)`` image of the frame with some pixel set, more than one of ``mask``,
            ``pixel``, ``box``, model colours that are not sRGB of the model's shape, or an
            unknown or invalid setting.
    """
    palette = (
        None if model_colors is None else model_palette(model_colors, len(np.asarray(model_points)))
    )
    model_points, model_normals = _checked_model(frame, model_points, model_normals)
    mask = _checked_prompt(frame, mask, pixel, box)
    settings = (settings or PipelineSettings()).replace(**keywords)
    stated = Calibration(hand_eye_covariance, intrinsics_sigma, depth_scale_sigma)
    key = jax.random.PRNGKey(0) if key is None else key
    progress = progress or (lambda stage: None)
    model = _prepare_model(
        model_points, model_normals, settings.voxel_size, float(settings.coarse_distances[0]),
        float(settings.fine_distances.max()),
    )  # fmt: skip
    noise = _noise(depth_noise, frame)
    rng = np.random.default_rng(0)  # the coarse clouds' and the source's subsamples
    records: dict[str, Any] = {}
    plane = None
    try:
        progress("segment")
        segmented = segment_stage(
            frame, model, settings.segment, key, noise, mask=mask, pixel=pixel, box=box,
            lift=settings.lift, palette=palette,
        )
        records["segment"], plane = segmented.record, segmented.plane
        coarse = coarse_search(frame, model, segmented, settings, noise, rng)
        records["register"] = coarse.record
        progress("lift")
        lifted = lift_stage(
            frame, coarse.region, plane, noise, settings.lift, settings.voxel_size,
            height_ceiling(model, settings.segment),
        )  # fmt: skip
        records["lift"] = lifted.record
        progress("register")
        found = refine_stage(
            frame, model, coarse, lifted, plane, settings, noise, symmetry, stated, rng
        )
        records["register"] = found.record
        return calibrated(_found(found, lifted, records, plane), calibration)
    except _Failed as failure:
        return _refused(frame, failure, records, plane)


def calibrated(estimate: PoseEstimate, calibration: BudgetCalibration | None) -> PoseEstimate:
    """``estimate`` with its budget and covariance calibrated (a success; else as it is)."""
    if calibration is None or estimate.budget is None:
        return estimate
    budget = calibration.apply(estimate.budget)
    return dataclasses.replace(estimate, budget=budget, covariance=budget.total)


def _in_order(records: dict[str, Any]) -> dict[str, Any]:
    """The stages' records in :data:`STAGES` order."""
    return {name: records[name] for name in STAGES if name in records}


def _found(found, lifted, records: dict[str, Any], plane) -> PoseEstimate:
    """The estimate of a register stage's answer ``found`` on the ``lifted`` segment."""
    return PoseEstimate(
        found.pose, found.inlier_rmse, found.inlier_fraction, found.budget.total, None,
        found.reason, _in_order(records), lifted.mask, lifted.points, found.budget, plane,
        found.equivalent_poses, found.view,
    )  # fmt: skip


def _refused(frame, failure: _Failed, records: dict[str, Any], plane, prefix="") -> PoseEstimate:
    """The estimate of a stage's ``failure`` (its record joins ``records``): no pose, the
    stage and ``prefix`` + its reason."""
    records[failure.stage] = failure.record
    return PoseEstimate(
        None, float("nan"), float("nan"), np.full((6, 6), np.nan), failure.stage,
        prefix + failure.reason, _in_order(records),
        np.zeros(frame.depth.shape, bool) if failure.mask is None else failure.mask,
        np.zeros((0, 3), np.float32) if failure.points is None else failure.points,
        None, plane,
    )  # fmt: skip


def _checked_model(frame, model_points, model_normals):
    """The model's finite points ``(M, 3)`` float32 and their normals (or ``None``), or
    ``ValueError``: a frame that is not an ``RGBDFrame``, a model that is not ``(M, 3)``
    with some finite point, normals of another shape, or units that cannot be metres."""
    if not isinstance(frame, RGBDFrame):
        raise ValueError(f"frame must be a jaxreg.RGBDFrame, got {type(frame).__name__}")
    model_points = np.asarray(model_points, dtype=np.float32)
    if model_points.ndim != 2 or model_points.shape[1] != 3:
        raise ValueError(f"model_points must be (M, 3), got shape {model_points.shape}")
    finite = np.all(np.isfinite(model_points), axis=1)
    if model_normals is not None:
        model_normals = np.asarray(model_normals, dtype=np.float32)
        if model_normals.shape != model_points.shape:
            raise ValueError(
                f"model_normals must match model_points {model_points.shape}, got "
                f"{model_normals.shape}"
            )
        model_normals = model_normals[finite]
    model_points = model_points[finite]
    if len(model_points) == 0:
        raise ValueError("model_points holds no finite point")
    _check_units(frame, model_points)
    return model_points, model_normals


def _checked_prompt(frame, mask, pixel, box) -> np.ndarray | None:
    """The caller's mask as ``(H, W)`` bool (or ``None``), or ``ValueError`` when more than
    one of ``mask``, ``pixel``, ``box`` is given."""
    if pixel is not None and box is not None:
        raise ValueError("give at most one prompt: pixel=(u, v) or box=(u0, v0, u1, v1)")
    if mask is None:
        return None
    if pixel is not None or box is not None:
        raise ValueError("give a mask or a prompt (pixel, box), not both")
    return _check_mask(mask, frame.depth.shape)


def _check_units(frame: RGBDFrame, model_points: np.ndarray) -> None:
    """``ValueError`` naming the units when the model or the depth cannot be metres: a model
    more than 3 m across (a graspable object in millimetres), or a median depth beyond 20 m
    (a depth camera's image in millimetres)."""
    span = float(np.linalg.norm(np.ptp(model_points, axis=0)))
    if span > 3.0:
        raise ValueError(
            f"model_points span {span:.4g} m across: they must be metres; a model in "
            "millimetres (as CAD files usually are) needs model_points * 0.001 "
            "(jaxreg pose --model-units mm)"
        )
    sample = np.asarray(frame.depth)[::8, ::8]
    sample = sample[np.isfinite(sample)]
    if len(sample) and float(np.median(sample)) > 20.0:
        raise ValueError(
            f"the frame's median depth is {float(np.median(sample)):.4g} m: depth must be "
            "metres; a depth image in millimetres needs depth * 0.001 (read_frame's "
            "depth_scale says what a PNG count is)"
        )


def _check_mask(mask, shape: tuple[int, int]) -> np.ndarray:
    """The caller's mask as ``(H, W)`` bool (nonzero = object), or ``ValueError``."""
    mask = np.asarray(mask)
    if mask.shape != tuple(shape):
        raise ValueError(
            f"mask must be an (H, W) = {tuple(shape)} image like the frame's depth, got shape "
            f"{mask.shape}"
        )
    if mask.dtype != bool and not np.issubdtype(mask.dtype, np.integer):
        raise ValueError(f"mask must be bool or integer (nonzero = object), got {mask.dtype}")
    mask = mask != 0
    if not mask.any():
        raise ValueError("the mask is empty: set the object's pixels (True or nonzero)")
    return mask


def _noise(depth_noise: DepthNoise | None, frame: RGBDFrame) -> DepthNoise:
    """The depth noise in the frame's base frame."""
    if depth_noise is None:
        return DepthNoise((0.0, 0.0, 2.5e-3), frame.base_T_camera)
    return eqx.tree_at(lambda n: n.base_T_camera, depth_noise, frame.base_T_camera)
