"""Nearest-neighbour search with static shapes: 1-NN, kNN and fixed-capacity radius queries.

Two engines, one contract (sentinel index ``== M``, the number of target rows, plus a mask;
fixed capacities chosen on the host; overflow reported, never silently dropped):

* :class:`NeighborGrid` (:func:`build_grid`, then :func:`query_nearest`,
  :func:`query_knn`, :func:`query_radius`). Built once per target on the host, then passed
  as a pytree into ``jit`` / ``vmap``: the structure ICP queries every iteration while the
  source moves. A uniform grid of cells no smaller than ``max_distance`` covers the
  target's bounding box grown by ``max_distance``; each cell is refined as an octree until
  every leaf's *candidate list* fits the leaf target (48 for ``k == 1``). A leaf lists only
  the target points that can be a query's nearest neighbour (or one of its ``k`` nearest)
  for some query inside the leaf within ``max_distance``; a point is dropped from a leaf's
  list when

  - it is farther than ``max_distance`` from the leaf's box, or
  - (``k == 1``) one of the point's 8 nearest points is strictly closer to every point of
    the box: the box lies beyond their bisecting plane, so no query in it has this point
    as its nearest. The near points' bisectors bound the point's Voronoi cell, so a leaf
    keeps roughly the points whose Voronoi cells cross it; or
  - (``k > 1``) it is farther from the box than the ``k``-th smallest farthest-corner
    distance of the leaf's candidates (``k`` points are then closer to every query in it).

  The ``k == 1`` build runs in compiled loops (:mod:`jaxreg._octree`, numba, compiled once
  per machine and cached on disk); the ``k > 1`` and radius builds are numpy, vectorised
  over all nodes of a level. The octree is stored flattened: each top-level cell owns a
  dense block of sub-cells at its deepest level, so a query finds its leaf with two integer
  gathers (cell, then sub-cell), reads the leaf's ``capacity`` candidates as contiguous
  rows, and takes a running minimum: O(capacity) per query, independent of the target's
  size and of the octree's depth.

  **Exactness.** For a query whose true nearest neighbour (for kNN: each of its true ``k``
  nearest) lies within ``max_distance``, that point is among its leaf's candidates, so the
  answer is exact up to ties of equal distance (broken arbitrarily) and float rounding;
  neighbours beyond ``max_distance`` are reported invalid (sentinel index, ``inf``
  distance). Boxes are grown by a relative margin before every test, so that float32
  rounding of the build and of the query's leaf never breaks this. The only way to lose
  exactness is an explicit ``capacity`` that a leaf still exceeds at the maximum depth: the
  leaf keeps the candidates nearest its centre and ``grid.overflow`` is set (the jax-md
  contract: rebuild with a larger capacity). With ``capacity=None`` the host sizes it so
  this never happens.

  **Shapes.** Only ``k`` is static: origin, cell size, ``dims`` and ``num_points`` are
  array leaves; the candidate table's rows are padded to a power of two, the cell table to
  the cells of the cube around the target's bounding sphere (which holds every rotation of
  it), the leaf map to eight entries per table row, and the capacity is rounded up to a
  multiple of 16. Targets of similar size and extent (a scene re-captured, the
  same cloud rotated) give grids of identical structure and shapes, so a jitted function
  taking the grid as an argument compiles once for all of them (tested on milk.pcd against
  itself rotated by 30 degrees with 5% of its points dropped).

* Blocked brute force (:func:`knn`, :func:`radius_search`): exact, jittable with the target
  traced (no host step), memory bounded by mapping ``lax.map`` over query blocks of ``block``
  rows (``block * M`` distances live at once). Distances are screened with one matrix product
  on clouds centred at the target's mean, and the kept ones recomputed exactly.

When each is used (``benchmarks/bench_neighbors.py`` on milk.pcd, 13.7k points, and its
4 mm voxel downsample, 3.7k points, radius 2 cm, on a 2-core CPU shared with other jobs, so
absolute timings vary up to ~2x between runs; Open3D timed in the same runs, 2026-11-21):

* ICP correspondences (1-NN within ``max_correspondence_distance``, the same target for
  every iteration and every start): the grid. At 3.7k points it builds in ~10-16 ms
  (capacity 48, depth 2, 3 MB; the vectorised numpy build it replaced took ~25-50 ms, the
  one before that ~140-380 ms), a query takes ~0.1 ms inside a loop (~0.4 ms as its own
  jitted call), 40 dependent queries in one jit ~4-8 ms: build + 40 queries ~20-25 ms,
  where Open3D's whole 40-iteration ``registration_icp`` takes ~30-40 ms (its kd-tree
  builds in 0.3 ms and it runs on both cores). At 13.7k: build ~70 ms (previously
  ~120-250 ms), 40 queries ~25 ms, together ~100 ms against ~190 ms for Open3D. Reuse a
  grid across calls on the same target (``icp(..., neighbors=grid)``,
  :func:`jaxreg.icp.multistart_icp`). 64 vmapped query sets cost ~35-40 ms (3.7k) and
  ~140 ms (13.7k). Blocked brute force takes ~80 ms per 3.7k query (one 3.7k x 3.7k
  distance matrix), so it is the reference, the engine under ``jit`` with a traced
  target, and the choice on GPUs, where that matrix product is cheap.
* kNN for normals (one pass, ``k`` ~ 20, exact kNN as Open3D): on a concrete cloud
  :func:`jaxreg.normals.estimate_normals` finds the exact ``k`` nearest with compiled host
  loops over a hash grid (:func:`jaxreg._octree.self_knn`, as fast as scipy's cKDTree);
  the whole estimate costs ~12-14 ms at 3.7k and ~44 ms at 13.7k, against ~7 ms and
  ~26 ms for Open3D's ``estimate_normals`` and ~80 ms and ~0.7 s with the blocked brute
  force it uses when the cloud is traced. A ``k``-NN grid (``build_grid(k=20)`` then
  :func:`query_knn`) costs about as much as the host loops and serves jitted code.
* A kd-tree in JAX was not written: its traversal is a data-dependent loop per query,
  which under ``vmap`` runs every lane to the slowest lane's depth, and its leaf scans are
  the same gathers the grid does after O(1) instead of O(log M) steps.

Shapes: targets are ``(M, 3)``, queries ``(N, 3)``; write queries unbatched and ``vmap`` over
query sets (the grid is shared: ``in_axes=None``). Frames: queries and target must be in the
same frame (for ICP: the source moved by the current pose, in target coordinates).
"""

from __future__ import annotations

import itertools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg import _octree

__all__ = [
    "NeighborGrid",
    "build_grid",
    "knn",
    "query_knn",
    "query_nearest",
    "query_radius",
    "radius_search",
    "valid_rows",
    "validate_grid",
    "voxel_downsample",
]

# Octant order of a node's children and of a box's corners: bit 2 = x, bit 1 = y, bit 0 = z.
_OCTANTS = np.array(list(itertools.product((0, 1), repeat=3)), dtype=np.int64)
_STENCIL = np.array(list(itertools.product((-1, 0, 1), repeat=3)), dtype=np.int64)
# Candidate lists this short or shorter are scanned by an unrolled loop (fast on CPU, compile
# time linear in the length); longer ones by a reduction over the candidate axis.
_UNROLL_LIMIT = 256


class NeighborGrid(eqx.Module):
    """A target cloud indexed for static-shape neighbour queries (see the module docstring).

    Built by :func:`build_grid`; a pytree of arrays (only ``k`` is static) whose shapes are
    rounded up to powers of two, so targets of similar size and extent give grids of the
    same structure and shapes: a jitted function taking the grid compiles once for them.

    Attributes:
        origin: ``(3,)`` corner of the top-level grid, in target coordinates.
        cell_size: ``()`` edge of a top-level cell (``>= max_distance``).
        max_distance: ``()`` the radius within which queries are exact.
        dims: ``(3,)`` top-level cells per axis.
        cells: ``(>= prod(dims), 2)`` per top-level cell (x-major order): the offset of its
            block in ``leaf_map`` and its refinement depth ``d``; the block holds the leaf
            row of each of its ``(2^d)^3`` sub-cells. Rows past ``prod(dims)`` are padding.
        leaf_map: ``(entries,)`` leaf row of every sub-cell; entry 0 and padding hold row 0,
            the empty leaf.
        candidate_index: ``(leaves, capacity)`` target row of each candidate, padded with
            the sentinel ``num_points``.
        candidate_points: ``(3, leaves, capacity)`` candidate coordinates, one plane per
            axis (``inf`` in padding slots), so a query reads them without a second gather.
        num_points: ``()`` ``M``, the number of target rows (masked rows included): the
            sentinel index.
        overflow: ``()`` True when some leaf had more candidates than ``capacity`` at the
            maximum depth and was truncated: queries may then be inexact.
        k: static: the grid answers kNN queries for up to ``k`` neighbours; ``None`` keeps
            every point within ``max_distance`` (needed by :func:`query_radius`).
    """

    origin: Float[Array, "3"]
    cell_size: Float[Array, ""]
    max_distance: Float[Array, ""]
    dims: Int[Array, "3"]
    cells: Int[Array, "cells 2"]
    leaf_map: Int[Array, " entries"]
    candidate_index: Int[Array, "leaves capacity"]
    candidate_points: Float[Array, "3 leaves capacity"]
    num_points: Int[Array, ""]
    overflow: Bool[Array, ""]
    k: int | None = eqx.field(static=True)

    @property
    def capacity(self) -> int:
        """Candidate slots per leaf (static: the candidate table's width)."""
        return self.candidate_index.shape[1]

    @property
    def num_leaves(self) -> int:
        """Rows of the candidate table, the empty leaf and padding included."""
        return self.candidate_index.shape[0]

    @property
    def depth(self) -> int:
        """Deepest refinement below the top-level cells (host; not under ``jit``)."""
        return int(self.cells[:, 1].max())

    @property
    def nbytes(self) -> int:
        """Memory held by the grid's arrays, in bytes."""
        return sum(x.nbytes for x in jax.tree_util.tree_leaves(self))


# --------------------------------------------------------------------------------------------
# Host-side construction.
#
# numpy on the host, vectorised over all nodes of a level at once (no Python loop over cells,
# nodes or points), in float32. Every box is grown by ``margin`` before it is tested, so
# float32 rounding (of the build, and of the query's choice of leaf) can only keep a candidate
# that exact arithmetic would drop, never drop one it would keep.

_OCT32 = _OCTANTS.astype(np.int32)
_OCT_F = _OCTANTS.astype(np.float32)
_NEAR = 9  # witnesses per target point (itself among them) pruning 1-NN candidate lists
# Default refinement target of 1-NN leaves. Measured on milk.pcd (bench_neighbors.py): 48
# builds 1.3-1.6x faster than 32 for 40 queries costing 1.1-1.2x more.
_LEAF_TARGET = 48


def _bucket(n: int) -> int:
    """Table length for ``n`` rows: the next power of two (at least 64), so that similar
    targets give identically shaped grids and a jitted caller does not recompile."""
    return 1 << max(6, max(0, int(n) - 1).bit_length())


def _split_plan(node_top, counts, level, map_size, leaf_target, max_depth, max_map, max_pairs):
    """Which nodes of this level to split, or ``None`` when refinement stops here.

    Nodes with more than ``leaf_target`` candidates split unless ``level`` is ``max_depth``
    or the split would grow ``leaf_map`` (now ``map_size`` entries) past ``max_map`` or the
    next level's pairs past ``max_pairs``. Returns ``(split (L,), deeper, grow)``: the
    top-level cells that gain a level and the ``leaf_map`` entries that costs.
    """
    split = counts > leaf_target
    if level == max_depth or not split.any():
        return None
    deeper = np.unique(node_top[split])
    grow = len(deeper) * 7 * 8**level
    if map_size + grow > max_map or 8 * int(counts[split].sum()) > max_pairs:
        return None
    return split, deeper, grow


def _levels_nearest(x, cell, dims, h, margin, r2, *budget):
    """Leaf nodes and candidate pairs for ``k == 1`` (see :mod:`jaxreg._octree`).

    ``x`` is float64 relative to the grid origin. Returns ``(levels, cell_depth)``, with per
    level ``(node_top, node_sub, node, pid)``: the top-level cell and sub-cell coordinates of
    each node, and the (node, point) pairs of its leaf nodes.
    """
    dims64 = np.asarray(dims, np.int64)
    half_spaces = _octree.witnesses(x, _octree.self_knn(x, _NEAR)[0], float(margin))
    node_top, counts, pid = _octree.top_level_nodes(
        x, cell.astype(np.int64), dims64, float(h), float(margin), float(r2), *half_spaces
    )
    node_sub = np.zeros((len(node_top), 3), np.int64)
    cell_depth = np.zeros(math.prod(dims), np.int32)
    levels = []
    map_size = len(node_top)
    level = 0
    while True:
        plan = _split_plan(node_top, counts, level, map_size, *budget)
        node = np.repeat(np.arange(len(counts)), counts)
        if plan is None:
            levels.append((node_top, node_sub, node, pid))
            return levels, cell_depth
        split, deeper, grow = plan
        map_size += grow
        cell_depth[deeper] = level + 1
        leaf = ~split[node]
        levels.append((node_top, node_sub, node[leaf], pid[leaf]))
        corner = np.stack(np.unravel_index(node_top, dims), axis=1) * 2**level + node_sub
        level += 1
        counts, pid = _octree.split_nodes(
            x, corner, counts, pid, split, h / 2**level, float(margin), float(r2), *half_spaces
        )
        node_top = np.repeat(node_top[split], 8)
        node_sub = (2 * node_sub[split][:, None, :] + _OCTANTS[None]).reshape(-1, 3)


def _kth_smallest(values: np.ndarray, lens: np.ndarray, k: int) -> np.ndarray:
    """Per run of ``values`` (runs of lengths ``lens >= 1``): its ``k``-th smallest, ``inf``
    for runs shorter than ``k``."""
    starts = np.cumsum(lens) - lens
    width = int(lens.max())
    if width < k:
        return np.full(len(lens), np.inf, values.dtype)
    run = np.repeat(np.arange(len(lens)), lens)
    table = np.full((len(lens), width), np.inf, values.dtype)
    table[run, np.arange(len(values)) - starts[run]] = values
    return np.partition(table, k - 1, axis=1)[:, k - 1]


def _prune_kth(b: list[np.ndarray], lens: np.ndarray, size, r2, k: int | None) -> np.ndarray:
    """Keep-mask of node-major pairs (runs ``lens``) with box-local coordinates ``b`` in grown
    boxes of edge ``size``: within ``max_distance`` of the box and, for ``k``, within the
    ``k``-th smallest farthest-corner distance of the node's points (``k`` points are then
    closer to every query in the box)."""
    g = [np.maximum(np.maximum(-bi, bi - size), np.float32(0)) for bi in b]
    keep = g[0] * g[0] + g[1] * g[1] + g[2] * g[2]
    if k is not None and len(lens):
        f = [np.maximum(bi, size - bi) for bi in b]
        bound = _kth_smallest(f[0] * f[0] + f[1] * f[1] + f[2] * f[2], lens, k)
        keep = keep <= np.minimum(np.repeat(bound, lens), r2)
    else:
        keep = keep <= r2
    return keep


def _levels_general(x, cell, dims, h, margin, r2, k, *budget):
    """Leaf nodes and candidate pairs for ``k > 1`` or radius grids (``k=None``), in node-major
    order built from a cell-sorted copy of the points (no pair sort). Same output as
    :func:`_levels_nearest`."""
    n_cells = math.prod(dims)
    lin = (cell[:, 0].astype(np.int64) * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(lin, kind="stable")
    count = np.bincount(lin, minlength=n_cells)
    start = np.cumsum(count) - count
    # Nodes: every cell within the 27-cell stencil of an occupied one.
    pad = tuple(d + 2 for d in dims)
    occupied = np.stack(np.unravel_index(np.flatnonzero(count), dims), axis=1)
    mark = np.zeros(pad, bool)
    for o in _STENCIL:
        mark[tuple(occupied[:, i] + 1 + o[i] for i in range(3))] = True
    node_top = np.flatnonzero(mark[1:-1, 1:-1, 1:-1].ravel())
    coords = np.stack(np.unravel_index(node_top, dims), axis=1)
    cpad, spad = np.zeros(pad, np.int64), np.zeros(pad, np.int64)
    cpad[1:-1, 1:-1, 1:-1] = count.reshape(dims)
    spad[1:-1, 1:-1, 1:-1] = start.reshape(dims)
    around = tuple(coords[:, i : i + 1] + 1 + _STENCIL[:, i] for i in range(3))
    lens27, starts27 = cpad[around].ravel(), spad[around].ravel()
    offsets = np.cumsum(lens27) - lens27
    pid = order[np.arange(int(lens27.sum())) + np.repeat(starts27 - offsets, lens27)]
    pid = pid.astype(np.int32)
    lens = lens27.reshape(-1, 27).sum(1)
    lo = coords.astype(np.float32) * np.float32(h) - np.float32(margin)
    b = [x[pid, i] - np.repeat(lo[:, i], lens) for i in range(3)]
    size = np.float32(h + 2 * margin)
    node_sub = np.zeros((len(node_top), 3), np.int32)
    cell_depth = np.zeros(n_cells, np.int32)
    levels = []
    map_size = len(node_top)
    level = 0
    while True:
        keep = np.flatnonzero(_prune_kth(b, lens, size, r2, k))
        node = np.repeat(np.arange(len(lens)), lens)[keep]
        pid, b = pid[keep], [bi[keep] for bi in b]
        counts = np.bincount(node, minlength=len(lens))
        plan = _split_plan(node_top, counts, level, map_size, *budget)
        if plan is None:
            levels.append((node_top, node_sub, node, pid))
            return levels, cell_depth
        split, deeper, grow = plan
        map_size += grow
        cell_depth[deeper] = level + 1
        on_split = split[node]
        leaf = np.flatnonzero(~on_split)
        levels.append((node_top, node_sub, node[leaf], pid[leaf]))
        # Children, octant-major: runs (octant, parent) stay contiguous, in parent order.
        sel = np.flatnonzero(on_split)
        level += 1
        edge = np.float32(h / 2**level)
        size = np.float32(h / 2**level + 2 * margin)
        b = [(bi[sel][None, :] - edge * _OCT_F[:, i : i + 1]).reshape(-1) for i, bi in enumerate(b)]
        pid = np.tile(pid[sel], 8)
        lens = np.tile(counts[split], 8)
        node_top = np.tile(node_top[split], 8)
        node_sub = (2 * node_sub[split][None] + _OCT32[:, None, :]).reshape(-1, 3)


def _group_order(keys: np.ndarray, n_keys: int) -> np.ndarray:
    """Stable order sorting integer ``0 <= keys < n_keys < 2^32``: LSD radix on 16-bit digits
    (numpy's stable sort of uint16 is a counting sort, far faster than a comparison sort)."""
    if n_keys <= 1 << 16:
        return np.argsort(keys.astype(np.uint16), kind="stable")
    low = np.argsort((keys & 0xFFFF).astype(np.uint16), kind="stable")
    return low[np.argsort((keys[low] >> 16).astype(np.uint16), kind="stable")]


def _assemble(levels, cell_depth, dims, h, x, capacity):
    """Flattened octree tables from the leaf pairs of every level (see :class:`NeighborGrid`).

    Returns ``(cells, leaf_map, rows, slots, pids, cap, overflow, n_rows)``: the table
    position ``(rows, slots)`` of each kept candidate ``pids`` (row 0 is the empty leaf).
    """
    n_cells = math.prod(dims)
    row_parts, pid_parts, leaf_info = [], [], []
    n_rows = 1
    for level, (node_top, node_sub, node, pid) in enumerate(levels):
        present = np.bincount(node, minlength=len(node_top)) > 0
        ids = np.flatnonzero(present)
        row_of = np.zeros(len(node_top), np.int64)
        row_of[ids] = n_rows + np.arange(len(ids))
        n_rows += len(ids)
        row_parts.append(row_of[node])
        pid_parts.append(pid)
        leaf_info.append((level, node_top[ids], node_sub[ids], row_of[ids]))
    rows = np.concatenate([np.zeros(0, np.int64), *row_parts])
    pids = np.concatenate([np.zeros(0, np.int32), *pid_parts])
    counts = np.bincount(rows, minlength=n_rows)
    needed = int(counts.max()) if len(rows) else 0
    cap = capacity if capacity is not None else max(16, -(-needed // 16) * 16)
    overflow = needed > cap
    if overflow:
        # Truncation keeps each leaf's candidates nearest its centre.
        centre = np.zeros((n_rows, 3), np.float32)
        for level, top, sub, row in leaf_info:
            corner = np.stack(np.unravel_index(top, dims), axis=1) * 2**level + sub
            centre[row] = (corner + 0.5) * np.float32(h / 2**level)
        dist = ((x[pids] - centre[rows]) ** 2).sum(1)
        order = np.lexsort((dist, rows))
    else:
        order = _group_order(rows, n_rows)
    rows, pids = rows[order], pids[order]
    starts = np.cumsum(counts) - counts
    slots = np.arange(len(rows)) - starts[rows]
    fits = slots < cap
    rows, pids, slots = rows[fits], pids[fits], slots[fits]

    # Each top-level cell with leaves owns a dense block of (2^depth)^3 entries.
    used = np.zeros(n_cells, bool)
    for _, top, _, _ in leaf_info:
        used[top] = True
    depth = np.where(used, cell_depth, 0)
    block = np.where(used, 8 ** depth.astype(np.int64), 0)
    base = np.where(used, 1 + np.cumsum(block) - block, 0)
    leaf_map = np.zeros(1 + int(block.sum()), np.int32)
    for level, top, sub, row in leaf_info:
        extra = depth[top] - level  # the leaf spans 2^extra sub-cells per axis
        for e in np.unique(extra):
            sel = np.flatnonzero(extra == e)
            side = 1 << int(e)
            span = np.stack(np.unravel_index(np.arange(side**3), (side,) * 3), axis=1)
            full = (1 << depth[top[sel]].astype(np.int64))[:, None]
            s = sub[sel][:, None, :].astype(np.int64) * side + span[None]
            entry = base[top[sel]][:, None] + (s[..., 0] * full + s[..., 1]) * full + s[..., 2]
            leaf_map[entry] = row[sel][:, None]
    cells = np.stack([base, depth], axis=1).astype(np.int32)
    return cells, leaf_map, rows, slots, pids, cap, overflow, n_rows


def build_grid(
    target: ArrayLike,
    max_distance: float,
    *,
    k: int | None = 1,
    capacity: int | None = None,
    max_depth: int | None = None,
    max_cells: int = 1 << 21,
    max_map: int = 1 << 22,
    max_pairs: int = 1 << 23,
    mask: ArrayLike | None = None,
) -> NeighborGrid:
    """Indexes a target cloud for exact neighbour queries within ``max_distance`` (host).

    Runs on the host with numpy (``target`` must be concrete, not a tracer); the result is a
    pytree to pass into jitted code. Build once per target, query many times.

    Args:
        target: ``(M, 3)`` target points. Rows that are not finite, or where ``mask`` is
            False, are never returned; indices refer to rows of ``target``.
        max_distance: radius within which queries are exact (ICP: the largest
            ``max_correspondence_distance`` of its schedule). Larger radii cost build time
            and memory, not query time.
        k: the largest ``k`` that :func:`query_knn` will ask for (1 for ICP, the default);
            ``None`` keeps every point within ``max_distance`` of a leaf, as
            :func:`query_radius` needs.
        capacity: candidate slots per leaf. ``None``: refine leaves to at most 48
            candidates for ``k == 1`` (``max(32, 2 k)`` otherwise) and size the capacity on
            the host (the longest list rounded up to a multiple of 16) so nothing is
            dropped. An explicit value is also the refinement target and a hard cap:
            leaves still above it at the maximum depth are truncated (keeping the
            candidates nearest the leaf's centre) and ``overflow`` is set. Query time
            grows with the capacity, build time falls.
        max_depth: levels of octree refinement below the top-level cells; default 6 for
            ``k == 1`` and 0 otherwise (kNN and radius lists shrink little when refined:
            measured, the build time it costs exceeds the query time it saves).
        max_cells: cap on the number of top-level cells; the cell size grows (beyond
            ``max_distance``) to respect it, which bounds memory for tiny radii.
        max_map: cap on the entries of ``leaf_map``; refinement stops before exceeding it.
        max_pairs: cap on the (node, candidate) pairs of one refinement level (host memory).
        mask: ``(M,)`` optional validity of the target rows.

    Returns:
        A :class:`NeighborGrid`, float32 unless ``target`` is float64 with x64 enabled.

    Raises:
        ValueError: ``target`` is a tracer or not ``(M, 3)``, ``max_distance`` is not
            positive and finite, ``k`` or ``capacity`` is not positive, or ``capacity < k``.
    """
    if isinstance(target, jax.core.Tracer):
        raise ValueError("build_grid runs on the host: build the grid outside jit, pass it in")
    pts = np.asarray(target, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"target must be (M, 3), got shape {pts.shape}")
    r = float(max_distance)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"max_distance must be positive and finite, got {max_distance}")
    if k is not None and k < 1:
        raise ValueError(f"k must be >= 1 or None, got {k}")
    if capacity is not None and capacity < max(1, k or 1):
        raise ValueError(f"capacity must be >= max(1, k), got {capacity} with k={k}")
    if max_depth is None:
        max_depth = 6 if k == 1 else 0
    num_points = pts.shape[0]
    valid = np.all(np.isfinite(pts), axis=1)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        if m.shape != (num_points,):
            raise ValueError(f"mask must be ({num_points},), got shape {m.shape}")
        valid &= m
    in_dtype = np.asarray(target).dtype
    dtype = jax.dtypes.canonicalize_dtype(
        in_dtype if np.issubdtype(in_dtype, np.floating) else np.float64
    )
    rows = np.flatnonzero(valid)
    points = pts[rows]

    # Boxes are grown by a margin far above float32 rounding of the query's sub-cell (and of
    # the build's own float32 arithmetic), so a query assigned to a neighbouring sub-cell by
    # rounding still finds its neighbours.
    margin = 1e-5 * (float(np.abs(points).max()) + r) if len(points) else 0.0
    if len(points):
        lo = points.min(0) - r - margin
        extent = points.max(0) + r + margin - lo
        # Cells at least max_distance (plus the margins) wide: the cells a point can be a
        # candidate of are then within its 27-cell stencil.
        h = max(r + 2 * margin, float(np.cbrt(np.prod(extent) / max_cells)))
        while True:
            dims = tuple(int(d) for d in np.maximum(np.ceil(extent / h), 1))
            if math.prod(dims) <= max_cells:
                break
            h *= 1.05
    else:
        lo, h, dims = np.zeros(3), r, (1, 1, 1)
    if capacity is not None:
        leaf_target = capacity
    else:
        leaf_target = _LEAF_TARGET if k == 1 else max(32, 2 * (k or 16))
    r2 = np.float32((r + margin) ** 2)
    x = (points - lo).astype(np.float32)
    cell = np.minimum(np.floor(x / np.float32(h)), np.array(dims) - 1).astype(np.int32)
    budget = (leaf_target, max_depth, max_map, max_pairs)
    if not len(points):
        levels, cell_depth = [], np.zeros(math.prod(dims), np.int32)
    elif k == 1:
        x64 = points - lo
        r2_64 = (r + margin) ** 2
        levels, cell_depth = _levels_nearest(x64, cell, dims, h, margin, r2_64, *budget)
    else:
        levels, cell_depth = _levels_general(x, cell, dims, h, margin, r2, k, *budget)
    cells, leaf_map, slot_rows, slots, pids, cap, overflow, n_rows = _assemble(
        levels, cell_depth, dims, h, x, capacity
    )
    # Padded sizes. The cell table to the cells of the cube around the bounding sphere (any
    # rotation of the target fits in it); the map to 8 entries per table row unless it needs
    # more (it depends on how many cells refine one level deeper, a threshold effect).
    n_table = _bucket(n_rows)
    if len(points):
        radius = float(np.sqrt(((points - points.mean(0)) ** 2).sum(1).max()))
        sphere = min(math.ceil((2 * (radius + r + margin)) / h + 1) ** 3, max_cells)
    else:
        sphere = 1
    cells = np.pad(cells, ((0, _bucket(max(len(cells), sphere)) - len(cells)), (0, 0)))
    leaf_map = np.pad(leaf_map, (0, max(_bucket(len(leaf_map)), 8 * n_table) - len(leaf_map)))
    cand_index, cand_points = _octree.candidate_tables(
        slot_rows, slots, pids, rows, points.astype(dtype), n_table, cap, num_points
    )
    arrays = jax.device_put(  # one transfer for all leaves
        (
            np.asarray(lo, dtype),
            np.asarray(h, dtype),
            np.asarray(r, dtype),
            np.asarray(dims, np.int32),
            cells,
            leaf_map,
            cand_index,
            cand_points,
            np.asarray(num_points, np.int32),
            np.asarray(overflow),
        )
    )
    return NeighborGrid(*arrays, k=k)


def validate_grid(grid: NeighborGrid, target: ArrayLike, max_distance: ArrayLike) -> None:
    """Checks on the host that ``grid`` can answer queries against ``target`` exactly.

    A grid's indices refer to the rows of the target it was built on, and its answers are
    exact only within ``grid.max_distance`` and without ``overflow``; a grid that fails any
    of these gives plausible but wrong neighbours, so callers that accept a prebuilt grid
    (ICP's ``neighbors=``) check it here before use. The coordinate check compares every
    filled candidate slot with ``target`` (vectorised numpy, O(leaves x capacity)).

    Values cannot be inspected under ``jit``: checks whose inputs are traced are skipped, so
    call this before entering ``jit`` (the shapes are still checked).

    Args:
        grid: from :func:`build_grid`.
        target: ``(M, 3)`` the target the caller will match against.
        max_distance: the largest query radius the caller will use (ICP: the largest
            ``max_correspondence_distance`` of its schedule); a scalar or an array of radii.

    Raises:
        ValueError: ``target`` is not ``(M, 3)``; the grid was built on another target
            (row count or candidate coordinates differ); ``grid.max_distance`` is smaller
            than ``max_distance``; or ``grid.overflow`` is set.
    """
    shape = np.shape(target)
    if len(shape) != 2 or shape[1] != 3:
        raise ValueError(f"target must be (M, 3), got shape {shape}")

    def concrete(*xs) -> bool:
        return not any(isinstance(x, jax.core.Tracer) for x in xs)

    if concrete(grid.num_points) and int(grid.num_points) != shape[0]:
        raise ValueError(
            f"the grid was built on a target of {int(grid.num_points)} rows, not this one "
            f"({shape[0]} rows): build it with build_grid(target, ...) on this target"
        )
    if concrete(grid.candidate_index, grid.candidate_points, target):
        index = np.asarray(grid.candidate_index)
        coords = np.asarray(grid.candidate_points)
        filled = index < shape[0]
        stored = coords[:, filled].T
        expected = np.asarray(target)[index[filled]].astype(coords.dtype)
        if not np.array_equal(stored, expected):
            raise ValueError(
                "the grid was built on another target (its candidate coordinates differ "
                "from target's rows): build it with build_grid(target, ...) on this target"
            )
    if concrete(grid.max_distance, max_distance):
        dtype = np.asarray(grid.max_distance).dtype
        needed = np.max(np.asarray(max_distance, dtype))
        if needed > np.asarray(grid.max_distance):
            raise ValueError(
                f"the grid is exact within {float(grid.max_distance):g} but queries reach "
                f"{float(needed):g}: rebuild it with build_grid(target, max_distance="
                f"{float(needed):g})"
            )
    if concrete(grid.overflow) and bool(grid.overflow):
        raise ValueError(
            "the grid overflowed (a leaf had more candidates than its capacity), so its "
            "queries may be inexact: rebuild it with capacity=None or a larger capacity"
        )


# --------------------------------------------------------------------------------------------
# Grid queries (jittable; vmap over query sets with the grid shared).


def _check_queries(queries: ArrayLike) -> Array:
    queries = jnp.asarray(queries)
    if queries.ndim != 2 or queries.shape[-1] != 3:
        raise ValueError(f"queries must be (N, 3) (vmap for batches), got {queries.shape}")
    return queries


def _leaf(grid: NeighborGrid, queries: Array) -> tuple[Array, Array]:
    """Leaf row of each query and whether the query lies inside the grid."""
    u = (queries.astype(grid.origin.dtype) - grid.origin) / grid.cell_size
    finite = jnp.all(jnp.isfinite(u), axis=-1)
    u = jnp.where(finite[:, None], u, -1.0)
    cell = jnp.floor(u)
    dims = jnp.asarray(grid.dims, u.dtype)
    inside = finite & jnp.all((cell >= 0) & (cell < dims), axis=-1)
    c = jnp.clip(cell, 0, dims - 1).astype(jnp.int32)
    cid = (c[:, 0] * grid.dims[1] + c[:, 1]) * grid.dims[2] + c[:, 2]
    info = grid.cells[cid]
    side = jnp.left_shift(1, info[:, 1])
    sub = jnp.floor((u - cell) * side[:, None].astype(u.dtype)).astype(jnp.int32)
    sub = jnp.clip(sub, 0, side[:, None] - 1)
    entry = info[:, 0] + (sub[:, 0] * side + sub[:, 1]) * side + sub[:, 2]
    return jnp.where(inside, grid.leaf_map[entry], 0), inside


def _candidate_sq_dists(grid: NeighborGrid, queries: Array, leaf: Array) -> Array:
    """``(N, capacity)`` squared distances to each query's candidates (``inf`` padding)."""
    q = queries.astype(grid.candidate_points.dtype)
    cx, cy, cz = grid.candidate_points
    dx, dy, dz = cx[leaf] - q[:, :1], cy[leaf] - q[:, 1:2], cz[leaf] - q[:, 2:]
    return dx * dx + dy * dy + dz * dz


def _pad_slots(index, sq_dists, mask, width: int, sentinel):
    """Pads ``(N, w)`` neighbour slots to ``(N, width)`` with empty ones (sentinel index,
    ``inf`` distance, mask False)."""
    pad = ((0, 0), (0, width - index.shape[1]))
    return (
        jnp.pad(index, pad, constant_values=sentinel),
        jnp.pad(sq_dists, pad, constant_values=jnp.inf),
        jnp.pad(mask, pad),
    )


def _radius2(grid: NeighborGrid, max_distance, dtype) -> Array:
    r = grid.max_distance if max_distance is None else jnp.minimum(max_distance, grid.max_distance)
    return jnp.square(jnp.asarray(r, dtype))


def _nearest_slot(d2: Float[Array, "N c"]) -> tuple[Float[Array, " N"], Int[Array, " N"]]:
    """Smallest squared distance of each row and its slot (the first on ties).

    Up to ``_UNROLL_LIMIT`` candidates: an unrolled running minimum over the columns, which
    XLA fuses with the candidate gather and vectorises over queries on CPU. A reduction
    along the minor axis (the fallback for longer lists, bounding compile time) is ~6x
    slower at capacity 96; a ``scan`` over column blocks was slower still (it materialises
    the gathered distances).
    """
    if d2.shape[1] > _UNROLL_LIMIT:
        return jnp.min(d2, axis=1), jnp.argmin(d2, axis=1).astype(jnp.int32)
    cols = d2.T
    best, slot = cols[0], jnp.zeros(cols.shape[1], jnp.int32)
    for j in range(1, cols.shape[0]):
        better = cols[j] < best
        best = jnp.where(better, cols[j], best)
        slot = jnp.where(better, j, slot)
    return best, slot


def query_nearest(
    grid: NeighborGrid, queries: ArrayLike, max_distance: ArrayLike | None = None
) -> tuple[Int[Array, " N"], Float[Array, " N"], Bool[Array, " N"]]:
    """Nearest target point of each query within ``max_distance`` (jittable).

    Args:
        grid: from :func:`build_grid` on the target.
        queries: ``(N, 3)`` points in the target's frame (``vmap`` for batches of query
            sets; non-finite queries are invalid).
        max_distance: ``()`` acceptance radius, default ``grid.max_distance``; clipped to it
            (exactness is guaranteed only up to ``grid.max_distance``). May be traced, e.g.
            a shrinking ICP schedule.

    Returns:
        ``indices (N,)`` into the target rows (sentinel ``grid.num_points`` when invalid),
        ``sq_dists (N,)`` squared distances (``inf`` when invalid) and ``valid (N,)``: a
        target point lies within ``max_distance``. Exact for valid queries (ties broken
        arbitrarily) unless ``grid.overflow``.
    """
    queries = _check_queries(queries)
    leaf, inside = _leaf(grid, queries)
    d2 = _candidate_sq_dists(grid, queries, leaf)
    best, slot = _nearest_slot(d2)
    valid = inside & (best <= _radius2(grid, max_distance, best.dtype))
    index = jnp.where(valid, grid.candidate_index[leaf, slot], grid.num_points)
    out_dtype = jnp.result_type(queries.dtype, grid.candidate_points.dtype)
    sq = jnp.where(valid, best, jnp.inf).astype(out_dtype)
    return index, sq, valid


def query_knn(
    grid: NeighborGrid, queries: ArrayLike, k: int, max_distance: ArrayLike | None = None
) -> tuple[Int[Array, "N k"], Float[Array, "N k"], Bool[Array, "N k"]]:
    """The ``k`` nearest target points of each query within ``max_distance`` (jittable).

    Args:
        grid: from :func:`build_grid` with ``grid.k >= k`` (or ``k=None``).
        queries: ``(N, 3)`` points in the target's frame.
        k: static number of neighbours.
        max_distance: ``()`` acceptance radius, default and maximum ``grid.max_distance``.

    Returns:
        ``indices (N, k)``, ``sq_dists (N, k)`` sorted nearest first, and ``mask (N, k)``;
        neighbours beyond ``max_distance`` (or missing) are the sentinel ``grid.num_points``
        with ``inf`` distance. Exact within ``max_distance`` unless ``grid.overflow``.

    Raises:
        ValueError: ``k`` exceeds what the grid was built for.
    """
    queries = _check_queries(queries)
    if grid.k is not None and k > grid.k:
        raise ValueError(f"grid was built for k <= {grid.k}; rebuild with k={k} or more")
    leaf, inside = _leaf(grid, queries)
    d2 = _candidate_sq_dists(grid, queries, leaf)
    kk = min(k, grid.capacity)
    neg, slot = jax.lax.top_k(-d2, kk)
    best = -neg
    mask = inside[:, None] & (best <= _radius2(grid, max_distance, best.dtype))
    index = jnp.where(mask, grid.candidate_index[leaf[:, None], slot], grid.num_points)
    out_dtype = jnp.result_type(queries.dtype, grid.candidate_points.dtype)
    sq = jnp.where(mask, best, jnp.inf).astype(out_dtype)
    return _pad_slots(index, sq, mask, k, grid.num_points)


def query_radius(
    grid: NeighborGrid, queries: ArrayLike, capacity: int, radius: ArrayLike | None = None
) -> tuple[Int[Array, "N c"], Float[Array, "N c"], Bool[Array, "N c"], Bool[Array, " N"]]:
    """All target points within ``radius`` of each query, up to ``capacity`` (jittable).

    Args:
        grid: from :func:`build_grid` with ``k=None``.
        queries: ``(N, 3)`` points in the target's frame.
        capacity: static neighbour slots per query.
        radius: ``()`` search radius, default and maximum ``grid.max_distance``.

    Returns:
        ``indices (N, capacity)`` and ``sq_dists (N, capacity)`` sorted nearest first,
        ``mask (N, capacity)``, and ``overflow (N,)``: more than ``capacity`` points lie
        within ``radius`` (the nearest ``capacity`` are kept). Padding is the sentinel
        ``grid.num_points`` with ``inf`` distance.

    Raises:
        ValueError: the grid was built with ``k`` set (its lists are pruned).
    """
    queries = _check_queries(queries)
    if grid.k is not None:
        raise ValueError("query_radius needs a grid built with k=None (unpruned lists)")
    leaf, inside = _leaf(grid, queries)
    d2 = _candidate_sq_dists(grid, queries, leaf)
    within = inside[:, None] & (d2 <= _radius2(grid, radius, d2.dtype))
    count = within.sum(-1)
    kk = min(capacity, grid.capacity)
    neg, slot = jax.lax.top_k(jnp.where(within, -d2, -jnp.inf), kk)
    mask = jnp.isfinite(neg)
    index = jnp.where(mask, grid.candidate_index[leaf[:, None], slot], grid.num_points)
    out_dtype = jnp.result_type(queries.dtype, grid.candidate_points.dtype)
    sq = jnp.where(mask, -neg, jnp.inf).astype(out_dtype)
    return *_pad_slots(index, sq, mask, capacity, grid.num_points), count > capacity


# --------------------------------------------------------------------------------------------
# Blocked brute force (jittable with the target traced; the reference).


def valid_rows(points: Array, mask: ArrayLike | None) -> Bool[Array, " M"]:
    """``(M,)`` rows of ``points (M, 3)`` that are finite and, when given, set in ``mask``.

    Raises:
        ValueError: ``mask`` is not ``(M,)``.
    """
    ok = jnp.all(jnp.isfinite(points), axis=-1)
    if mask is None:
        return ok
    mask = jnp.asarray(mask)
    if mask.shape != ok.shape:
        raise ValueError(f"mask must be ({ok.shape[0]},), got {mask.shape}")
    return ok & mask


def _brute_setup(queries, points, mask, block):
    queries = _check_queries(queries)
    points = jnp.asarray(points)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must be (M, 3), got {points.shape}")
    m = points.shape[0]
    dtype = jnp.result_type(queries.dtype, points.dtype)
    ok = valid_rows(points, mask)
    # Centre at the valid points' mean: the screening product then loses little to rounding.
    count = ok.sum()
    centre = jnp.where(ok[:, None], points, 0).sum(0) / jnp.maximum(count, 1)
    p = jnp.where(ok[:, None], points - centre, 0).astype(dtype)
    q = (queries - centre).astype(dtype)
    q_ok = jnp.all(jnp.isfinite(q), axis=-1)
    q = jnp.where(q_ok[:, None], q, 0)
    n = q.shape[0]
    if block is None:
        block = max(1, min(n, (1 << 22) // max(m, 1)))
    n_blocks = -(-n // block)
    qb = jnp.pad(q, ((0, n_blocks * block - n), (0, 0))).reshape(n_blocks, block, 3)
    return q, p, ok, q_ok, qb, n


def _screen(qb, p, ok):
    """``(block, M)`` squared distances by one matrix product, ``inf`` at invalid points."""
    pn = jnp.where(ok, (p * p).sum(-1), jnp.inf)
    return (qb * qb).sum(-1, keepdims=True) - 2 * qb @ p.T + pn


def _exact(q, p, ok, idx):
    """Exact squared distances ``(N, K)`` from queries to the chosen points (inf if invalid)."""
    d = q[:, None, :] - p[idx]
    return jnp.where(ok[idx], (d * d).sum(-1), jnp.inf)


def knn(
    queries: ArrayLike,
    points: ArrayLike,
    k: int,
    *,
    max_distance: ArrayLike | None = None,
    mask: ArrayLike | None = None,
    block: int | None = None,
) -> tuple[Int[Array, "N k"], Float[Array, "N k"], Bool[Array, "N k"]]:
    """The ``k`` nearest points of each query by blocked brute force (exact, jittable).

    Args:
        queries: ``(N, 3)``; non-finite rows get no neighbours.
        points: ``(M, 3)`` in the same frame; may be traced.
        k: static number of neighbours (the query itself counts when it is a point).
        max_distance: optional ``()`` radius: neighbours beyond it are masked out.
        mask: ``(M,)`` optional validity of ``points``; non-finite points are invalid too.
        block: static queries per block; ``block * M`` distances are held at once
            (default: about 4M, 16 MB in float32).

    Returns:
        ``indices (N, k)``, ``sq_dists (N, k)`` nearest first, ``mask (N, k)``. Missing
        neighbours (fewer than ``k`` valid points, beyond ``max_distance``) have the sentinel
        index ``M`` and ``inf`` distance. Distances are exact; candidates are screened with a
        matrix product, so neighbours whose distances tie to ~1e-4 relative (float32) may
        come in either order.
    """
    q, p, ok, q_ok, qb, n = _brute_setup(queries, points, mask, block)
    m = p.shape[0]
    kk = min(k, m)

    def one(qblock):
        d2 = _screen(qblock, p, ok)
        if kk == 1:
            return jnp.argmin(d2, axis=-1)[:, None].astype(jnp.int32)
        return jax.lax.top_k(-d2, kk)[1].astype(jnp.int32)

    if kk == 0:
        idx = jnp.zeros((n, 0), jnp.int32)
    else:
        idx = jax.lax.map(one, qb).reshape(-1, kk)[:n]
    d2 = _exact(q, p, ok, idx)
    neg, order = jax.lax.top_k(-d2, kk) if kk > 1 else (-d2, jnp.zeros_like(idx))
    idx = jnp.take_along_axis(idx, order, axis=1)
    d2 = -neg
    valid = q_ok[:, None] & jnp.isfinite(d2)
    if max_distance is not None:
        valid = valid & (d2 <= jnp.square(jnp.asarray(max_distance, d2.dtype)))
    idx = jnp.where(valid, idx, m)
    d2 = jnp.where(valid, d2, jnp.inf)
    return _pad_slots(idx, d2, valid, k, m)


def radius_search(
    queries: ArrayLike,
    points: ArrayLike,
    radius: ArrayLike,
    capacity: int,
    *,
    mask: ArrayLike | None = None,
    block: int | None = None,
) -> tuple[Int[Array, "N c"], Float[Array, "N c"], Bool[Array, "N c"], Bool[Array, " N"]]:
    """All points within ``radius`` of each query, up to ``capacity`` (brute force, jittable).

    Args:
        queries: ``(N, 3)``; non-finite rows get no neighbours.
        points: ``(M, 3)`` in the same frame; may be traced.
        radius: ``()`` search radius (may be traced).
        capacity: static neighbour slots per query.
        mask: ``(M,)`` optional validity of ``points``.
        block: static queries per block (see :func:`knn`).

    Returns:
        ``indices (N, capacity)`` and ``sq_dists (N, capacity)`` nearest first,
        ``mask (N, capacity)``, and ``overflow (N,)``: more than ``capacity`` points lie
        within ``radius`` (the nearest ``capacity`` are kept). Padding is the sentinel ``M``
        with ``inf`` distance.
    """
    q, p, ok, q_ok, qb, n = _brute_setup(queries, points, mask, block)
    m = p.shape[0]
    kk = min(capacity, m)
    r2 = jnp.square(jnp.asarray(radius, p.dtype))

    def one(qblock):
        d2 = _screen(qblock, p, ok)
        within = d2 <= r2
        idx = jax.lax.top_k(jnp.where(within, -d2, -jnp.inf), kk)[1].astype(jnp.int32)
        return idx, within.sum(-1)

    idx, count = jax.lax.map(one, qb)
    idx, count = idx.reshape(-1, kk)[:n], count.reshape(-1)[:n]
    d2 = _exact(q, p, ok, idx)
    neg, order = jax.lax.top_k(-d2, kk)
    idx = jnp.take_along_axis(idx, order, axis=1)
    d2 = -neg
    valid = q_ok[:, None] & (d2 <= r2)
    idx = jnp.where(valid, idx, m)
    d2 = jnp.where(valid, d2, jnp.inf)
    return *_pad_slots(idx, d2, valid, capacity, m), q_ok & (count > capacity)


# --------------------------------------------------------------------------------------------
# Host helpers.


def voxel_downsample(points: ArrayLike, voxel_size: float) -> np.ndarray:
    """Centroid of the points in each occupied voxel, like Open3D's ``voxel_down_sample``.

    Host-side numpy (the output size depends on the data). Voxels are aligned, as in Open3D,
    so that the cloud's minimum lies half a voxel inside the first one; non-finite rows are
    dropped. Output rows are ordered by voxel (x-major), not as Open3D orders them.

    Args:
        points: ``(N, 3)``.
        voxel_size: voxel edge (> 0), in the points' units.

    Returns:
        ``(K, 3)`` centroids, in the input's float dtype.

    Raises:
        ValueError: bad shape or a non-positive voxel size.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got shape {pts.shape}")
    if not (math.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"voxel_size must be positive, got {voxel_size}")
    dtype = pts.dtype if np.issubdtype(pts.dtype, np.floating) else np.float64
    pts = pts[np.all(np.isfinite(pts), axis=1)].astype(np.float64)
    if len(pts) == 0:
        return np.zeros((0, 3), dtype)
    origin = pts.min(0) - 0.5 * voxel_size
    key = np.floor((pts - origin) / voxel_size).astype(np.int64)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, pts)
    return (sums / counts[:, None]).astype(dtype)
