"""What the stages of :func:`jaxreg.estimate_pose` find. Each stage returns one frozen record of
its output (:class:`Segmented`, :class:`CoarseSearch`, :class:`LiftedSegment`,
:class:`Registration`) holding its evidence record (:class:`SegmentRecord`,
:class:`LiftRecord`, :class:`RegisterRecord`): what the stage measured, read by attribute
(``estimate.stages["lift"].valid_depth_fraction``), and :meth:`as_dict` for JSON (a stage that
stopped early leaves its later, optional fields ``None``, and they are left out).

Units are in the field names: ``_mm`` millimetres, ``ms`` milliseconds of wall time; counts
are pixels, grid points (every ``stride``-th pixel of every ``stride``-th row) or points.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np
from jaxlie import SE3

from jaxreg.pipeline.segment import Segmentation, TablePlane
from jaxreg.uncertainty.budget import PoseBudget

__all__ = [
    "Alternatives", "Candidate", "CoarseSearch", "EquivalentPose", "LiftRecord", "LiftedSegment",
    "MeasuredView", "RegisterRecord", "Registration", "SegmentRecord", "Segmented",
]  # fmt: skip


@dataclasses.dataclass(frozen=True)
class _Record:
    def as_dict(self) -> dict[str, Any]:
        """The fields as plain Python (nested records as dicts); optional fields (default
        ``None``) that were not measured are left out."""
        optional = {f.name for f in dataclasses.fields(self) if f.default is None}
        return {
            k: v for k, v in dataclasses.asdict(self).items() if v is not None or k not in optional
        }

    def with_ms(self, start: float, **changes):
        """This record with ``changes`` and ``ms`` the wall time since ``start``
        (``time.perf_counter()``, to 0.01 ms)."""
        ms = round((time.perf_counter() - start) * 1e3, 2)
        return dataclasses.replace(self, **changes, ms=ms)


@dataclasses.dataclass(frozen=True)
class Candidate(_Record):
    """One candidate segment scored by the coarse registration.

    Attributes:
        clusters: the cluster indices it joins (``[]``: the caller's mask).
        score: ``explained * confirmed share`` of its best coarse pose that keeps the segment
            within ``max_overhang`` of the model's span, or of its best coarse pose when none
            does.
        explained: fraction of its points within the finest correspondence distance (which
            follows the depth noise and the model's sampling) of the model at that pose.
        contradicted: share of the model's judged surface the image sees through.
        overhang_mm: its largest span beyond the model along a principal axis.
        sunk_mm: how far that pose puts the model's lowest point below the table (0 above it
            or without a table).
        underneath_mm: how far its points reach below the model's lowest point at that pose
            (negative: they stay above it; 0 without a table).
    """

    clusters: list[int]
    score: float
    explained: float
    contradicted: float
    overhang_mm: float
    sunk_mm: float
    underneath_mm: float


@dataclasses.dataclass(frozen=True)
class SegmentRecord(_Record):
    """The segment stage: the table plane and clusters (table route), or the caller's mask.

    Attributes:
        ms: wall time.
        plane_inliers, plane_inlier_fraction: grid points on the table plane (and their share
            of the valid ones); with a mask, ``None`` when the frame shows no table under it.
        valid_grid_points: grid points with depth.
        above_plane: grid points in the band above the plane (table route).
        cluster_sizes, cluster_radii_mm: grid points and radius of each cluster (table route).
        overflow: the clustering's capacity overflowed (table route).
        other_color: the clusters set aside as showing other colours than the model's
            (table route, given ``model_colors`` and a frame with RGB; else ``None``).
        stripped_by_color: the clusters whose grid points of another colour (a touching
            neighbour of another paint) were left out of their candidates (same condition).
        mask_pixels: pixels of the caller's mask (mask route).
        surface_pixels: of them, pixels on the object's surface (mask route: with depth, and
            connected to the object by the depth image, not the background behind it or an
            occluder in front).
        mask_grid_points: of them, grid points (above the table band when there is a table):
            the one candidate (mask route).
    """

    ms: float
    valid_grid_points: int
    plane_inliers: int | None = None
    plane_inlier_fraction: float | None = None
    above_plane: int | None = None
    cluster_sizes: list[int] | None = None
    cluster_radii_mm: list[float] | None = None
    overflow: bool | None = None
    other_color: list[int] | None = None
    stripped_by_color: list[int] | None = None
    mask_pixels: int | None = None
    surface_pixels: int | None = None
    mask_grid_points: int | None = None


@dataclasses.dataclass(frozen=True)
class LiftRecord(_Record):
    """The lift stage (:func:`jaxreg.pipeline._lift_stage.lift_region`'s counts).

    Attributes:
        ms: wall time.
        footprint_pixels: pixels of the segment's footprint (with the holes inside it).
        valid_depth_fraction: share of them with depth.
        pixels: pixels kept after the filters.
        flying_pixels_removed, below_band_removed: pixels each filter removed.
        isolated_points_removed: voxels removed as isolated.
        points: base-frame points left to register.
    """

    ms: float
    footprint_pixels: int
    valid_depth_fraction: float
    pixels: int | None = None
    flying_pixels_removed: int | None = None
    below_band_removed: int | None = None
    isolated_points_removed: int | None = None
    points: int | None = None


@dataclasses.dataclass(frozen=True)
class RegisterRecord(_Record):
    """The register stage: the coarse search over the candidates (before the lift), then the
    refinement of the winner (after it; these fields are ``None`` when the lift failed).

    Attributes:
        ms: wall time of both parts.
        starts: coarse starts per candidate.
        candidates: the candidates scored by the coarse search, best first.
        coarse_kept_starts: coarse poses of the winner kept for refinement.
        chosen_clusters: the clusters lifted (table route; ``None`` with a mask).
        refined_starts: distinct coarse poses refined on the lifted points.
        trim_fraction: the refinement's trimmed overlap.
        iterations, icp_status: the chosen refinement's ICP iterations and status message.
        inlier_rmse_mm: its residual (``None`` when no segment point is matched).
        inlier_fraction: fraction of the segment within the final correspondence distance.
        equally_good_starts: refined starts as good as the chosen one.
        start_agreement_mm, start_agreement_deg: their largest offset and angle to it.
        model_confirmed, model_contradicted: shares of the model's judged surface the image
            confirms and sees through (``None`` when the image judges none of it).
        overhang_mm: the span beyond the model, along its three principal axes, of the
            segment's points not explained away (on the model or carrying its surface on).
        sunk_mm: how far the answer puts the model's lowest point below the table (0 above).
        underneath_mm: how far the segment reaches below the answer's lowest point.
        equally_good_probes: the answer turned about the model's axes and refined again, as
            good as the answer (each widens the ambiguity term of the error budget).
        resting_on_table: whether the answer was settled on the table plane.
        contact_shift_mm: how far settling moved the model's lowest point onto the table.
        view_carried_deg: with :func:`jaxreg.track`, how far (degrees) the camera's direction
            in the object's frame has turned since the view's terms were measured, when they
            were carried from the previous estimate (:class:`MeasuredView`); ``None`` when
            they were measured on this frame.
        explained_away: segment points the answer's model does not explain and that do not
            carry its surface on (a neighbour, the background, an occluder).
        runs_on: segment points that carry the model's surface on past its edge.
        hypothesis: base_T_object (4 x 4 nested list, metres) of the best fit the stage
            judged, refused or not (``None`` before the refinement): what a refused estimate
            tried, to draw or inspect.
    """

    ms: float
    starts: int
    candidates: list[Candidate]
    coarse_kept_starts: int
    chosen_clusters: list[int] | None = None
    refined_starts: int | None = None
    trim_fraction: float | None = None
    iterations: int | None = None
    icp_status: str | None = None
    inlier_rmse_mm: float | None = None
    inlier_fraction: float | None = None
    equally_good_starts: int | None = None
    start_agreement_mm: float | None = None
    start_agreement_deg: float | None = None
    model_confirmed: float | None = None
    model_contradicted: float | None = None
    overhang_mm: list[float] | None = None
    sunk_mm: float | None = None
    underneath_mm: float | None = None
    equally_good_probes: int | None = None
    resting_on_table: bool | None = None
    contact_shift_mm: float | None = None
    view_carried_deg: float | None = None
    explained_away: int | None = None
    runs_on: int | None = None
    hypothesis: list[list[float]] | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class EquivalentPose:
    """A turn of the model that fits the view as well as the answer: depth alone cannot tell
    it from the answer (a box's half turn, a can seen from its side).

    Attributes:
        pose: ``base_T_object`` of the turned answer, refined.
        axis: ``(3,)`` the axis of the turn (object frame, unit): the model's principal axis
            a probe was turned about, or the axis of a refined start's rotation from the answer.
        angle_deg: the turn (degrees): a probe's before refinement, a refined start's after.
        score: its explained share times the image's confirmed share (the answer's evidence).
        inlier_rmse: its residual (metres).
        weight: how likely it is against the answer (1: the evidence cannot prefer either;
            ``exp(-gap^2 / 2)`` with ``gap`` its shortfall in standard errors; 1 for a turn
            under which the model matches itself within the fit's residual gate (a box's half
            turn, a can's spin) whose fit passes the answer's gates: their fits differ where
            the model's surface differs from the object's, not by the pose).
    """

    pose: SE3
    axis: np.ndarray
    angle_deg: float
    score: float
    inlier_rmse: float
    weight: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: the pose as a 4x4 list, lengths in millimetres."""
        return {
            "pose": np.asarray(self.pose.as_matrix()).tolist(),
            "axis": [round(float(a), 4) for a in self.axis],
            "angle_deg": round(self.angle_deg, 1),
            "score": round(self.score, 3),
            "inlier_rmse_mm": round(self.inlier_rmse * 1e3, 3),
            "weight": round(self.weight, 3),
        }


# --------------------------------------------------------------------------------------------
# What each stage returns.


@dataclasses.dataclass(frozen=True, eq=False)
class Segmented:
    """The segment stage's output.

    Attributes:
        plane: the table plane (base frame), or ``None`` (a mask on an object not standing on
            a table, or a frame without one).
        candidates: ``(clusters, cloud)`` per candidate segment: the cluster indices it joins
            (``()``: the caller's mask) and its grid points ``(N, 3)`` (base frame, metres).
        clusters: the table route's :class:`~jaxreg.pipeline.segment.Segmentation` (labels,
            points, footprints), or ``None`` with a mask.
        mask: the caller's mask ``(H, W)`` bool, or ``None`` on the table route.
        record: the stage's evidence.
        palette: on the table route with the model's colours, their chromaticities
            ``(K, 2)`` (:func:`~jaxreg.pipeline._colour.model_palette`): the winner's region
            keeps only its pixels of the model's colours; else ``None``.
        bounds: ``(H, W)`` bool, the pixels of a ``box`` prompt: the winner's region keeps
            only those; else ``None``.
    """

    plane: TablePlane | None
    candidates: list[tuple[tuple[int, ...], np.ndarray]]
    clusters: Segmentation | None
    mask: np.ndarray | None
    record: SegmentRecord
    palette: np.ndarray | None = None
    bounds: np.ndarray | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class CoarseSearch:
    """The register stage's coarse search over the candidates.

    Attributes:
        region: ``(H, W)`` bool footprint to lift (the winner with the clusters its coarse
            pose explains, or the caller's mask).
        poses: ``(K, 7)`` the winner's coarse poses, ``object_T_base`` wxyz_xyz, best first.
        explained: fraction of the winner's points its best coarse pose explains.
        tolerances: the register stage's distances and gates for the segment's depth
            (:class:`~jaxreg.pipeline._register_stage.Tolerances`).
        record: the register stage's record so far (its coarse part).
        border: pixels of ``region``'s border that may hold what borders the object (a
            caller's mask's ``SegmentSettings.mask_border``; 0 for clusters).
    """

    region: np.ndarray
    poses: np.ndarray
    explained: float
    tolerances: Any
    record: RegisterRecord
    border: int = 0


@dataclasses.dataclass(frozen=True, eq=False)
class LiftedSegment:
    """The lift stage's output.

    Attributes:
        mask: ``(H, W)`` bool pixels lifted (after the filters).
        points: ``(K, 3)`` float32 base-frame points (voxelled, isolated points removed).
        record: the stage's evidence.
    """

    mask: np.ndarray
    points: np.ndarray
    record: LiftRecord


@dataclasses.dataclass(frozen=True, eq=False)
class Registration:
    """The register stage's answer.

    Attributes:
        pose: ``base_T_object``.
        inlier_rmse, inlier_fraction: the final fit's residual (metres) and share of the
            segment explained.
        budget: the pose's error budget.
        reason: a one-line summary of the success.
        record: the register stage's whole record.
        equivalent_poses: the turns of the model that fit the view as well.
        view: what the stage measured of the view (or carried from the previous frame).
    """

    pose: SE3
    inlier_rmse: float
    inlier_fraction: float
    budget: PoseBudget
    reason: str
    record: RegisterRecord
    equivalent_poses: tuple[EquivalentPose, ...] = ()
    view: MeasuredView | None = None


@dataclasses.dataclass(frozen=True, eq=False)
class Alternatives:
    """What fits the view as well as the register stage's answer.

    Attributes:
        pose: ``(7,)`` the reported ``base_T_object`` (the answer on its symmetry branch).
        spread: ``(2,)`` the largest offset (metres) and angle (degrees) of the equally good
            refined starts from it.
        equal_starts: ``(S,)`` bool the refined starts as good as the answer.
        equal_probes: ``(P,)`` bool the probes as good as the answer.
        tangents, weights: ``(A, 6)`` the starts and probes that fit about as well, as right
            perturbations of ``pose`` (object axes), and their weights (``exp(-gap^2/2)``,
            :func:`~jaxreg.pipeline._judge.evidence_gap`): the budget's ambiguity term.
        view_free, view_reason: the rotation axes the view leaves free (``(6,)`` bool) and
            why.
        equivalent: the distinct turned answers as good as the answer (or turns under which
            the model matches itself).
    """

    pose: np.ndarray
    spread: np.ndarray
    equal_starts: np.ndarray
    equal_probes: np.ndarray
    tangents: np.ndarray
    weights: np.ndarray
    view_free: np.ndarray
    view_reason: str | None
    equivalent: tuple[EquivalentPose, ...]


@dataclasses.dataclass(frozen=True, eq=False)
class MeasuredView:
    """What the register stage measured of the view beyond the fit itself, the costly part of
    an answer (the answer turned about the model's axes and refined again, the segment
    re-registered with its membership perturbed). While the camera's view of the object
    changes little these stay what they were, so :func:`jaxreg.track` carries them from the
    previous estimate instead of measuring them again on every frame.

    They are carried only when a track step measured them: a track step registers the pixels
    that agree with the model's projection, while :func:`jaxreg.estimate_pose` registers a
    table cluster or the caller's mask, and the probes find a different set of equally good
    turns on the two.

    Attributes:
        model: identifies the model (its points and normals) and the settings they were
            measured with: they are carried only to the same.
        pose: ``base_T_object`` where they were measured.
        camera_T_object: the pose in the camera's frame there.
        points: the segment points registered there.
        alternatives: what fit the view as well as the answer there.
        segmentation: ``(6, 6)`` the budget's segmentation term (object axes).
        segmentation_unknown: why that term could not be computed, or ``None``.
        followed: measured by a :func:`jaxreg.track` step, on the pixels that agree with the
            model's projection (the only kind it carries).
    """

    model: tuple
    pose: SE3
    camera_T_object: SE3
    points: int
    alternatives: Alternatives
    segmentation: np.ndarray
    segmentation_unknown: str | None
    followed: bool = False
