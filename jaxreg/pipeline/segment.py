"""Segmentation of a tabletop depth frame: the table plane by RANSAC, then Euclidean clusters
of what stands on it.

The first stage of the pixels-to-pose pipeline (:func:`jaxreg.estimate_pose`). A tabletop
frame is mostly table; removing the plane leaves the objects, which fall apart into clusters
of nearby points. Everything runs in one compiled call on a strided grid of the depth image
(``stride`` pixels apart, every ``stride``-th row and column), with static shapes:

* **Table plane** (:func:`fit_plane`): ``num_hypotheses`` planes through 3 distinct valid
  points each, drawn from ``key`` (the same key gives the same plane) and scored in one
  ``vmap`` by the number of points within ``plane_distance``; the best is refit twice by
  least squares (PCA) on its inliers. The normal points to the camera's side, so a point's
  signed distance is its height above the table.
* **Above the table**: points higher than ``min_height`` and lower than ``max_height``.
* **Euclidean clusters** (:func:`euclidean_clusters`): two grid points are joined when they
  lie within ``window`` grid steps in the image and ``cluster_distance`` in space, and
  clusters are the connected components of that graph, found by min-label propagation with
  pointer jumping in a bounded ``while_loop`` over the points above the table alone (up to
  ``capacity`` of them; the whole grid beyond). Searching image neighbours instead of a 3D
  radius is what the organized image allows: a point's 3D neighbours within a few
  millimetres are its image neighbours, except across occlusions, which separate objects
  anyway. The ``max_clusters`` largest components are kept, largest first; ``overflow``
  says that a further component would have reached ``min_cluster_size``, or that the
  propagation hit ``max_iterations``.

Grid coordinates: ``labels[i, j]`` describes pixel ``(u, v) = (stride * j, stride * i)``.
:func:`cluster_mask` turns a cluster into a full-resolution pixel mask.

Failure is data: :class:`SegmentStatus` says whether the frame had valid depth, a plane and
something on it.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxreg.camera.model import RGBDFrame
from jaxreg.core._program_cache import persistent_jit
from jaxreg.core._result import select_status

__all__ = [
    "Clusters",
    "SegmentStatus",
    "Segmentation",
    "TablePlane",
    "choose_cluster",
    "cluster_mask",
    "euclidean_clusters",
    "fit_plane",
    "segment_frame",
]

_NONE = np.iinfo(np.int32).max  # label of a grid point in no cluster during propagation


class SegmentStatus(eqx.Enumeration):
    """Outcome of :func:`segment_frame`; each member's value is the message a user needs."""

    success = "segmented: a table plane and at least one cluster standing on it"
    too_few_points = "fewer than 3 sampled pixels have valid depth: the frame is (nearly) all holes"
    no_plane = (
        "no table plane: no plane through 3 sampled points had min_plane_inliers points within "
        "plane_distance; is the table in view, or is plane_distance too small for the noise?"
    )
    no_clusters = (
        "nothing stands on the table: no cluster above the plane reached min_cluster_size grid "
        "points; is the object in view, or the stride too coarse for its size?"
    )


class TablePlane(eqx.Module):
    """A plane ``normal . x + offset = 0`` (base frame, metres); ``normal`` is a unit vector
    pointing toward the camera, so ``normal . x + offset`` is the height above the plane.

    Attributes:
        normal: ``(3,)``.
        offset: ``()`` metres.
        num_inliers: ``()`` points within the inlier distance of the refit plane.
        inlier_fraction: ``()`` ``num_inliers`` over the valid points offered.
    """

    normal: Float[Array, " 3"]
    offset: Float[Array, ""]
    num_inliers: Int[Array, ""]
    inlier_fraction: Float[Array, ""]

    def height(self, points: Float[Array, "... 3"]) -> Float[Array, "..."]:
        """Signed height ``(...)`` of ``points`` ``(..., 3)`` above the plane (metres)."""
        return points @ self.normal + self.offset


def _refit(points: Array, weights: Array) -> tuple[Array, Array]:
    """Least-squares plane (unit normal, offset) of the weighted points (PCA)."""
    total = jnp.maximum(weights.sum(), 1.0)
    centroid = (weights[:, None] * points).sum(0) / total
    d = (points - centroid) * jnp.sqrt(weights)[:, None]
    _, vectors = jnp.linalg.eigh(d.T @ d)
    normal = vectors[:, 0]
    return normal, -normal @ centroid


def fit_plane(
    points: Float[Array, "N 3"],
    valid: Bool[Array, " N"],
    key: Array,
    *,
    distance: float | Array = 0.008,
    num_hypotheses: int = 64,
    score_step: int = 3,
    viewpoint: Float[Array, " 3"] | None = None,
) -> TablePlane:
    """The plane with the most points within ``distance`` (RANSAC, then two PCA refits).

    Args:
        points: ``(N, 3)`` (rows where ``valid`` is False are ignored; they may be NaN).
        valid: ``(N,)`` bool.
        key: PRNG key; hypothesis ``h`` uses the ``h``-th of ``num_hypotheses`` draws, so the
            result is a function of ``key`` and the inputs.
        distance: inlier distance (metres).
        num_hypotheses: static number of 3-point hypotheses, scored in one ``vmap``.
        score_step: static; hypotheses are scored on every ``score_step``-th point (the
            refits use all).
        viewpoint: ``(3,)`` a point on the side the normal must face (the camera centre);
            default the origin.

    Returns:
        :class:`TablePlane`; with fewer than 3 valid points its ``num_inliers`` is 0.
    """
    dtype = points.dtype
    safe = jnp.where(valid[:, None], points, 0.0)
    count = valid.sum()
    cumulative = jnp.cumsum(valid.astype(jnp.int32))
    # ranks 1..count of valid points; a repeated draw is a degenerate hypothesis (dropped)
    ranks = jax.random.randint(key, (num_hypotheses, 3), 1, jnp.maximum(count, 1) + 1)
    idx = jnp.searchsorted(cumulative, ranks)
    a, b, c = safe[idx[:, 0]], safe[idx[:, 1]], safe[idx[:, 2]]
    normals = jnp.cross(b - a, c - a)
    norm = jnp.linalg.norm(normals, axis=-1)
    ok = norm > 1e-9
    normals = normals / jnp.where(ok, norm, 1.0)[:, None]
    offsets = -jnp.sum(normals * a, -1)
    distance = jnp.asarray(distance, dtype)

    sub, sub_valid = safe[::score_step], valid[::score_step]

    def score(n, d):
        return jnp.sum(sub_valid & (jnp.abs(sub @ n + d) <= distance))

    scores = jnp.where(ok, jax.vmap(score)(normals, offsets), -1)
    best = jnp.argmax(scores)
    normal, offset = normals[best], offsets[best]
    for _ in range(2):
        inliers = valid & (jnp.abs(safe @ normal + offset) <= distance)
        new_normal, new_offset = _refit(safe, inliers.astype(dtype))
        enough = inliers.sum() >= 3
        normal = jnp.where(enough, new_normal, normal)
        offset = jnp.where(enough, new_offset, offset)
    viewpoint = jnp.zeros(3, dtype) if viewpoint is None else viewpoint.astype(dtype)
    flip = jnp.where(viewpoint @ normal + offset < 0, -1.0, 1.0).astype(dtype)
    normal, offset = normal * flip, offset * flip
    inliers = valid & (jnp.abs(safe @ normal + offset) <= distance)
    num = jnp.where(count >= 3, inliers.sum(), 0)
    return TablePlane(normal, offset, num, num / jnp.maximum(count, 1).astype(dtype))


class Clusters(eqx.Module):
    """Connected components of a grid of points (see :func:`euclidean_clusters`).

    Attributes:
        labels: ``(h, w)`` int32 cluster of each grid point, ``0 .. max_clusters - 1`` by
            decreasing size, ``-1`` for none (masked out, or in a component smaller than
            ``min_size`` or beyond the capacity).
        sizes: ``(max_clusters,)`` grid points per cluster (0 for unused slots).
        num_clusters: ``()`` clusters reported.
        overflow: ``()`` a component of at least ``min_size`` points did not fit the capacity,
            or the propagation stopped at ``max_iterations`` (labels may be split).
        iterations: ``()`` propagation rounds taken.
    """

    labels: Int[Array, "h w"]
    sizes: Int[Array, " C"]
    num_clusters: Int[Array, ""]
    overflow: Bool[Array, ""]
    iterations: Int[Array, ""]


def _offsets(window: int) -> list[tuple[int, int]]:
    return [
        (dy, dx)
        for dy in range(-window, window + 1)
        for dx in range(-window, window + 1)
        if (dy, dx) != (0, 0)
    ]


def _shift(x: Array, dy: int, dx: int, fill) -> Array:
    """``out[i, j] = x[i + dy, j + dx]``, ``fill`` outside the grid."""
    h, w = x.shape[:2]
    pad = [(max(-dy, 0), max(dy, 0)), (max(-dx, 0), max(dx, 0))] + [(0, 0)] * (x.ndim - 2)
    padded = jnp.pad(x, pad, constant_values=fill)
    return padded[max(dy, 0) : max(dy, 0) + h, max(dx, 0) : max(dx, 0) + w]


def _edges_dense(points, mask, d2, window):
    """Per grid offset ``(dy, dx)``: ``(h, w)`` bool, the point and its neighbour at that
    offset are both in ``mask`` and within ``sqrt(d2)`` metres."""
    edges = {}
    for dy, dx in _offsets(window)[len(_offsets(window)) // 2 :]:  # (dy, dx) > (0, 0)
        other = _shift(points, dy, dx, jnp.nan)
        near = jnp.sum(jnp.square(other - points), -1) <= d2  # False where either is NaN
        edges[dy, dx] = near & mask & _shift(mask, dy, dx, False)
        edges[-dy, -dx] = _shift(edges[dy, dx], -dy, -dx, False)  # the same edge, seen back
    return edges


def _propagate(propagate, start, max_iterations):
    """Min-label propagation to a fixed point (or ``max_iterations`` rounds): the labels,
    whether they were still changing, and the rounds taken."""

    def cond(state):
        labels, previous, i = state
        return (i < max_iterations) & jnp.any(labels != previous)

    def body(state):
        labels, _, i = state
        return propagate(labels), labels, i + 1

    labels, previous, iterations = jax.lax.while_loop(
        cond, body, (propagate(start), start, jnp.int32(1))
    )
    return labels, jnp.any(labels != previous), iterations


def _clusters_dense(points, mask, d2, window, max_iterations, max_clusters, min_size):
    """:func:`euclidean_clusters` on the whole grid: one shifted copy per offset and round;
    a component's root is the smallest flat grid index in it."""
    h, w = mask.shape
    edges = _edges_dense(points, mask, d2, window)
    start = jnp.where(mask, jnp.arange(h * w, dtype=jnp.int32).reshape(h, w), _NONE)

    def propagate(labels):
        best = labels
        for (dy, dx), edge in edges.items():
            best = jnp.minimum(best, jnp.where(edge, _shift(labels, dy, dx, _NONE), _NONE))
        for _ in range(2):  # pointer jumping: a label is a grid index whose label is smaller
            best = jnp.where(mask, best.reshape(-1)[jnp.where(mask, best, 0)], _NONE)
        return best

    labels, unconverged, iterations = _propagate(propagate, start, max_iterations)
    roots = jnp.where(mask, labels, h * w).reshape(-1)
    clusters = _largest(roots, max_clusters, min_size, unconverged, iterations)
    return eqx.tree_at(lambda c: c.labels, clusters, clusters.labels.reshape(h, w))


def _clusters_compact(points, mask, d2, window, max_iterations, max_clusters, min_size, capacity):
    """:func:`_clusters_dense` on the masked points alone, gathered into ``capacity`` slots
    (static; at least ``mask.sum()``) with each slot's neighbour slots listed once: a
    tabletop's few hundred points above the plane cost a few hundred, not the grid's tens of
    thousands. The same clusters (slots keep the grid's order, so ties break alike)."""
    h, w = mask.shape
    n = h * w
    (index,) = jnp.nonzero(mask.reshape(-1), size=capacity, fill_value=n)  # flat, n: padding
    live = index < n
    slot = jnp.full(n + 1, capacity, jnp.int32).at[index].set(jnp.arange(capacity, dtype=jnp.int32))
    slot = slot.at[n].set(capacity)  # grid index -> slot; capacity: not a masked point
    flat = points.reshape(-1, 3)
    here = flat[jnp.minimum(index, n - 1)]
    row, col = index // w, index % w
    neighbours = []
    for dy, dx in _offsets(window):
        r, c = row + dy, col + dx
        inside = live & (r >= 0) & (r < h) & (c >= 0) & (c < w)
        other = jnp.where(inside, r * w + c, n)
        near = jnp.sum(jnp.square(flat[jnp.minimum(other, n - 1)] - here), -1) <= d2
        neighbours.append(jnp.where(inside & near, slot[other], capacity))
    neighbours = jnp.stack(neighbours, -1)  # (capacity, offsets); capacity: no edge
    start = jnp.where(live, index, _NONE)

    def propagate(labels):
        best = jnp.minimum(labels, jnp.append(labels, _NONE)[neighbours].min(-1))
        for _ in range(2):  # pointer jumping, as in _clusters_dense
            best = jnp.where(live, jnp.append(best, _NONE)[slot[jnp.where(live, best, n)]], _NONE)
        return best

    labels, unconverged, iterations = _propagate(propagate, start, max_iterations)
    roots = slot[jnp.where(live, labels, n)]  # the root's slot; capacity for padding
    clusters = _largest(roots, max_clusters, min_size, unconverged, iterations)
    grid = jnp.full(n, -1, jnp.int32).at[index].set(clusters.labels, mode="drop")
    return eqx.tree_at(lambda c: c.labels, clusters, grid.reshape(h, w))


def euclidean_clusters(
    points: Float[Array, "h w 3"],
    mask: Bool[Array, "h w"],
    *,
    distance: float | Array,
    window: int = 2,
    max_clusters: int = 16,
    min_size: int = 20,
    max_iterations: int = 64,
    capacity: int = 4096,
) -> Clusters:
    """Connected components of the grid points in ``mask``, joined within ``window`` grid
    steps and ``distance`` metres (3D), the ``max_clusters`` largest of at least
    ``min_size`` points. When at most ``capacity`` points are masked, the propagation runs
    on those points alone; otherwise on the whole grid (same answer). ``window``,
    ``max_clusters``, ``min_size``, ``max_iterations`` and ``capacity`` are static.
    Jittable."""
    h, w = mask.shape
    if capacity <= max_clusters:
        raise ValueError(f"capacity ({capacity}) must exceed max_clusters ({max_clusters})")
    d2 = jnp.square(jnp.asarray(distance, points.dtype))
    args = (points, mask, d2, window, max_iterations, max_clusters, min_size)
    if capacity >= h * w:
        return _clusters_dense(*args)
    return jax.lax.cond(
        mask.sum() <= capacity,
        lambda: _clusters_compact(*args, capacity),
        lambda: _clusters_dense(*args),
    )


def _largest(roots, max_clusters, min_size, unconverged, iterations) -> Clusters:
    """The ``max_clusters`` largest components of at least ``min_size`` points, from each
    point's root ``(P,)`` (an id below ``P``; ``P`` for a point in none); labels ``(P,)``."""
    size = roots.shape[0]
    counts = jax.ops.segment_sum(jnp.ones_like(roots), roots, num_segments=size + 1)[:size]
    k = min(max_clusters + 1, size)
    sizes, ids = jax.lax.top_k(counts, k)
    if k <= max_clusters:  # fewer points than slots (a tiny image): the rest are empty
        sizes = jnp.concatenate([sizes, jnp.zeros(max_clusters + 1 - k, sizes.dtype)])
        ids = jnp.concatenate([ids, jnp.full(max_clusters + 1 - k, size, ids.dtype)])
    keep = sizes[:max_clusters] >= min_size
    extra = sizes[max_clusters] >= min_size
    match = (roots[:, None] == ids[None, :max_clusters]) & keep[None, :]
    out = jnp.where(match.any(-1), jnp.argmax(match, -1), -1).astype(jnp.int32)
    sizes = jnp.where(keep, sizes[:max_clusters], 0)
    return Clusters(out, sizes, keep.sum(), extra | unconverged, iterations)


class Segmentation(eqx.Module):
    """Result of :func:`segment_frame` (grid coordinates: see the module docstring).

    Attributes:
        points: ``(h, w, 3)`` base-frame points of the grid (NaN holes).
        plane: the :class:`TablePlane`.
        clusters: :class:`Clusters` of the points above the plane.
        footprint: ``(h, w)`` int32: each cluster's grid points plus the depth holes next to
            them (two 3x3 dilations into holes), ``-1`` elsewhere; the pixels a cluster
            covers in the image, measured or not.
        centroids: ``(C, 3)`` base-frame centroid of each cluster (zeros for unused slots).
        radii: ``(C,)`` largest distance of a cluster point from its centroid (metres).
        heights: ``(C,)`` largest height of a cluster point above the plane (metres).
        valid_points: ``()`` grid points with valid depth.
        above_plane: ``()`` grid points between ``min_height`` and ``max_height``.
        status: :class:`SegmentStatus`.
        stride: static grid step in pixels.
    """

    points: Float[Array, "h w 3"]
    plane: TablePlane
    clusters: Clusters
    footprint: Int[Array, "h w"]
    centroids: Float[Array, "C 3"]
    radii: Float[Array, " C"]
    heights: Float[Array, " C"]
    valid_points: Int[Array, ""]
    above_plane: Int[Array, ""]
    status: SegmentStatus
    stride: int = eqx.field(static=True)

    def status_message(self) -> str:
        """The status as text (host)."""
        return str(self.status._enumeration._index_to_message[int(self.status._value)])


def _footprint(labels: Array, holes: Array) -> Array:
    """Cluster labels grown twice into adjacent holes (3x3), -1 elsewhere."""
    out = labels
    for _ in range(2):
        grown = jnp.full_like(out, _NONE)
        for dy, dx in _offsets(1):
            nbr = _shift(out, dy, dx, -1)
            grown = jnp.minimum(grown, jnp.where(nbr >= 0, nbr, _NONE))
        out = jnp.where((out < 0) & holes & (grown != _NONE), grown, out)
    return out


def grid_points(frame: RGBDFrame, stride: int) -> Float[Array, "h w 3"]:
    """``(h, w, 3)`` base-frame points of every ``stride``-th pixel of every ``stride``-th row
    (``frame.points()[::stride, ::stride]`` without lifting the other pixels); NaN holes."""
    h, w = frame.depth.shape
    rows, cols = jnp.meshgrid(jnp.arange(0, h, stride), jnp.arange(0, w, stride), indexing="ij")
    return frame.points_at(rows, cols)


@persistent_jit
def _segment(frame, key, floats, min_plane_inliers, options):
    plane_distance, min_height, max_height, cluster_distance = floats
    stride, num_hypotheses, window, max_clusters, min_cluster_size = options
    points = grid_points(frame, stride)
    h, w = points.shape[:2]
    valid = jnp.all(jnp.isfinite(points), -1)
    flat, flat_valid = points.reshape(-1, 3), valid.reshape(-1)
    viewpoint = frame.base_T_camera.translation()
    plane = fit_plane(
        flat, flat_valid, key, distance=plane_distance, num_hypotheses=num_hypotheses,
        viewpoint=viewpoint,
    )  # fmt: skip
    height = jnp.where(valid, plane.height(jnp.where(valid[..., None], points, 0.0)), -jnp.inf)
    above = valid & (height > min_height) & (height < max_height)
    clusters = euclidean_clusters(
        points, above, distance=cluster_distance, window=window, max_clusters=max_clusters,
        min_size=min_cluster_size,
    )  # fmt: skip
    onehot = (clusters.labels.reshape(-1)[:, None] == jnp.arange(max_clusters)).astype(points.dtype)
    safe = jnp.where(flat_valid[:, None], flat, 0.0)
    count = jnp.maximum(onehot.sum(0), 1.0)
    centroids = (onehot.T @ safe) / count[:, None]
    spread = jnp.linalg.norm(safe[:, None, :] - centroids[None], axis=-1)
    radii = jnp.max(jnp.where(onehot > 0, spread, 0.0), 0)
    heights = jnp.max(jnp.where(onehot > 0, height.reshape(-1)[:, None], 0.0), 0)
    num_valid = flat_valid.sum()
    status = select_status(
        [
            (num_valid < 3, SegmentStatus.too_few_points),
            (plane.num_inliers < min_plane_inliers, SegmentStatus.no_plane),
            (clusters.num_clusters == 0, SegmentStatus.no_clusters),
        ],
        SegmentStatus.success,
    )
    return Segmentation(
        points=points,
        plane=plane,
        clusters=clusters,
        footprint=_footprint(clusters.labels, ~valid),
        centroids=centroids,
        radii=radii,
        heights=heights,
        valid_points=num_valid,
        above_plane=above.sum(),
        status=status,
        stride=stride,
    )


def segment_frame(
    frame: RGBDFrame,
    *,
    key: Array | None = None,
    stride: int = 4,
    plane_distance: float = 0.008,
    num_hypotheses: int = 64,
    min_plane_inliers: int = 200,
    min_height: float = 0.01,
    max_height: float = 0.5,
    cluster_distance: float = 0.015,
    window: int = 2,
    max_clusters: int = 16,
    min_cluster_size: int = 15,
) -> Segmentation:
    """Table plane and the clusters standing on it, in one compiled call.

    Args:
        frame: the :class:`~jaxreg.camera.RGBDFrame` (points in its base frame).
        key: PRNG key of the plane hypotheses (default ``PRNGKey(0)``).
        stride: grid step in pixels (static); 4 on an 848x480 image is a 212x120 grid.
        plane_distance: table inlier distance (metres).
        num_hypotheses: 3-point plane hypotheses (static).
        min_plane_inliers: grid points the plane needs.
        min_height, max_height: the band above the plane that holds objects (metres).
        cluster_distance: largest 3D gap inside a cluster (metres).
        window: image neighbourhood searched, in grid steps (static).
        max_clusters: cluster capacity (static).
        min_cluster_size: smallest cluster, in grid points (static).

    Returns:
        :class:`Segmentation`.
    """
    if not isinstance(frame, RGBDFrame):
        raise ValueError(f"frame must be a jaxreg.RGBDFrame, got {type(frame).__name__}")
    if stride < 1 or window < 1 or max_clusters < 1:
        raise ValueError("stride, window and max_clusters must be positive")
    key = jax.random.PRNGKey(0) if key is None else key
    dtype = frame.depth.dtype
    floats = [
        jnp.asarray(x, dtype) for x in (plane_distance, min_height, max_height, cluster_distance)
    ]
    options = (stride, num_hypotheses, window, max_clusters, min_cluster_size)
    return _segment(frame, key, floats, jnp.asarray(min_plane_inliers), options)


def cluster_mask(
    segmentation: Segmentation, index: int | Sequence[int], shape: tuple[int, int]
) -> np.ndarray:
    """``(H, W)`` bool host mask of the full-resolution pixels in the footprint of cluster
    ``index`` (or of several clusters; each grid point stands for its ``stride`` x
    ``stride`` block)."""
    s = segmentation.stride
    grid = np.isin(np.asarray(segmentation.footprint), np.atleast_1d(index))
    full = np.repeat(np.repeat(grid, s, axis=0), s, axis=1)
    out = np.zeros(shape, bool)
    out[: min(shape[0], full.shape[0]), : min(shape[1], full.shape[1])] = full[
        : shape[0], : shape[1]
    ]
    return out


def choose_cluster(
    segmentation: Segmentation,
    *,
    pixel: tuple[float, float] | None = None,
    box: tuple[float, float, float, float] | None = None,
    among: Sequence[int] | None = None,
) -> int | None:
    """The cluster a prompt points at (host): the one under ``pixel`` ``(u, v)`` (else the
    nearest within 3 grid steps), or the one with the most grid points inside ``box``
    ``(u0, v0, u1, v1)`` (pixels, inclusive); of the clusters ``among`` when given (every
    cluster otherwise). ``None`` when the prompt touches no such cluster."""
    if (pixel is None) == (box is None):
        raise ValueError("give exactly one prompt: pixel=(u, v) or box=(u0, v0, u1, v1)")
    labels = np.asarray(segmentation.clusters.labels)
    s = segmentation.stride
    rows, cols = np.nonzero(
        labels >= 0 if among is None else np.isin(labels, np.asarray(among, int))
    )
    if len(rows) == 0:
        return None
    if pixel is not None:
        u, v = pixel
        d2 = (cols - u / s) ** 2 + (rows - v / s) ** 2
        best = int(np.argmin(d2))
        return int(labels[rows[best], cols[best]]) if d2[best] <= 9 else None
    u0, v0, u1, v1 = box
    inside = (cols * s >= u0) & (cols * s <= u1) & (rows * s >= v0) & (rows * s <= v1)
    if not inside.any():
        return None
    return int(np.bincount(labels[rows[inside], cols[inside]]).argmax())
