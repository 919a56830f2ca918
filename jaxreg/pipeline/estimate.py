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
   cluster. Every candidate is scored by registration in one compiled call (below, on its
   grid points): the fraction of its points the model explains (within 1.5 voxels, 6 mm at
   the default voxel) times the share of the model's camera-facing surface that the depth
   image confirms (:func:`visibility`, within 1 cm or 4 sigma_z of the depth noise; seeing
   through the model, or the model below the table, counts against it). The best candidate
   wins, unless its points span beyond the model at its coarse pose (``max_overhang``: a
   larger object of a similar shape), and every cluster that its coarse pose explains (60%
   of its points within 1 cm) joins it.
2. **Lift**: the winning clusters' footprint at full resolution (their pixels and the depth
   holes between them), its valid-depth fraction, the pixels above the table band, flying
   pixels removed (a pixel needs ``min_consistent_neighbors`` of its 8 neighbours within the
   depth tolerance; a mixed-depth pixel floating between two surfaces has none), lifted
   through the intrinsics and ``base_T_camera`` into the base frame, voxel-downsampled, and
   isolated points removed (fewer than 2 occupied voxels among the 26 around theirs).
3. **Register**: the segment (source, base frame) is registered into the model (target,
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
4. **Error budget** (:mod:`jaxreg.pipeline._budget`): one covariance per source of error, the
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
(:func:`~jaxreg.pipeline._segment_stage.segment_mask`): the table plane is fitted outside it
and used when the object stands on it; without one, the coarse search has no resting starts
and the lift no band above a table. Lift and register are the same, and can still refuse.

A stage fails on its own evidence, and the estimate then makes no pose claim (``pose`` is
``None``): no plane or nothing on it, no cluster of the model's size, a mask with too few
points with depth, or segments far smaller or larger than the model (segment; the message
names the units when the model's scale cannot fit the frame's metres); too few
pixels with depth in the footprint, or too few points left after filtering (lift); too small
a fraction of the segment explained by the model, too large a residual, a model that the
depth image contradicts (surface predicted where the camera sees through it), a segment
that spans beyond the model or whose span cannot be measured, or a final registration whose
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
from jaxreg.pipeline._budget import Calibration
from jaxreg.pipeline._lift import lift_stage
from jaxreg.pipeline._model import _prepare_model
from jaxreg.pipeline._records import LiftRecord, RegisterRecord, SegmentRecord
from jaxreg.pipeline._refine import refine_stage
from jaxreg.pipeline._register_stage import visibility as visibility
from jaxreg.pipeline._segment_stage import segment_mask, segment_table
from jaxreg.pipeline._settings import _Failed, _Settings
from jaxreg.pipeline.segment import TablePlane
from jaxreg.uncertainty import DepthNoise
from jaxreg.uncertainty.budget import PoseBudget

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
            :class:`~jaxreg.pipeline._records.SegmentRecord`, ``LiftRecord`` or
            ``RegisterRecord`` (``ms`` and the stage's diagnostics as attributes;
            ``as_dict()`` for JSON).
        mask: ``(H, W)`` bool pixels of the lifted segment (all False if lift did not run).
        points: ``(K, 3)`` base-frame points that were registered (empty if none).
        budget: the :class:`~jaxreg.uncertainty.budget.PoseBudget` (one covariance per
            source of error: depth, fit, segmentation, calibration, ambiguity; the free
            axes), or ``None`` without a pose.
        table: the :class:`~jaxreg.pipeline.segment.TablePlane` the segment stage found
            (base frame), or ``None`` (no table, or the segment stage failed).
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

    @property
    def success(self) -> bool:
        """True when every stage passed and ``pose`` is a claim."""
        return self.failed_stage is None


# --------------------------------------------------------------------------------------------
# The stages. Each records its diagnostics in ``stages[name]`` (a typed record) and raises
# ``_Failed`` when its evidence says there is no pose to claim.


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


def estimate_pose(
    frame: RGBDFrame,
    model_points: Float[Any, "M 3"],
    *,
    mask: Bool[Any, "H W"] | None = None,
    model_normals: Float[Any, "M 3"] | None = None,
    symmetry: Symmetry | None = None,
    depth_noise: DepthNoise | None = None,
    hand_eye_covariance: Float[Any, "6 6"] | None = None,
    intrinsics_sigma: Float[Any, " 4"] | None = None,
    depth_scale_sigma: float = 0.0,
    key: Array | None = None,
    pixel: tuple[float, float] | None = None,
    box: tuple[float, float, float, float] | None = None,
    voxel_size: float = 0.004,
    stride: int = 4,
    plane_distance: float = 0.008,
    min_height: float = 0.01,
    lift_min_height: float = 0.003,
    cluster_distance: float = 0.015,
    cluster_margin: float = 0.02,
    max_candidates: int = 4,
    num_starts: int = 24,
    resting_yaws: int = 8,
    coarse_points: int = 128,
    coarse_screen: int = 2,
    coarse_survivors: int = 24,
    coarse_first: int = 6,
    coarse_keep: int = 6,
    max_points: int = 768,
    min_segment_points: int = 30,
    min_valid_fraction: float = 0.5,
    min_consistent_neighbors: int = 3,
    min_inlier_fraction: float = 0.7,
    max_inlier_rmse: float = 0.004,
    max_contradicted: float = 0.25,
    max_overhang: float = 0.003,
    rest_tolerance: float = 0.015,
    refined_starts: int = 4,
    progress: Callable[[str], object] | None = None,
) -> PoseEstimate:
    """Estimate ``base_T_object`` of a model in one depth frame (see the module docstring).

    Args:
        frame: the depth frame; points are expressed in its base frame.
        model_points: ``(M, 3)`` points on the model's surface in its own frame (metres),
            e.g. :func:`jaxreg.io.load_points` of a mesh or scan.
        mask: ``(H, W)`` bool (or integer, nonzero = object) image of the object's pixels
            from your own segmenter: the table plane and clusters are skipped (see
            :func:`~jaxreg.pipeline._segment_stage.segment_mask`); the lift's filters and
            the registration's evidence, which can still refuse, are kept.
        model_normals: ``(M, 3)`` unit normals of the model points (a mesh's face normals),
            used instead of normals estimated from the points; give them for thin-walled
            objects, whose two faces a point neighbourhood mixes.
        symmetry: the model's :class:`~jaxreg.Symmetry`, if any.
        depth_noise: the camera's noise as a :class:`~jaxreg.uncertainty.DepthNoise` in the
            camera frame (its ``base_T_camera`` is replaced by the frame's); default a
            structured-light / stereo camera with ``sigma_z = 2.5e-3 z^2`` (metres).
        hand_eye_covariance: ``(6, 6)`` covariance of the right perturbation of the frame's
            ``base_T_camera`` (camera axes, ``(v, w)``, metres and radians): the hand-eye
            calibration's uncertainty, propagated into the budget's calibration term.
        intrinsics_sigma: ``(4,)`` standard deviations of ``(fx, fy, cx, cy)`` (pixels).
        depth_scale_sigma: relative standard deviation of the depth scale (0.01 = 1%).
        key: PRNG key of the plane hypotheses (default ``PRNGKey(0)``).
        pixel, box: optional prompt ``(u, v)`` or ``(u0, v0, u1, v1)`` (pixels) naming the
            object's cluster instead of scoring every candidate.
        voxel_size: voxel of the lifted segment and the model (metres).
        stride, plane_distance, min_height, cluster_distance: see
            :func:`jaxreg.pipeline.segment.segment_frame`.
        lift_min_height: the lifted segment keeps points this high above the plane (metres;
            lower than ``min_height``: the table is no longer a cluster's neighbour here,
            and a low part such as a tray's floor pins the object's height).
        cluster_margin: a candidate cluster's diameter may exceed the model's by this
            (metres).
        max_candidates: clusters scored by registration.
        num_starts: rotation-grid starts of the coarse registration (plus 4 PCA starts).
        resting_yaws: headings of the starts resting on the table on each of the model's six
            principal half-axes (``6 * resting_yaws`` more starts; 0: none).
        coarse_points: grid points of a candidate given to the coarse registration (static).
        coarse_screen: coarse ICP iterations (of 20) that every start takes.
        coarse_survivors: distinct starts per candidate (those whose model explains most of
            the candidate after ``coarse_screen`` iterations) that go on to ``coarse_first``
            iterations and are judged against the depth image (sparsely).
        coarse_first: coarse ICP iterations of the survivors.
        coarse_keep: distinct survivors per candidate (the best after ``coarse_first``
            iterations) that take the remaining coarse iterations and are judged against the
            depth image at full density.
        max_points: cloud size given to ICP (static; larger segments are subsampled).
        min_segment_points: fewest lifted points worth registering.
        min_valid_fraction: fewest pixels with depth in the footprint, as a fraction.
        min_consistent_neighbors: flying-pixel test (of 8 neighbours).
        min_inlier_fraction, max_inlier_rmse, max_contradicted: the registration's evidence
            that the model is there (fraction of segment points explained, their RMS
            distance in metres, share of the model's judged surface the image sees through).
        max_overhang: how far (metres) the segment may span beyond the model along one of
            the model's principal axes at the fitted pose (between its 2% and 98%
            quantiles; depth noise): a larger object of a similar shape fits the model well
            by every other measure, but reaches beyond it.
        rest_tolerance: an answer whose model has a flat face within this distance (metres)
            of the table, facing it, rests there: it is moved onto the table and settled by
            ICP with contact points on the face (a partial view pins an object's height
            poorly; the table pins it). 0 turns this off.
        refined_starts: distinct coarse poses of the winning candidate refined on the lifted
            points (the best first; each differs from the others by 1 cm or 0.2 rad).
        progress: called with each stage's name as it starts (a command line's progress).

    Returns:
        :class:`PoseEstimate`.

    Raises:
        ValueError: a frame that is not an ``RGBDFrame`` or whose depth is not in metres, a
            model that is not ``(M, 3)`` finite points in metres, a mask that is not an
            ``(H, W)`` image of the frame with some pixel set, or more than one of ``mask``,
            ``pixel``, ``box``.
    """
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
    if pixel is not None and box is not None:
        raise ValueError("give at most one prompt: pixel=(u, v) or box=(u0, v0, u1, v1)")
    if not (isinstance(refined_starts, int) and 1 <= refined_starts <= coarse_keep):
        raise ValueError(
            f"refined_starts must be an integer from 1 to coarse_keep ({coarse_keep}), got "
            f"{refined_starts!r}"
        )
    calibration = Calibration(hand_eye_covariance, intrinsics_sigma, depth_scale_sigma)
    if mask is not None:
        if pixel is not None or box is not None:
            raise ValueError("give a mask or a prompt (pixel, box), not both")
        mask = _check_mask(mask, frame.depth.shape)
    key = jax.random.PRNGKey(0) if key is None else key
    progress = progress or (lambda stage: None)
    settings = _Settings(
        pixel=pixel,
        box=box,
        voxel_size=voxel_size,
        stride=stride,
        plane_distance=plane_distance,
        min_height=min_height,
        lift_min_height=lift_min_height,
        cluster_distance=cluster_distance,
        cluster_margin=cluster_margin,
        max_candidates=max_candidates,
        num_starts=num_starts,
        resting_yaws=resting_yaws,
        coarse_points=coarse_points,
        coarse_screen=coarse_screen,
        coarse_survivors=coarse_survivors,
        coarse_first=coarse_first,
        coarse_keep=coarse_keep,
        max_points=max_points,
        min_segment_points=min_segment_points,
        min_valid_fraction=min_valid_fraction,
        min_consistent_neighbors=min_consistent_neighbors,
        min_inlier_fraction=min_inlier_fraction,
        max_inlier_rmse=max_inlier_rmse,
        max_contradicted=max_contradicted,
        max_overhang=max_overhang,
        rest_tolerance=rest_tolerance,
        refined_starts=refined_starts,
    )
    model = _prepare_model(
        model_points, model_normals, voxel_size, float(settings.coarse_distances[0]),
        float(settings.fine_distances.max()),
    )  # fmt: skip
    noise = _noise(depth_noise, frame)
    stages: dict[str, Any] = {}
    rng = np.random.default_rng(0)  # the coarse clouds' and the source's subsamples
    plane = None
    try:
        progress("segment")
        if mask is None:
            found = segment_table(frame, model, settings, key, rng, stages, noise)
        else:
            found = segment_mask(frame, model, settings, mask, key, rng, stages, noise)
        plane, region, coarse_poses, coarse_fraction = found
        progress("lift")
        lifted, points = lift_stage(frame, region, plane, noise, settings, stages)
        progress("register")
        pose, rmse, fraction, budget, reason = refine_stage(
            frame, plane, model, settings, coarse_poses, coarse_fraction, lifted, points, noise,
            symmetry, calibration, rng, stages,
        )  # fmt: skip
        return PoseEstimate(
            pose, rmse, fraction, budget.total, None, reason, stages, lifted, points, budget, plane
        )
    except _Failed as failure:
        return PoseEstimate(
            None, float("nan"), float("nan"), np.full((6, 6), np.nan), failure.stage,
            failure.reason, stages,
            np.zeros(frame.depth.shape, bool) if failure.mask is None else failure.mask,
            np.zeros((0, 3), np.float32) if failure.points is None else failure.points,
            None, plane,
        )  # fmt: skip


def _noise(depth_noise: DepthNoise | None, frame: RGBDFrame) -> DepthNoise:
    """The depth noise in the frame's base frame."""
    if depth_noise is None:
        return DepthNoise((0.0, 0.0, 2.5e-3), frame.base_T_camera)
    return eqx.tree_at(lambda n: n.base_T_camera, depth_noise, frame.base_T_camera)
