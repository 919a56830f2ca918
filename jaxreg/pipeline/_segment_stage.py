"""The segment stage of :func:`jaxreg.estimate_pose`: the candidate segments the register
stage's coarse search chooses from. The table route finds the table plane and the clusters
standing on it; each cluster, and each cluster with the clusters near it (one object split
by a thin rim), is a candidate when its diameter fits the model's. The mask route takes the
caller's own mask as the one candidate, with the table plane fitted outside it. Given the
model's colours and a frame with RGB, the table route sets aside the clusters whose pixels do
not show them (:mod:`jaxreg.pipeline._colour`): a look-alike of another paint.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np

from jaxreg.camera.model import RGBDFrame
from jaxreg.geometry.metrics import diameter
from jaxreg.pipeline._colour import colour_match, other_colour
from jaxreg.pipeline._lift_stage import below_band, lift_pixels
from jaxreg.pipeline._stages import _Failed
from jaxreg.pipeline._surface import mask_surface
from jaxreg.pipeline.records import Segmented, SegmentRecord
from jaxreg.pipeline.segment import SegmentStatus, choose_cluster, segment_frame
from jaxreg.pipeline.settings import LiftSettings, SegmentSettings

__all__ = ["segment_stage"]

# The fewest grid points a cluster holds, whatever the model (a 2 x 3 block of the grid):
# fewer are a few flying pixels at a depth edge. The segmentation keeps clusters of this size
# (one compiled program for every model); the table route then asks each for the grid points
# the model could show at its depth (:func:`_least_points`).
FEWEST_GRID_POINTS = 6


def segment_stage(
    frame: RGBDFrame, model, settings: SegmentSettings, key, noise, *, mask=None, pixel=None,
    box=None, lift: LiftSettings, palette=None,
) -> Segmented:  # fmt: skip
    """The candidates of ``frame`` for the prepared ``model``: the object's surface in the
    caller's ``mask`` ``(H, W)`` (:func:`_mask_route`), or the table route's clusters
    (:func:`_table_route`; a ``pixel`` ``(u, v)`` or ``box`` ``(u0, v0, u1, v1)`` prompt names
    the seed cluster). A box that holds no cluster (a thin object far away, whose depth the
    camera keeps in fewer grid points than a cluster needs) is taken as a mask: its surface
    above the table is the candidate (:func:`_mask_route`). ``key``: the plane hypotheses'
    PRNG key; ``noise``: the camera's ``DepthNoise``; ``lift``: the lift's settings, whose
    band above the table the mask route's surface leaves out; ``palette``: the model's
    chromaticities (:func:`~jaxreg.pipeline._colour.model_palette`) or ``None``. Raises
    ``_Failed`` when no candidate can be the model."""
    if mask is not None:
        return _mask_route(frame, model, settings, mask, key, noise, lift)
    segmented = _table_route(frame, model, settings, key, pixel, box, palette)
    if segmented is None:
        return _mask_route(
            frame, model, settings, _box_pixels(box, frame.depth.shape), key, noise, lift,
            prompt="box",
        )  # fmt: skip
    return segmented


def height_ceiling(model, settings: SegmentSettings) -> float:
    """How high above the table (metres) the segment and the lift reach: ``max_height``, or
    the model's diameter plus ``cluster_margin`` when that is more (an object standing on the
    table reaches no higher than its diameter)."""
    return max(settings.max_height, model.diameter + settings.cluster_margin)


def _segment(frame: RGBDFrame, model, settings: SegmentSettings, key):
    """:func:`segment_frame` with the stage's settings, finished."""
    s = settings
    return jax.block_until_ready(
        segment_frame(
            frame, key=key, stride=s.stride, plane_distance=s.plane_distance,
            min_height=s.min_height, max_height=height_ceiling(model, s),
            cluster_distance=s.cluster_distance, min_cluster_size=FEWEST_GRID_POINTS,
        )
    )  # fmt: skip


def _table_route(
    frame, model, settings: SegmentSettings, key, pixel, box, palette
) -> Segmented | None:
    """Plane and clusters; every cluster (or the one a ``pixel`` prompt names), alone and with
    the clusters within 1.2 model radii of it, whose diameter is at most the model's plus
    ``cluster_margin``, the largest first, then those larger than the model (an object
    touching its neighbours), nearest the model's size first; ``max_candidates`` in all. A
    ``box`` prompt's candidates are the clusters it holds, most grid points inside first, each
    cut to the box whatever its size: a detector's box holds the object and the neighbours it
    touches, which the model's fit explains away (:mod:`jaxreg.pipeline._evidence`); ``None``
    when the box holds no cluster.
    Unprompted, with a ``palette`` and the frame's RGB, the clusters whose pixels do not show
    the model's colours are no candidates, and the grid points of another colour are left out
    of the others' (:func:`_by_colour`)."""
    s = settings
    start = time.perf_counter()
    seg = _segment(frame, model, s, key)
    sizes = np.asarray(seg.clusters.sizes)
    radii = np.asarray(seg.radii)
    record = SegmentRecord(
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
        raise _Failed("segment", reason, record.with_ms(start))

    if seg.status == SegmentStatus.no_clusters and box is not None:
        return None
    if seg.status != SegmentStatus.success:
        fail(seg.status_message())
    grid_points = np.asarray(seg.points)
    labels = np.asarray(seg.clusters.labels)
    least = _least_points(frame, model, np.asarray(seg.centroids), s)
    live = [k for k in range(len(sizes)) if sizes[k] > 0 and sizes[k] >= least[k]]
    if not live:
        if box is not None:
            return None
        fail(
            f"nothing of the model's size stands on the table: the clusters hold "
            f"{record.cluster_sizes} grid points, fewer than half of what the model's smallest "
            "silhouette would cover at their depth (or min_cluster_size); is the object in view, "
            "and its depth measured?"
        )
    inside, bounds = labels >= 0, None
    if box is not None:  # every cluster in the box, cut to it: the model's fit carves
        bounds = _box_pixels(box, frame.depth.shape)
        inside = bounds[:: s.stride, :: s.stride][: labels.shape[0], : labels.shape[1]]
        counts = np.bincount(labels[inside & (labels >= 0)], minlength=len(sizes))
        seeds = [int(k) for k in np.argsort(-counts, kind="stable") if counts[k] and k in live]
        if not seeds:
            return None
    elif pixel is not None:
        chosen = choose_cluster(seg, pixel=pixel, among=live)
        if chosen is None:
            fail(f"the prompt {pixel} touches no cluster of the model's size")
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
    keep, other, used = labels >= 0, set(), None
    if palette is not None and frame.rgb is not None and pixel is None and box is None:
        rgb = np.asarray(frame.rgb)[:: s.stride, :: s.stride]
        judged, match = colour_match(rgb, palette, s.color_tolerance)
        other_points = other_colour(judged, match, labels >= 0, rim=1)
        other, stripped = _by_colour(judged, match, other_points, labels, live, s)
        keep &= ~other_points
        used = palette
        record = dataclasses.replace(record, other_color=other, stripped_by_color=stripped)
    candidates, larger, spans = [], [], []
    for group in groups:  # a partial view's centroid is off the object's: compare diameters
        if set(group) & set(other):
            continue
        cloud = grid_points[np.isin(labels, group) & keep & inside]
        spans.append(diameter(cloud) if len(cloud) else np.inf)
        if len(cloud) and (box is not None or spans[-1] <= model.diameter + s.cluster_margin):
            candidates.append((group, cloud))
        elif np.isfinite(spans[-1]):
            larger.append((spans[-1], group, cloud))
    if not candidates and other:
        fail(
            f"every cluster shows other colours than the model's (clusters {other} under "
            f"{s.min_color_share:.0%} of their pixels within the colour tolerance, the others "
            "not of the model's size): check model_colors (sRGB) and the lighting, or name the "
            "object with pixel=, box= or mask="
        )
    candidates.sort(key=lambda item: -len(item[1]))
    # clusters larger than the model (the object and the neighbours it touches) fill the
    # slots left, nearest the model's size first: the model's fit carves the object out
    larger.sort(key=lambda item: item[0])
    candidates = (candidates + [(group, cloud) for _, group, cloud in larger])[: s.max_candidates]
    if not candidates:
        fail(
            f"no cluster of the model's size: cluster radii {record.cluster_radii_mm} mm, "
            f"none spans at most the model's {model.diameter * 1e3:.0f} mm "
            f"(+{s.cluster_margin * 1e3:.0f} mm allowed)" + _units_hint(model, min(spans))
        )
    # no cluster spans more than twice its radius (clusters, not the candidates' groups:
    # within 1.2 radii of a model ten times too large, every cluster joins one group)
    too_small = _units_hint(model, 2 * max(float(radii[k]) for k in live))
    if too_small:
        fail("every cluster is far smaller than the model (is it in view?)" + too_small)
    return Segmented(seg.plane, candidates, seg, None, record.with_ms(start), used, bounds)


def _least_points(frame, model, centroids: np.ndarray, settings: SegmentSettings) -> np.ndarray:
    """``(C,)`` the grid points a cluster with centroid ``centroids`` ``(C, 3)`` (base frame)
    must hold to be a candidate, alone or in a group: ``min_cluster_size``, or half of the grid
    points the model's smallest silhouette (its two shorter extents) covers at the cluster's
    depth where that is fewer, at least :data:`FEWEST_GRID_POINTS`."""
    extents = np.sort(model.bounds[1] - model.bounds[0])
    eye = np.asarray(frame.base_T_camera.translation(), np.float64)
    depth = np.linalg.norm(np.asarray(centroids, np.float64) - eye, axis=1)
    cell = depth * settings.stride / float(frame.intrinsics.fx)  # a grid step there (metres)
    cover = extents[0] * extents[1] / np.maximum(cell, 1e-9) ** 2
    return np.clip(np.ceil(cover / 2), FEWEST_GRID_POINTS, settings.min_cluster_size)


def _box_pixels(box, shape: tuple[int, int]) -> np.ndarray:
    """``(H, W)`` bool: the pixels of ``box`` ``(u0, v0, u1, v1)`` (inclusive) in an image of
    ``shape``."""
    u0, v0, u1, v1 = (int(round(float(c))) for c in box)
    pixels = np.zeros(shape, bool)
    pixels[max(v0, 0) : max(v1 + 1, 0), max(u0, 0) : max(u1 + 1, 0)] = True
    return pixels


def _by_colour(judged, match, other_points, labels, live, settings):
    """The clusters (of ``live``, labels of the ``labels`` grid) whose ``judged`` grid pixels
    show the model's colours (``match``; both ``(h, w)``,
    :func:`~jaxreg.pipeline._colour.colour_match`) less often than ``min_color_share`` (a
    cluster with none judged is kept), and of the others those that hold grid points of
    another colour (``other_points`` ``(h, w)``, a touching neighbour of another paint),
    sorted lists both."""
    other, stripped = [], []
    for k in live:
        members = labels == k
        seen = int(judged[members].sum())
        if seen and match[members].sum() / seen < settings.min_color_share:
            other.append(k)
        elif other_points[members].any():
            stripped.append(k)
    return other, stripped


# Fewest points with depth a mask's surface must hold to be registered.
MIN_MASK_POINTS = 15


def _mask_route(
    frame, model, settings: SegmentSettings, mask, key, noise, lift: LiftSettings,
    prompt: str = "mask",
) -> Segmented:  # fmt: skip
    """The object's surface in the caller's mask as the one candidate: the mask's pixels
    that the depth image connects to the object (:func:`~jaxreg.pipeline._surface.
    mask_surface`: not the background behind it or an occluder in front, which a mask's
    border holds). Its extent is judged against the model's, and it is what the lift lifts.

    The table plane is fitted to the pixels outside the mask (:func:`segment_frame` on the
    frame with the mask's depth removed: the program the table route compiled); it is used
    when the object stands on it (the lowest 5% of the surface's points within 2 cm above it,
    and no more than 2% below it by more than ``plane_distance``: a plane fitted to another
    object's face may cut through this one): the band above it filters the segment, the
    resting starts stand the model on it, and the image's judgement counts a model below it
    as contradicted. The table's own pixels in the mask (below the lift's band:
    :func:`~jaxreg.pipeline._lift_stage.below_band`) are then left out and the surface found
    again: a mask that bleeds onto the table would otherwise join the object to a neighbour
    standing on the same table, whose depth the table's meets smoothly. Without a table (no
    plane, or the object not on it) there is no band, and the resting starts' share of the
    coarse search goes to the rotation grid. The candidate is the surface's grid points (every
    ``stride``-th pixel), or all its pixels where the grid holds fewer than
    ``MIN_MASK_POINTS`` (a thin object far away, whose depth the camera keeps in a few
    pixels). ``prompt`` names the caller's region in a refusal's reason (``"mask"``, or
    ``"box"`` for a box read as a mask)."""
    s = settings
    start = time.perf_counter()
    depth = np.asarray(frame.depth)
    outside = RGBDFrame(np.where(mask, np.nan, depth), frame.intrinsics, frame.rgb,
                        frame.base_T_camera)  # fmt: skip
    seg = _segment(outside, model, s, key)
    grid = np.zeros_like(mask)
    grid[:: s.stride, :: s.stride] = True

    def candidate(surface):  # the grid's points, or every pixel's where the grid holds few
        rows, cols = np.nonzero(surface & grid)
        if len(rows) < MIN_MASK_POINTS:
            rows, cols = np.nonzero(surface)
        return lift_pixels(frame, rows, cols)

    surface = mask_surface(depth, mask, noise, float(frame.intrinsics.fx))
    cloud = candidate(surface)
    plane = None
    if seg.status in (SegmentStatus.success, SegmentStatus.no_clusters) and len(cloud):
        height = cloud @ np.asarray(seg.plane.normal) + float(seg.plane.offset)
        low, lowest = np.percentile(height, [5, 2])
        if low < 0.02 and lowest > -s.plane_distance:
            plane = seg.plane
            table = below_band(frame, mask, plane, noise, lift)
            surface = mask_surface(depth, mask & ~table, noise, float(frame.intrinsics.fx))
            cloud = candidate(surface)
            height = cloud @ np.asarray(plane.normal) + float(plane.offset)
            cloud = cloud[height > s.min_height]
    record = SegmentRecord(
        ms=0.0,
        valid_grid_points=int(seg.valid_points),
        plane_inliers=None if plane is None else int(plane.num_inliers),
        plane_inlier_fraction=None if plane is None else round(float(plane.inlier_fraction), 3),
        mask_pixels=int(mask.sum()),
        surface_pixels=int(surface.sum()),
        mask_grid_points=len(cloud),
    )

    def fail(reason: str):
        raise _Failed("segment", reason, record.with_ms(start))

    if len(cloud) < MIN_MASK_POINTS:
        fail(
            f"the {prompt}'s {int(mask.sum())} pixels hold {len(cloud)} points with depth"
            + ("" if plane is None else " above the table")
            + f" (need {MIN_MASK_POINTS}): a {prompt} on a hole in the depth, or on the table, "
            "or an object too small to register at this distance"
        )
    span = diameter(cloud)
    if span > 3 * model.diameter:
        fail(
            f"the {prompt}'s segment spans {span * 1e3:.0f} mm, more than 3 times the model's "
            f"{model.diameter * 1e3:.0f} mm: give model_points in the frame's units (metres; "
            f"jaxreg pose --model-units), or a {prompt} on the object alone"
        )
    hint = _units_hint(model, span)
    if hint:
        fail(
            f"the {prompt}'s segment is far smaller than the model (a {prompt} on another "
            "object?)" + hint
        )
    return Segmented(plane, [((), cloud)], None, surface, record.with_ms(start))


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
