"""Pixels to pose: segment -> lift -> register, with the evidence for each stage and the stage
to blame when one fails.

:func:`estimate_pose` takes one :class:`~jaxreg.camera.RGBDFrame` and a model (points in the
object's own frame) and returns a :class:`PoseEstimate`: ``base_T_object``, the registration's
fit, the covariance of the pose under the depth camera's noise, and per-stage milliseconds and
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
   the branch nearest the base axes); their disagreement is a diagnostic. The covariance is
   :func:`jaxreg.icp_covariance` of the final registration with the depth noise
   (:class:`~jaxreg.uncertainty.DepthNoise`) on the segment, moved to the right perturbation
   of ``base_T_object``. FPFH + RANSAC starts are not used yet.

A stage fails on its own evidence, and the estimate then makes no pose claim (``pose`` is
``None``): no plane or nothing on it, or no cluster of the model's size (segment); too few
pixels with depth in the footprint, or too few points left after filtering (lift); a final
registration whose ICP failed (non-finite, too few pairs, or degenerate geometry without a
``symmetry`` to explain it), too small a fraction of the segment explained by the model, too
large a residual, a model that the depth image contradicts (surface predicted where the camera
sees through it), or a segment that spans beyond the model, or whose span cannot be measured
(register).

Host-side entry point: bad arguments raise ``ValueError``. The compiled pieces have static
shapes: the segment grid is fixed by the image size and stride, and the clouds given to ICP
are padded (or subsampled) to ``max_points``.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, Float

from jaxreg.camera.model import RGBDFrame
from jaxreg.geometry.metrics import Symmetry
from jaxreg.pipeline._lift import lift_region
from jaxreg.pipeline._register_stage import (
    _coarse_problem,
    _confirmed_share,
    _diameter,
    _distinct,
    _finish,
    _judge,
    _near_model,
    _prepare_model,
    _register_starts,
    _score_candidates,
    _support,
    overhang,
    visibility as visibility,
)
from jaxreg.pipeline.segment import SegmentStatus, choose_cluster, cluster_mask, segment_frame
from jaxreg.registration._icp_setup import _bucket
from jaxreg.registration.icp import ICPStatus
from jaxreg.uncertainty import DepthNoise

__all__ = ["PoseEstimate", "estimate_pose", "visibility"]

STAGES = ("segment", "lift", "register")
# depth agreement (metres) of the image's judgement of a pose; more where the depth noise's
# NOISE_SIGMAS sigma_z(z) is more (see visibility)
_TOLERANCE = np.float32(0.01)
# Final ICP statuses that leave a pose to judge (the iteration bound leaves the last step's
# pose); degenerate geometry passes too when a symmetry is given (its free directions).
_USABLE = (ICPStatus.success, ICPStatus.max_iterations)


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
            object frame; metres and radians) from the depth noise through the final
            registration; NaN without a pose.
        failed_stage: ``None``, ``"segment"``, ``"lift"`` or ``"register"``.
        reason: why that stage failed, or a one-line summary of a success.
        stages: ``{stage: {"ms": float, ...diagnostics}}`` for the stages that ran.
        mask: ``(H, W)`` bool pixels of the lifted segment (all False if lift did not run).
        points: ``(K, 3)`` base-frame points that were registered (empty if none).
    """

    pose: SE3 | None
    inlier_rmse: float
    inlier_fraction: float
    covariance: np.ndarray
    failed_stage: str | None
    reason: str
    stages: dict[str, dict[str, Any]]
    mask: np.ndarray
    points: np.ndarray

    @property
    def success(self) -> bool:
        """True when every stage passed and ``pose`` is a claim."""
        return self.failed_stage is None


# --------------------------------------------------------------------------------------------
# The stages. Each records its diagnostics in ``stages[name]`` and raises ``_Failed`` when its
# evidence says there is no pose to claim.


@dataclasses.dataclass(frozen=True)
class _Settings:
    """:func:`estimate_pose`'s keyword settings, as its stages read them."""

    pixel: tuple[float, float] | None
    box: tuple[float, float, float, float] | None
    voxel_size: float
    stride: int
    plane_distance: float
    min_height: float
    lift_min_height: float
    cluster_distance: float
    cluster_margin: float
    max_candidates: int
    num_starts: int
    resting_yaws: int
    coarse_points: int
    coarse_screen: int
    coarse_survivors: int
    coarse_first: int
    coarse_keep: int
    max_points: int
    min_segment_points: int
    min_valid_fraction: float
    min_consistent_neighbors: int
    min_inlier_fraction: float
    max_inlier_rmse: float
    max_contradicted: float
    max_overhang: float
    refined_starts: int
    coarse_distances: np.ndarray = dataclasses.field(
        default_factory=lambda: np.geomspace(0.04, 0.01, 20).astype(np.float32)
    )

    @property
    def fine_distances(self) -> np.ndarray:
        """The refinement's correspondence distances (metres, 15 mm down to 1.5 voxels)."""
        return np.geomspace(0.015, 1.5 * self.voxel_size, 30).astype(np.float32)


class _Failed(Exception):
    """A stage found no pose to claim: its name, the reason, and what it had segmented."""

    def __init__(self, stage: str, reason: str, mask=None, points=None):
        super().__init__(reason)
        self.stage, self.reason, self.mask, self.points = stage, reason, mask, points


def _padded(points: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """``(size, 3)`` float32: ``points`` subsampled (without replacement) when longer, NaN
    rows (ignored by ICP) after them when shorter."""
    if len(points) > size:
        points = points[np.sort(rng.choice(len(points), size, replace=False))]
    out = np.full((size, 3), np.nan, np.float32)
    out[: len(points)] = points
    return out


def _ms(start: float) -> float:
    return round((time.perf_counter() - start) * 1e3, 2)


def estimate_pose(
    frame: RGBDFrame,
    model_points: Float[Any, "M 3"],
    *,
    model_normals: Float[Any, "M 3"] | None = None,
    symmetry: Symmetry | None = None,
    depth_noise: DepthNoise | None = None,
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
    refined_starts: int = 4,
    progress: Callable[[str], object] | None = None,
) -> PoseEstimate:
    """Estimate ``base_T_object`` of a model in one depth frame (see the module docstring).

    Args:
        frame: the depth frame; points are expressed in its base frame.
        model_points: ``(M, 3)`` points on the model's surface in its own frame (metres),
            e.g. :func:`jaxreg.io.load_points` of a mesh or scan.
        model_normals: ``(M, 3)`` unit normals of the model points (a mesh's face normals),
            used instead of normals estimated from the points; give them for thin-walled
            objects, whose two faces a point neighbourhood mixes.
        symmetry: the model's :class:`~jaxreg.Symmetry`, if any.
        depth_noise: the camera's noise as a :class:`~jaxreg.uncertainty.DepthNoise` in the
            camera frame (its ``base_T_camera`` is replaced by the frame's); default a
            structured-light / stereo camera with ``sigma_z = 2.5e-3 z^2`` (metres).
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
        refined_starts: distinct coarse poses of the winning candidate refined on the lifted
            points (the best first; each differs from the others by 1 cm or 0.2 rad).
        progress: called with each stage's name as it starts (a command line's progress).

    Returns:
        :class:`PoseEstimate`.

    Raises:
        ValueError: a frame that is not an ``RGBDFrame``, a model that is not ``(M, 3)``
            finite points, or both prompts.
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
    if pixel is not None and box is not None:
        raise ValueError("give at most one prompt: pixel=(u, v) or box=(u0, v0, u1, v1)")
    if not (isinstance(refined_starts, int) and 1 <= refined_starts <= coarse_keep):
        raise ValueError(
            f"refined_starts must be an integer from 1 to coarse_keep ({coarse_keep}), got "
            f"{refined_starts!r}"
        )
    key = jax.random.PRNGKey(0) if key is None else key
    progress = progress or (lambda stage: None)
    settings = _Settings(
        pixel, box, voxel_size, stride, plane_distance, min_height, lift_min_height,
        cluster_distance, cluster_margin, max_candidates, num_starts, resting_yaws,
        coarse_points, coarse_screen, coarse_survivors, coarse_first, coarse_keep, max_points,
        min_segment_points, min_valid_fraction, min_consistent_neighbors, min_inlier_fraction,
        max_inlier_rmse, max_contradicted, max_overhang, refined_starts,
    )  # fmt: skip
    model = _prepare_model(
        model_points, model_normals, voxel_size, float(settings.coarse_distances[0]),
        float(settings.fine_distances[0]),
    )  # fmt: skip
    noise = _noise(depth_noise, frame)
    stages: dict[str, dict[str, Any]] = {}
    rng = np.random.default_rng(0)  # the coarse clouds' and the source's subsamples
    try:
        progress("segment")
        seg, joined, coarse_poses, coarse_fraction = _segment(
            frame, model, settings, key, rng, stages, noise
        )
        progress("lift")
        mask, points = _lift(frame, seg, joined, noise, settings, stages)
        progress("register")
        return _register(
            frame, seg, model, settings, coarse_poses, coarse_fraction, mask, points, noise,
            symmetry, rng, stages,
        )  # fmt: skip
    except _Failed as failure:
        return PoseEstimate(
            None, float("nan"), float("nan"), np.full((6, 6), np.nan), failure.stage,
            failure.reason, stages,
            np.zeros(frame.depth.shape, bool) if failure.mask is None else failure.mask,
            np.zeros((0, 3), np.float32) if failure.points is None else failure.points,
        )  # fmt: skip


def _segment(frame, model, settings: _Settings, key, rng, stages, noise: DepthNoise):
    """Plane, clusters, and the candidate clusters scored by registration: the segment, the
    winning clusters (with the pieces split off them), the winner's coarse poses
    (object_T_base ``(K, 7)``, best first) and the fraction of it they explain."""
    s = settings
    start = time.perf_counter()
    seg = jax.block_until_ready(
        segment_frame(
            frame, key=key, stride=s.stride, plane_distance=s.plane_distance,
            min_height=s.min_height, cluster_distance=s.cluster_distance,
        )
    )  # fmt: skip
    sizes = np.asarray(seg.clusters.sizes)
    radii = np.asarray(seg.radii)
    diag = stages["segment"] = {
        "ms": None,
        "plane_inliers": int(seg.plane.num_inliers),
        "plane_inlier_fraction": round(float(seg.plane.inlier_fraction), 3),
        "valid_grid_points": int(seg.valid_points),
        "above_plane": int(seg.above_plane),
        "cluster_sizes": [int(size) for size in sizes if size > 0],
        "cluster_radii_mm": [
            round(float(r) * 1e3, 1) for r, size in zip(radii, sizes, strict=True) if size > 0
        ],
        "overflow": bool(seg.clusters.overflow),
    }

    def fail(reason: str):
        diag["ms"] = _ms(start)
        raise _Failed("segment", reason)

    if seg.status != SegmentStatus.success:
        fail(seg.status_message())
    grid_points = np.asarray(seg.points)
    labels = np.asarray(seg.clusters.labels)
    live = [k for k in range(len(sizes)) if sizes[k] > 0]
    if s.pixel is not None or s.box is not None:
        chosen = choose_cluster(seg, pixel=s.pixel, box=s.box)
        if chosen is None:
            fail(f"the prompt {s.pixel or s.box} touches no cluster")
        seeds = [chosen]
    else:
        seeds = live
    centroids = np.asarray(seg.centroids)
    groups: list[tuple[int, ...]] = []
    for k in seeds:  # a cluster, and with the pieces near it (one object split by a rim)
        near = np.linalg.norm(centroids[live] - centroids[k], axis=1) < 1.2 * model.radius
        for group in ((k,), tuple(sorted({k, *np.asarray(live)[near].tolist()}))):
            if group not in groups:
                groups.append(group)
    candidates = []
    for group in groups:  # a partial view's centroid is off the object's: compare diameters
        cloud = grid_points[np.isin(labels, group)]
        if _diameter(cloud) <= model.diameter + s.cluster_margin:
            candidates.append((group, cloud))
    candidates.sort(key=lambda item: -len(item[1]))
    candidates = candidates[: s.max_candidates]
    if not candidates:
        fail(
            f"no cluster of the model's size: cluster radii {diag['cluster_radii_mm']} mm, "
            f"none spans at most the model's {model.diameter * 1e3:.0f} mm "
            f"(+{s.cluster_margin * 1e3:.0f} mm allowed)"
        )
    clouds = np.full((s.max_candidates, s.coarse_points, 3), np.nan, np.float32)
    for i, (_, cloud) in enumerate(candidates):
        clouds[i] = _padded(cloud, s.coarse_points, rng)
    used = np.arange(s.max_candidates) < len(candidates)
    problem, *rounds = _coarse_problem(
        model, s.coarse_points, s.coarse_distances, (s.coarse_screen, s.coarse_first)
    )
    coarse = jax.block_until_ready(
        _score_candidates(
            frame, seg.plane, problem, tuple(rounds), clouds, used, model.points, model.screen,
            model.axes, _TOLERANCE, noise.coefficients, s.fine_distances[-1], s.num_starts,
            s.resting_yaws, s.coarse_survivors, s.coarse_keep,
        )
    )  # fmt: skip
    scored = []
    for i, (group, cloud) in enumerate(candidates):
        counts = np.asarray(coarse.visibility[i, 0])
        confirmed, contradicted = _support(counts)
        explained = float(coarse.explained[i, 0])
        score = explained * confirmed
        reach = float(overhang(model, np.asarray(coarse.poses[i, 0]), cloud).max())
        scored.append((score, group, i, explained, contradicted, reach))
    scored.sort(key=lambda item: (not item[5] <= s.max_overhang, -item[0]))  # larger (or NaN) last
    _, group, chosen, coarse_fraction, _, _ = scored[0]
    coarse_poses = np.asarray(coarse.poses[chosen])  # object_T_base per start, best first
    # pieces of the object the clustering split off: clusters the coarse pose explains
    members = labels >= 0
    points = _padded(grid_points[members], _bucket(int(members.sum())), rng)
    near = np.asarray(_near_model(model.fine_grid, coarse_poses[0], points, np.float32(0.01)))
    near, member_labels = near[: members.sum()], labels[members]
    joined = sorted({*group, *(k for k in live if near[member_labels == k].mean() >= 0.6)})
    diag.update(
        candidates=[
            {
                "clusters": list(g),
                "score": round(sc, 3),
                "explained": round(f, 3),
                "contradicted": round(c, 3),
                "overhang_mm": round(r * 1e3, 1),
            }
            for sc, g, _, f, c, r in scored
        ],  # fmt: skip
        chosen_clusters=list(joined),
        ms=_ms(start),
    )
    return seg, joined, coarse_poses, coarse_fraction


def _lift(frame, seg, joined, noise: DepthNoise, settings: _Settings, stages):
    """The winning clusters' footprint lifted and filtered (:mod:`jaxreg.pipeline._lift`): the mask
    of the lifted pixels ``(H, W)`` and the base-frame points ``(K, 3)``."""
    s = settings
    start = time.perf_counter()
    region = cluster_mask(seg, joined, frame.depth.shape)
    depth = np.asarray(frame.depth)
    rows, cols = np.nonzero(region)
    has_depth = np.isfinite(depth[rows, cols])
    valid_fraction = float(has_depth.mean()) if len(rows) else 0.0
    rows, cols = rows[has_depth], cols[has_depth]
    diag = stages["lift"] = {
        "ms": None,
        "footprint_pixels": int(region.sum()),
        "valid_depth_fraction": round(valid_fraction, 3),
    }
    if valid_fraction < s.min_valid_fraction:
        diag["ms"] = _ms(start)
        raise _Failed(
            "lift",
            f"too little valid depth: {valid_fraction:.0%} of the segment's {int(region.sum())} "
            f"pixels have depth (need {s.min_valid_fraction:.0%}); dark, shiny or grazing "
            "surfaces, or the object too near the camera",
            mask=region,
        )
    sigma = np.polynomial.polynomial.polyval(
        depth[rows, cols], np.asarray(noise.coefficients, np.float64)
    )
    mask, points, counts = lift_region(
        frame, rows, cols, sigma, np.asarray(seg.plane.normal), float(seg.plane.offset),
        min_height=s.lift_min_height, voxel_size=s.voxel_size,
        min_consistent_neighbors=s.min_consistent_neighbors,
    )  # fmt: skip
    diag.update(**counts, ms=_ms(start))
    if len(points) < s.min_segment_points:
        raise _Failed(
            "lift",
            f"only {len(points)} points left after filtering (need {s.min_segment_points}): "
            "the segment is too small or too noisy to register",
            mask=mask,
            points=points,
        )
    return mask, points


def _register(
    frame, seg, model, settings: _Settings, coarse_poses, coarse_fraction, mask, points, noise,
    symmetry, rng, stages,
):  # fmt: skip
    """The best distinct coarse poses refined on the lifted points and judged; the estimate,
    or ``_Failed`` when the evidence says the model is not there."""
    s = settings
    fine_distances = s.fine_distances
    start = time.perf_counter()
    source = _padded(points, s.max_points, rng)
    picks = _distinct(coarse_poses, s.refined_starts, 0.01)
    inits = SE3(jax.device_put(coarse_poses[picks]))
    trim = np.float32(np.clip(coarse_fraction, 0.6, 0.95))  # an argument: one program for all
    results = _register_starts(
        source, model.points, model.normals, model.fine_grid, inits, fine_distances, trim, 30
    )
    fractions = np.asarray(results.inlier_fraction)
    rmses = np.nan_to_num(np.asarray(results.inlier_rmse), nan=np.inf)
    seen = np.asarray(
        _judge(
            frame, seg.plane, results.pose.wxyz_xyz, model.points, _TOLERANCE, noise.coefficients
        )
    )
    scores = fractions * _confirmed_share(seen)
    ranked = np.lexsort((rmses, -np.round(scores, 2)))
    best = results[int(ranked[0])]
    fraction, rmse = float(fractions[ranked[0]]), float(rmses[ranked[0]])
    confirmed, contradicted = _support(seen[ranked[0]])
    reach = overhang(model, np.asarray(results.pose.wxyz_xyz[ranked[0]]), points)
    equal = (scores >= scores[ranked[0]] - 0.02) & (rmses <= rmse * 1.1 + 1e-4)
    wxyz_xyz, spread, covariance = _finish(
        source, model.points, model.normals, model.fine_grid, results.pose.wxyz_xyz,
        np.int32(ranked[0]), equal, symmetry, fine_distances[-1], trim, noise,
    )  # fmt: skip
    spread_mm, spread_deg = (float(x) for x in np.asarray(spread))
    stages["register"] = {
        "ms": _ms(start),
        "starts": s.num_starts + 4 + 6 * s.resting_yaws,
        "coarse_kept_starts": int(coarse_poses.shape[0]),
        "refined_starts": len(picks),
        "trim_fraction": round(float(trim), 3),
        "iterations": int(best.iterations),
        "icp_status": str(best.status_message()),
        "inlier_rmse_mm": round(rmse * 1e3, 3),
        "inlier_fraction": round(fraction, 3),
        "equally_good_starts": int(equal.sum()),
        "start_agreement_mm": round(spread_mm * 1e3, 3),
        "start_agreement_deg": round(spread_deg, 3),
        "model_confirmed": round(confirmed, 3),
        "model_contradicted": round(contradicted, 3),
        "overhang_mm": [round(float(r) * 1e3, 1) for r in reach],
    }
    usable = _USABLE + ((ICPStatus.degenerate,) if symmetry is not None else ())
    if not any(bool(best.status == status) for status in usable):
        raise _Failed(
            "register", f"the final registration failed: {best.status_message()}", mask=mask,
            points=points,
        )  # fmt: skip
    problems = []
    if fraction < s.min_inlier_fraction:
        problems.append(
            f"the model explains only {fraction:.0%} of the segment (need "
            f"{s.min_inlier_fraction:.0%})"
        )
    if not rmse <= s.max_inlier_rmse:
        problems.append(
            f"the residual is {rmse * 1e3:.1f} mm (at most {s.max_inlier_rmse * 1e3:g})"
        )
    if contradicted > s.max_contradicted:
        problems.append(
            f"the camera sees through {contradicted:.0%} of the model's surface facing it (at "
            f"most {s.max_contradicted:.0%})"
        )
    if np.isnan(reach).any():
        problems.append(
            "the segment's span beyond the model could not be measured (NaN: a non-finite "
            "pose or segment point)"
        )
    elif reach.max() > s.max_overhang:
        problems.append(
            f"the segment spans {reach.max() * 1e3:.0f} mm beyond the model along its "
            f"{('longest', 'middle', 'shortest')[int(reach.argmax())]} axis (at most "
            f"{s.max_overhang * 1e3:g}): a larger object of a similar shape, or the object "
            "merged with a neighbour"
        )
    if problems:
        raise _Failed(
            "register", "the model is not there: " + "; ".join(problems), mask=mask, points=points
        )
    reason = (
        f"found: {fraction:.0%} of {len(points)} segment points within "
        f"{fine_distances[-1] * 1e3:.0f} mm of the model, residual {rmse * 1e3:.2f} mm"
    )
    return PoseEstimate(
        SE3(wxyz_xyz), rmse, fraction, np.asarray(covariance), None, reason, stages, mask, points
    )


def _noise(depth_noise: DepthNoise | None, frame: RGBDFrame) -> DepthNoise:
    """The depth noise in the frame's base frame."""
    if depth_noise is None:
        return DepthNoise((0.0, 0.0, 2.5e-3), frame.base_T_camera)
    return eqx.tree_at(lambda n: n.base_T_camera, depth_noise, frame.base_T_camera)
