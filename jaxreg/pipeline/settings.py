"""The settings of :func:`jaxreg.estimate_pose`, grouped by the stage that reads them: frozen
records with documented defaults (metres, counts, fractions). ``estimate_pose`` takes them as
``settings=PipelineSettings(...)`` or as its keywords (``voxel_size=0.003``), which fill the
group that holds the name.

Counts that size compiled programs (``coarse_points``, ``max_points``, ``max_candidates``,
``num_starts``, ``resting_yaws``, ``coarse_survivors``, ``coarse_keep``) are static: a new value
compiles the pipeline's programs once more.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["LiftSettings", "PipelineSettings", "RegisterSettings", "SegmentSettings"]


@dataclasses.dataclass(frozen=True)
class SegmentSettings:
    """The segment stage (:func:`jaxreg.pipeline.segment.segment_frame` and the candidates).

    Attributes:
        stride: every ``stride``-th pixel of every ``stride``-th row is a grid point.
        plane_distance: table-plane inlier distance (metres).
        min_height: a grid point belongs to a cluster this high above the plane (metres).
        max_height: grid points higher than this above the plane (metres) are ignored
            (walls, people, the robot), and the lift keeps the segment below it; raised to
            the model's diameter plus ``cluster_margin`` when the model is taller, so a
            target is never cut.
        cluster_distance: grid points nearer than this (metres) join one cluster.
        min_cluster_size: a cluster is a candidate, alone or grouped with the clusters near it,
            when it holds this many grid points, or half of those the model's smallest
            silhouette (its two shorter extents) covers at the cluster's depth where that is
            fewer: a marker 18 mm across standing 1 m from the camera keeps about ten. Never
            fewer than
            :data:`~jaxreg.pipeline._segment_stage.FEWEST_GRID_POINTS`.
        cluster_margin: a candidate's diameter may exceed the model's by this (metres): a
            partial view's points can lie farther from its centroid than the model's radius.
        max_candidates: the largest clusters (by grid points) scored by registration.
        color_tolerance: with the model's colours (``model_colors``) and the frame's RGB, a
            pixel shows a model colour when its chromaticity (red and green shares of the
            sRGB sum) lies within this of one of the model's (:mod:`jaxreg.pipeline._colour`):
            about three times the spread of an 8-bit camera pixel's chromaticity at mid
            brightness (two counts of noise per channel); raise it for a camera whose white
            balance or colour noise moves one paint's chromaticity more.
        min_color_share: a cluster whose judged pixels show the model's colours less often
            than this is another object, and no candidate (a look-alike of another paint).
        mask_border: pixels of a caller's mask's border that may hold what borders the
            object (a network's or a hand label's mask misses the silhouette by 2-5 pixels):
            a surface the mask holds there that carries on outside it is a neighbour's, and
            does not run the model's surface on.
    """

    stride: int = 4
    plane_distance: float = 0.008
    min_height: float = 0.01
    max_height: float = 0.5
    cluster_distance: float = 0.015
    min_cluster_size: int = 15
    cluster_margin: float = 0.02
    max_candidates: int = 4
    color_tolerance: float = 0.03
    min_color_share: float = 0.3
    mask_border: int = 5

    def __post_init__(self):
        if self.min_cluster_size < 1:
            raise ValueError(
                f"min_cluster_size must be 1 grid point or more, got {self.min_cluster_size!r}"
            )
        if self.mask_border < 0:
            raise ValueError(f"mask_border must be 0 or more pixels, got {self.mask_border!r}")
        if not 0.0 < self.color_tolerance < 1.0 or not 0.0 <= self.min_color_share <= 1.0:
            raise ValueError(
                "color_tolerance must lie in (0, 1) and min_color_share in [0, 1], got "
                f"{self.color_tolerance!r} and {self.min_color_share!r}"
            )


@dataclasses.dataclass(frozen=True)
class LiftSettings:
    """The lift stage (:func:`jaxreg.pipeline._lift_stage.lift_region`).

    Attributes:
        min_height: the lifted segment keeps points this high above the table (metres; lower
            than the segment's: a low part such as a tray's floor pins the object's height).
        band_sigmas: and at least this many standard deviations of the depth noise at each
            point's depth: the table's own pixels at a footprint's edge (a mask that bleeds
            onto it, the depth holes between clusters) scatter above a fixed band where the
            noise is larger than it (a far object), and would widen the segment.
        min_valid_fraction: fewest pixels with depth in the segment's footprint, as a fraction.
        min_consistent_neighbors: a pixel needs this many of its 8 neighbours within the
            depth tolerance (a mixed-depth pixel floating between two surfaces has none).
        min_segment_points: fewest lifted points worth registering.
    """

    min_height: float = 0.003
    band_sigmas: float = 3.0
    min_valid_fraction: float = 0.5
    min_consistent_neighbors: int = 3
    min_segment_points: int = 30


@dataclasses.dataclass(frozen=True)
class RegisterSettings:
    """The register stage: the coarse search over the candidates, the refinement of the
    winner and the evidence that may refuse it.

    Attributes:
        num_starts: rotation-grid starts of the coarse search (plus the 4 PCA frames).
        resting_yaws: headings of the starts resting on the table on each of the model's six
            principal half-axes (``6 * resting_yaws`` more starts; 0: none).
        coarse_points: grid points of a candidate given to the coarse search.
        coarse_screen: coarse ICP iterations (of 20) that every start takes.
        coarse_survivors: starts per candidate (those whose model explains most of it after
            ``coarse_screen`` iterations) that go on to ``coarse_first`` iterations and are
            judged against the depth image sparsely.
        coarse_first: the coarse iteration after which the survivors are judged (of 20).
        coarse_keep: distinct survivors per candidate that take the remaining coarse
            iterations and are judged against the depth image at full density.
        max_points: cloud size given to ICP (larger segments are subsampled).
        refined_starts: distinct coarse poses of the winner refined on the lifted points
            (the best first; each differs from the others by 1 cm or 0.2 rad); 1 to
            ``coarse_keep``.
        rest_tolerance: an answer whose model has a flat face within this distance (metres)
            of the table, facing it, is moved onto the table and settled there; 0 turns this
            off.
        min_inlier_fraction: fewest segment points the model must explain (within the final
            correspondence distance, which follows the depth noise at the segment's depth
            and the model's sampling), as a fraction of those it explains or whose surface
            carries the model's on past its edge; the others (a touching neighbour, the
            background or an occluder a mask or box holds) are explained away.
        max_inlier_rmse: largest RMS distance (metres) of the explained segment points;
            ``None``: 1.5 times what the depth noise at the segment's depth, the model's
            sampling and the model-sensor mismatch explain
            (:func:`~jaxreg.pipeline._register_stage.tolerances`).
        min_confirmed: smallest share of the model's judged surface (facing the camera,
            where the image has depth) the image must confirm: the rest is seen through or
            hidden by an occluder. With no judged surface at all the pose is refused.
        max_contradicted: largest share of the model's judged surface the image may see
            through.
        min_seen: smallest share of the model's surface facing the camera and hidden by
            nothing nearer that the image confirms, where the parts outside the image or over
            depth holes count as unconfirmed: a corner of the model in view (the rest cut off
            by the image's edge or lost to holes) fits the corner of many objects.
        max_overhang: how far (metres) a candidate's segment may span beyond the model along
            one of its principal axes at a coarse or rival pose (2% to 98% quantiles, which
            hold the depth noise's tails), in the coarse search's ranking and the contest
            between separate segments: a larger object of a similar shape fits well by every
            other measure but reaches beyond the model. There, the model may reach this far
            into the table, and the segment this far below the model, or 4 sigma_z of the
            depth noise at the segment's depth where that is more.
        false_refusal: the chance (one-sided, per test) that a test of the answer against
            the frame's physical evidence refuses a right pose when the depth noise model
            holds (:mod:`jaxreg.pipeline._evidence`): the segment carrying the model's
            surface on past its edge, the model sunk into the table, the segment below the
            model, each allowed this tail of its standard deviation (0.001: 3.1 sigma).
    """

    num_starts: int = 24
    resting_yaws: int = 8
    coarse_points: int = 128
    coarse_screen: int = 2
    coarse_survivors: int = 24
    coarse_first: int = 6
    coarse_keep: int = 6
    max_points: int = 768
    refined_starts: int = 4
    rest_tolerance: float = 0.015
    min_inlier_fraction: float = 0.7
    max_inlier_rmse: float | None = None
    min_confirmed: float = 0.2
    max_contradicted: float = 0.25
    min_seen: float = 0.2
    max_overhang: float = 0.003
    false_refusal: float = 0.001

    def __post_init__(self):
        if not 0.0 < self.false_refusal < 0.5:
            raise ValueError(f"false_refusal must lie in (0, 0.5), got {self.false_refusal!r}")
        count = self.refined_starts
        if not (isinstance(count, int) and 1 <= count <= self.coarse_keep):
            raise ValueError(
                f"refined_starts must be an integer from 1 to coarse_keep ({self.coarse_keep}), "
                f"got {self.refined_starts!r}"
            )


@dataclasses.dataclass(frozen=True)
class PipelineSettings:
    """Every setting of :func:`jaxreg.estimate_pose`, by stage.

    Attributes:
        voxel_size: voxel (metres) of the lifted segment and of the model; the refinement's
            last correspondence distance is 1.5 voxels.
        segment, lift, register: the stages' settings.
    """

    voxel_size: float = 0.004
    segment: SegmentSettings = SegmentSettings()
    lift: LiftSettings = LiftSettings()
    register: RegisterSettings = RegisterSettings()

    @property
    def coarse_distances(self) -> np.ndarray:
        """The coarse search's correspondence distances (metres, 40 mm down to 10 mm, 20)."""
        return np.geomspace(0.04, 0.01, 20).astype(np.float32)

    @property
    def fine_distances(self) -> np.ndarray:
        """The refinement's correspondence distances (metres, 15 mm down to 1.5 voxels, 30)."""
        return np.geomspace(0.015, 1.5 * self.voxel_size, 30).astype(np.float32)

    def replace(self, **keywords) -> PipelineSettings:
        """These settings with ``keywords`` changed, each a field of one group (the lift's
        ``min_height`` is ``lift_min_height`` here, the segment's keeps its name) or
        ``voxel_size``; ``ValueError`` names a keyword no group has."""
        groups = {"segment": {}, "lift": {}, "register": {}}
        top = {}
        for name, value in keywords.items():
            if name == "voxel_size":
                top[name] = value
            elif name == "lift_min_height":
                groups["lift"]["min_height"] = value
            elif name in _FIELDS["segment"]:
                groups["segment"][name] = value
            elif name in _FIELDS["lift"] and name != "min_height":
                groups["lift"][name] = value
            elif name in _FIELDS["register"]:
                groups["register"][name] = value
            else:
                raise ValueError(
                    f"estimate_pose got an unknown setting {name!r}; the settings are "
                    f"voxel_size, lift_min_height and the fields of SegmentSettings, "
                    f"LiftSettings and RegisterSettings"
                )
        return dataclasses.replace(
            self, **top,
            **{g: dataclasses.replace(getattr(self, g), **kw) for g, kw in groups.items() if kw},
        )  # fmt: skip


_FIELDS = {
    "segment": {f.name for f in dataclasses.fields(SegmentSettings)},
    "lift": {f.name for f in dataclasses.fields(LiftSettings)},
    "register": {f.name for f in dataclasses.fields(RegisterSettings)},
}
