"""The segment stage of :func:`jaxreg.estimate_pose`: the table route (plane, clusters, the
candidates scored by coarse registration) and the mask route (the caller's own mask). Each
returns the table plane (or ``None``), the footprint to lift ``(H, W)``, the winner's coarse
poses (object_T_base ``(K, 7)`` wxyz_xyz, best first) and the fraction of its points they
explain, and records a :class:`~jaxreg.pipeline._records.SegmentRecord`.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from jaxreg.camera.model import RGBDFrame
from jaxreg.pipeline._lift import lift_pixels
from jaxreg.pipeline._model import _diameter
from jaxreg.pipeline._records import Candidate, SegmentRecord
from jaxreg.pipeline._register_stage import (
    _coarse_problem,
    _near_model,
    _score_candidates,
    _support,
    overhang,
)
from jaxreg.pipeline._settings import _TOLERANCE, _Failed, _ms, _padded, _Settings
from jaxreg.pipeline.segment import (
    SegmentStatus,
    TablePlane,
    choose_cluster,
    cluster_mask,
    segment_frame,
)


def segment_table(frame, model, settings: _Settings, key, rng, stages, noise):
    """Plane, clusters, and the candidate clusters scored by registration: the plane, the
    footprint ``(H, W)`` of the winning clusters (with the pieces split off them), the
    winner's coarse poses (object_T_base ``(K, 7)``, best first) and the fraction of it they
    explain."""
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
    diag = SegmentRecord(
        ms=0.0,
        plane_inliers=int(seg.plane.num_inliers),
        plane_inlier_fraction=round(float(seg.plane.inlier_fraction), 3),
        valid_grid_points=int(seg.valid_points),
        above_plane=int(seg.above_plane),
        cluster_sizes=[int(size) for size in sizes if size > 0],
        cluster_radii_mm=[
            round(float(r) * 1e3, 1) for r, size in zip(radii, sizes, strict=True) if size > 0
        ],
        overflow=bool(seg.clusters.overflow),
    )

    def fail(reason: str):
        stages["segment"] = dataclasses.replace(diag, ms=_ms(start))
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
    candidates, spans = [], []
    for group in groups:  # a partial view's centroid is off the object's: compare diameters
        cloud = grid_points[np.isin(labels, group)]
        spans.append(_diameter(cloud))
        if spans[-1] <= model.diameter + s.cluster_margin:
            candidates.append((group, cloud, spans[-1]))
    candidates.sort(key=lambda item: -len(item[1]))
    candidates = candidates[: s.max_candidates]
    if not candidates:
        fail(
            f"no cluster of the model's size: cluster radii {diag.cluster_radii_mm} mm, "
            f"none spans at most the model's {model.diameter * 1e3:.0f} mm "
            f"(+{s.cluster_margin * 1e3:.0f} mm allowed)" + _units_hint(model, min(spans))
        )
    # no cluster spans more than twice its radius (clusters, not the candidates' groups:
    # within 1.2 radii of a model ten times too large, every cluster joins one group)
    too_small = _units_hint(model, 2 * max(float(radii[k]) for k in live))
    if too_small:
        fail("every cluster is far smaller than the model (is it in view?)" + too_small)
    coarse, scored = _score(
        frame, seg.plane, model, s, [c for _, c, _ in candidates], rng, noise
    )
    _, coarse_fraction, _, _, chosen = scored[0]
    group = candidates[chosen][0]
    coarse_poses = np.asarray(coarse.poses[chosen])  # object_T_base per start, best first
    # pieces of the object the clustering split off: clusters the coarse pose explains
    members = labels >= 0  # the whole grid, non-members NaN: one shape for every frame
    points = np.where(members[..., None], grid_points, np.nan).astype(np.float32)
    near = np.asarray(_near_model(model.fine_grid, coarse_poses[0], points, np.float32(0.01)))
    near, member_labels = near[members], labels[members]
    joined = sorted({*group, *(k for k in live if near[member_labels == k].mean() >= 0.6)})
    region = cluster_mask(seg, joined, frame.depth.shape)
    stages["segment"] = dataclasses.replace(
        diag,
        candidates=[_candidate(list(candidates[i][0]), *rest) for *rest, i in scored],
        chosen_clusters=list(joined),
        ms=_ms(start),
    )
    return seg.plane, region, coarse_poses, coarse_fraction


def segment_mask(frame, model, settings: _Settings, mask, key, rng, stages, noise):
    """The caller's mask as the segment. The table plane is fitted to the pixels outside the
    mask (:func:`segment_frame` on the frame with the mask's depth removed: the program the
    table route compiled); it is used when the object stands on it (the lowest 5% of the
    mask's points within 2 cm above it, and no more than 2% below it by more than
    ``plane_distance``: a plane fitted to another object's face may cut through this one):
    the band above it filters the segment, the resting
    starts stand the model on it, and the image's judgement counts a model below it as
    contradicted. Without a table (no plane, or the object not on it) there is no band, and
    the resting starts' share of the coarse search goes to the rotation grid. The mask's
    grid points (every ``stride``-th pixel) are the one candidate scored by registration.
    Returns what :func:`segment_table` returns."""
    s = settings
    start = time.perf_counter()
    depth = np.asarray(frame.depth)
    outside = RGBDFrame(np.where(mask, np.nan, depth), frame.intrinsics, frame.rgb,
                        frame.base_T_camera)  # fmt: skip
    seg = jax.block_until_ready(
        segment_frame(
            outside, key=key, stride=s.stride, plane_distance=s.plane_distance,
            min_height=s.min_height, cluster_distance=s.cluster_distance,
        )
    )  # fmt: skip
    grid = np.zeros_like(mask)
    grid[:: s.stride, :: s.stride] = True
    rows, cols = np.nonzero(mask & grid & np.isfinite(depth))
    cloud = lift_pixels(frame, rows, cols)
    plane = None
    if seg.status in (SegmentStatus.success, SegmentStatus.no_clusters) and len(cloud):
        height = cloud @ np.asarray(seg.plane.normal) + float(seg.plane.offset)
        low, lowest = np.percentile(height, [5, 2])
        if low < 0.02 and lowest > -s.plane_distance:
            plane = seg.plane
            cloud = cloud[height > s.min_height]
    diag = SegmentRecord(
        ms=0.0,
        valid_grid_points=int(seg.valid_points),
        plane_inliers=None if plane is None else int(plane.num_inliers),
        plane_inlier_fraction=None if plane is None else round(float(plane.inlier_fraction), 3),
        mask_pixels=int(mask.sum()),
        mask_grid_points=len(cloud),
    )

    def fail(reason: str):
        stages["segment"] = dataclasses.replace(diag, ms=_ms(start))
        raise _Failed("segment", reason)

    if len(cloud) < 15:
        fail(
            f"the mask's {int(mask.sum())} pixels hold {len(cloud)} points with depth"
            + ("" if plane is None else " above the table")
            + f" on the {s.stride}-pixel grid (need 15): a mask on a hole in the depth, "
            "or on the table, or an object too small to register at this distance"
        )
    span = _diameter(cloud)
    if span > 3 * model.diameter:
        fail(
            f"the masked segment spans {span * 1e3:.0f} mm, more than 3 times the model's "
            f"{model.diameter * 1e3:.0f} mm: give model_points in the frame's units (metres; "
            "jaxreg pose --model-units), or a mask on the object alone"
        )
    hint = _units_hint(model, span)
    if hint:
        fail("the masked segment is far smaller than the model (a mask on another object?)" + hint)
    coarse, scored = _score(frame, plane, model, s, [cloud], rng, noise)
    stages["segment"] = dataclasses.replace(
        diag, candidates=[_candidate([], *rest) for *rest, _ in scored], ms=_ms(start)
    )
    return plane, mask, np.asarray(coarse.poses[0]), scored[0][1]


def _score(frame, plane: TablePlane | None, model, settings: _Settings, clouds, rng, noise):
    """Coarse registration of the candidate ``clouds`` (each ``(N, 3)``, base frame) in one
    compiled call, and each one's evidence, best first: tuples ``(score, explained,
    contradicted, overhang, slot)``; a candidate whose points reach beyond the model
    (``max_overhang``: a larger object of a similar shape, or a span that cannot be measured)
    ranks after those that do not. ``noise``: the camera's ``DepthNoise`` (the image's
    judgement allows 4 sigma_z at each depth)."""
    s = settings
    padded = np.full((s.max_candidates, s.coarse_points, 3), np.nan, np.float32)
    for i, cloud in enumerate(clouds):
        padded[i] = _padded(cloud, s.coarse_points, rng)
    used = np.arange(s.max_candidates) < len(clouds)
    problem, *rounds = _coarse_problem(
        model, s.coarse_points, s.coarse_distances, (s.coarse_screen, s.coarse_first)
    )
    coarse = jax.block_until_ready(
        _score_candidates(
            frame, plane, problem, tuple(rounds), model.fine_grid, padded, used, model.points,
            model.screen, model.axes, _TOLERANCE, noise.coefficients, s.fine_distances[-1],
            s.num_starts, s.resting_yaws, s.coarse_survivors, s.coarse_keep,
        )
    )  # fmt: skip
    scored = []
    for i, cloud in enumerate(clouds):
        confirmed, contradicted = _support(np.asarray(coarse.visibility[i, 0]))
        explained = float(coarse.explained[i, 0])
        reach = float(overhang(model, np.asarray(coarse.poses[i, 0]), cloud).max())
        scored.append((explained * confirmed, explained, contradicted, reach, i))
    # larger objects (or an unmeasurable span) last
    scored.sort(key=lambda item: (not item[3] <= s.max_overhang, -item[0]))
    return coarse, scored


def _candidate(clusters, score, explained, contradicted, reach) -> Candidate:
    return Candidate(
        clusters=clusters,
        score=round(score, 3),
        explained=round(explained, 3),
        contradicted=round(contradicted, 3),
        overhang_mm=round(reach * 1e3, 1),
    )


def _units_hint(model, span: float) -> str:
    """A sentence naming the units when a segment spanning ``span`` metres cannot be a view
    of the model, else ``""``: any view of an object shows about its middle extent (a box
    seen end-on, its two shorter sides), so a segment below a third of it is another object,
    or a model in other units than the frame's metres."""
    extents = np.sort(model.bounds[1] - model.bounds[0])[::-1]
    if span * 3 >= extents[1]:
        return ""
    return (
        f": the segment spans {span * 1e3:.0f} mm, the model's middle extent is "
        f"{extents[1] * 1e3:.0f} mm; is the model in the frame's units (metres)? A model in "
        "millimetres needs model_points * 0.001 (jaxreg pose --model-units mm)"
    )
