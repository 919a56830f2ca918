"""Typed records of :func:`jaxreg.estimate_pose`'s stages: what each stage measured, read by
attribute (``estimate.stages["lift"].valid_depth_fraction``), and :meth:`as_dict` for JSON
(a stage that stopped early leaves its later, optional fields ``None``, and they are left out).

Units are in the field names: ``_mm`` millimetres, ``ms`` milliseconds of wall time; counts
are pixels, grid points (every ``stride``-th pixel of every ``stride``-th row) or points.
"""

from __future__ import annotations

import dataclasses
from typing import Any

__all__ = ["Candidate", "LiftRecord", "RegisterRecord", "SegmentRecord"]


@dataclasses.dataclass(frozen=True)
class _Record:
    def as_dict(self) -> dict[str, Any]:
        """The fields as plain Python (nested records as dicts); optional fields (default
        ``None``) that were not measured are left out."""
        optional = {f.name for f in dataclasses.fields(self) if f.default is None}
        return {
            k: v for k, v in dataclasses.asdict(self).items() if v is not None or k not in optional
        }


@dataclasses.dataclass(frozen=True)
class Candidate(_Record):
    """One candidate segment scored by the coarse registration.

    Attributes:
        clusters: the cluster indices it joins (``[]``: the caller's mask).
        score: ``explained * confirmed share`` of its best coarse pose.
        explained: fraction of its points within 6 mm of the model at that pose.
        contradicted: share of the model's judged surface the image sees through.
        overhang_mm: its largest span beyond the model along a principal axis.
    """

    clusters: list[int]
    score: float
    explained: float
    contradicted: float
    overhang_mm: float


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
        mask_pixels: pixels of the caller's mask (mask route).
        mask_grid_points: of them, grid points with depth (above the table band when there
            is a table) given to the coarse registration (mask route).
        candidates: the candidates scored, best first.
        chosen_clusters: the clusters lifted (table route).
    """

    ms: float
    valid_grid_points: int
    plane_inliers: int | None = None
    plane_inlier_fraction: float | None = None
    above_plane: int | None = None
    cluster_sizes: list[int] | None = None
    cluster_radii_mm: list[float] | None = None
    overflow: bool | None = None
    mask_pixels: int | None = None
    mask_grid_points: int | None = None
    candidates: list[Candidate] | None = None
    chosen_clusters: list[int] | None = None


@dataclasses.dataclass(frozen=True)
class LiftRecord(_Record):
    """The lift stage (:func:`jaxreg.pipeline._lift.lift_region`'s counts).

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
    """The register stage.

    Attributes:
        ms: wall time.
        starts: coarse starts per candidate.
        coarse_kept_starts: coarse poses kept for refinement.
        refined_starts: distinct coarse poses refined on the lifted points.
        trim_fraction: the refinement's trimmed overlap.
        iterations, icp_status: the chosen refinement's ICP iterations and status message.
        inlier_rmse_mm: its residual (``None`` when no segment point is matched).
        inlier_fraction: fraction of the segment within the final correspondence distance.
        equally_good_starts: refined starts as good as the chosen one.
        start_agreement_mm, start_agreement_deg: their largest offset and angle to it.
        model_confirmed, model_contradicted: shares of the model's judged surface the image
            confirms and sees through.
        overhang_mm: the segment's span beyond the model along its three principal axes.
        equally_good_probes: the answer turned about the model's axes and refined again, as
            good as the answer (each widens the ambiguity term of the error budget).
        resting_on_table: whether the answer was settled on the table plane.
        contact_shift_mm: how far settling moved the model's lowest point onto the table.
    """

    ms: float
    starts: int
    coarse_kept_starts: int
    refined_starts: int
    trim_fraction: float
    iterations: int
    icp_status: str
    inlier_rmse_mm: float | None
    inlier_fraction: float
    equally_good_starts: int
    start_agreement_mm: float
    start_agreement_deg: float
    model_confirmed: float
    model_contradicted: float
    overhang_mm: list[float]
    equally_good_probes: int = 0
    resting_on_table: bool = False
    contact_shift_mm: float | None = None
