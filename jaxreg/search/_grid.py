"""The neighbour grid: its structure, its host-side build and the check of a prebuilt grid.

:class:`NeighborGrid` is a target cloud indexed once on the host (:func:`build_grid`, which
plans an octree over a uniform grid and fills its candidate lists with the compiled loops of
:mod:`jaxreg.search._octree`) and then passed into ``jit`` / ``vmap`` as a pytree; the jittable
queries and the contract they keep are in :mod:`jaxreg.search.neighbors`, which re-exports these
names. :func:`validate_grid` is for callers that accept a grid built elsewhere: a grid's
indices refer to the target it was built on, and it is exact only within its radius and
without overflow.
"""

from __future__ import annotations

import functools
import itertools
import math

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.core._sizes import power_of_two
from jaxreg.core._threads import in_pieces, num_pieces
from jaxreg.search import _knn, _octree

__all__ = ["NeighborGrid", "build_grid", "pad_grid", "validate_grid"]

# Octant order of a node's children: bit 2 = x, bit 1 = y, bit 0 = z (as in _octree).
_OCTANTS = np.array(list(itertools.product((0, 1), repeat=3)), dtype=np.int64)


class NeighborGrid(eqx.Module):
    """A target cloud indexed for static-shape neighbour queries (:mod:`jaxreg.search.neighbors`).

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
            every point within ``max_distance`` (radius queries need it:
            :func:`~jaxreg.search.neighbors.radius_search`).
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
# The candidate lists of every level come from compiled loops (:mod:`jaxreg.search._octree`), which
# also lay the leaves out as tables; numpy here plans the refinement. Every box is grown by
# ``margin`` before it is tested, so float32 rounding (of the stored coordinates, and of the
# query's choice of leaf) can only keep a candidate that exact arithmetic would drop, never
# drop one it would keep.

_NEAR = 9  # witnesses per target point (itself among them) pruning 1-NN candidate lists
# Default refinement target of 1-NN leaves. Measured on milk.pcd (bench_neighbors.py): 48
# builds 1.3-1.6x faster than 32 for 40 queries costing 1.1-1.2x more.
_LEAF_TARGET = 48
# Candidate tests (node, point) per piece of a threaded level: ~0.5 ms of work.
_GRAIN = 30_000


def _table_rows(n: int) -> int:
    """Table length for ``n`` rows: the next power of two (at least 64), so that similar
    targets give identically shaped grids and a jitted caller does not recompile."""
    return power_of_two(n, 64)


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


def _top_piece(x, order, start, node_top, dims, h, tests, a, b):
    """Top-level nodes ``a:b`` of :func:`jaxreg.search._octree.stencil_cells`' list."""
    return _octree.top_level_nodes(x, order, start, node_top[a:b], dims, h, *tests)


def _split_piece(x, corner, counts, pid, split, edge, tests, a, b):
    """The children of the nodes ``a:b`` that ``split`` marks."""
    mine = np.zeros_like(split)
    mine[a:b] = split[a:b]
    return _octree.split_nodes(x, corner, counts, pid, mine, edge, *tests)


def _in_pieces(fill, work):
    """The candidate lists of a level's nodes, filled in pieces of consecutive nodes of about
    equal ``work (L,)`` (on one thread per core: :func:`jaxreg.core._threads.in_pieces`): ``fill(a,
    b)`` returns ``(counts, pid)`` of nodes ``a:b``, concatenated here in node order."""
    cumulative = np.cumsum(work)
    pieces = num_pieces(int(cumulative[-1]) if len(work) else 0, _GRAIN)
    cuts = np.searchsorted(cumulative, cumulative[-1] * np.arange(1, pieces) / pieces)
    bounds = np.unique(np.concatenate(([0], cuts, [len(work)])))
    parts = in_pieces(fill, zip(bounds[:-1], bounds[1:], strict=True))
    if len(parts) == 1:
        return parts[0]
    return tuple(np.concatenate(p) for p in zip(*parts, strict=True))


def _levels(x, cell, dims, h, margin, r2, k, *budget):
    """Every node of every refinement level with its candidates (see :mod:`jaxreg.search._octree`).

    ``x`` is float64 relative to the grid origin, ``cell`` its top-level cells. Returns
    ``(nodes, counts, leaf, pid, cell_depth)``: ``nodes (L, 5)`` the top-level cell,
    sub-cell coordinates and level of each node, level by level; ``counts (L,)`` its
    candidates, ``pid`` in node order; ``leaf (L,)`` it is not split; ``cell_depth`` each
    top-level cell's refinement depth.
    """
    if k == 1:
        half_spaces = _octree.witnesses(x, _knn.self_knn(x, _NEAR)[0], margin)
    else:
        half_spaces = _octree.no_witnesses(len(x))
    tests = (margin, r2, *half_spaces, k or 0)
    order, start, node_top = _octree.stencil_cells(cell, np.asarray(dims))
    args = (x, order, start, node_top, np.asarray(dims), h, tests)
    # A node's tests are about 27 x / (nodes) on average.
    work = np.full(len(node_top), 27 * len(x) / len(node_top))
    counts, pid = _in_pieces(functools.partial(_top_piece, *args), work)
    node_sub = np.zeros((len(node_top), 3), np.int64)
    cell_depth = np.zeros(math.prod(dims), np.int32)
    parts = []
    map_size = len(node_top)
    level = 0
    while True:
        plan = _split_plan(node_top, counts, level, map_size, *budget)
        split = np.zeros(len(counts), bool) if plan is None else plan[0]
        nodes = np.column_stack([node_top, node_sub, np.full(len(counts), level)])
        parts.append((nodes, counts, ~split, pid))
        if plan is None:
            nodes, counts, leaf, pid = (np.concatenate(p) for p in zip(*parts, strict=True))
            return nodes, counts, leaf, pid, cell_depth
        _, deeper, grow = plan
        map_size += grow
        cell_depth[deeper] = level + 1
        corner = np.stack(np.unravel_index(node_top, dims), axis=1) * 2**level + node_sub
        level += 1
        args = (x, corner, counts, pid, split, h / 2**level, tests)
        counts, pid = _in_pieces(functools.partial(_split_piece, *args), np.where(split, counts, 0))
        node_top = np.repeat(node_top[split], 8)
        node_sub = (2 * node_sub[split][:, None, :] + _OCTANTS[None]).reshape(-1, 3)


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

    Runs on the host in compiled loops (``target`` must be concrete, not a tracer); the
    result is a pytree to pass into jitted code. Build once per target, query many times.

    Args:
        target: ``(M, 3)`` target points. Rows that are not finite, or where ``mask`` is
            False, are never returned; indices refer to rows of ``target``.
        max_distance: radius within which queries are exact (ICP: the largest
            ``max_correspondence_distance`` of its schedule). Larger radii cost build time
            and memory, not query time.
        k: the largest ``k`` that :func:`~jaxreg.search.neighbors.knn` will ask for (1 for
            ICP, the default); ``None`` keeps every point within ``max_distance`` of a leaf, as
            :func:`~jaxreg.search.neighbors.radius_search` needs.
        capacity: candidate slots per leaf. ``None``: refine leaves to at most 48
            candidates for ``k == 1`` (``max(32, 2 k)`` otherwise) and size the capacity on
            the host (the longest list rounded up to a multiple of 16) so nothing is
            dropped. An explicit value is also the refinement target and a hard cap:
            leaves still above it at the maximum depth are truncated (keeping the
            candidates nearest the leaf's centre) and ``overflow`` is set. Query time
            grows with the capacity, build time falls.
        max_depth: levels of octree refinement below the top-level cells; default 6 for
            ``k == 1`` and 0 otherwise (kNN and radius lists shrink little when refined:
            on milk.pcd one level costs 3-5x the build time and memory for 10-30% faster
            queries).
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
    x = points - lo
    cell = np.minimum(np.floor(x / h), np.array(dims) - 1).astype(np.int64)
    budget = (leaf_target, max_depth, max_map, max_pairs)
    if len(points):
        nodes, counts, leaf, pid, cell_depth = _levels(
            x, cell, dims, h, margin, (r + margin) ** 2, k, *budget
        )
    else:
        nodes, counts, leaf = np.zeros((0, 5), np.int64), np.zeros(0, np.int64), np.zeros(0, bool)
        pid, cell_depth = np.zeros(0, np.int64), np.zeros(math.prod(dims), np.int32)
    leaf_counts = counts[leaf]
    needed = int(leaf_counts.max()) if len(leaf_counts) else 0
    cap = capacity if capacity is not None else max(16, -(-needed // 16) * 16)
    overflow = needed > cap
    # Padded sizes. The candidate table to a bucketed row count; the cell table to the cells
    # of the cube around the bounding sphere (any rotation of the target fits in it); the
    # map to 8 entries per table row unless it needs more (it depends on how many cells
    # refine one level deeper, a threshold effect).
    n_table = _table_rows(1 + np.count_nonzero(leaf_counts))
    cells, leaf_map, cand_index, cand_points = _octree.leaf_tables(
        nodes,
        counts,
        leaf,
        pid,
        cell_depth,
        np.asarray(dims, np.int64),
        h,
        x,
        points.astype(dtype),
        rows,
        (n_table, cap, num_points, overflow),
    )
    if len(points):
        radius = float(np.sqrt(((points - points.mean(0)) ** 2).sum(1).max()))
        sphere = min(math.ceil((2 * (radius + r + margin)) / h + 1) ** 3, max_cells)
    else:
        sphere = 1
    cells = np.pad(cells, ((0, _table_rows(max(len(cells), sphere)) - len(cells)), (0, 0)))
    leaf_map = np.pad(leaf_map, (0, max(_table_rows(len(leaf_map)), 8 * n_table) - len(leaf_map)))
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


def pad_grid(
    grid: NeighborGrid, *, cells: int = 0, entries: int = 0, leaves: int = 0, capacity: int = 0
) -> NeighborGrid:
    """``grid`` with its tables padded to at least the given sizes (host): ``cells`` rows of
    the cell table, ``entries`` of the leaf map, ``leaves`` rows and ``capacity`` columns of
    the candidate table. The padding is what :func:`build_grid` pads with (cell and map rows
    of zeros, candidate slots holding the sentinel ``num_points`` at ``inf``), so every query
    answers exactly as before; grids of different targets padded to the same sizes share
    their shapes, and a jitted function taking them compiles once.
    """
    if isinstance(grid.candidate_index, jax.core.Tracer):
        raise ValueError("pad_grid runs on the host: pad the grid outside jit, pass it in")
    index = np.asarray(grid.candidate_index)
    coords = np.asarray(grid.candidate_points)
    more_rows = max(0, leaves - index.shape[0])
    more_slots = max(0, capacity - index.shape[1])
    sentinel = int(grid.num_points)
    padded = (
        np.pad(np.asarray(grid.cells), ((0, max(0, cells - grid.cells.shape[0])), (0, 0))),
        np.pad(np.asarray(grid.leaf_map), (0, max(0, entries - grid.leaf_map.shape[0]))),
        np.pad(index, ((0, more_rows), (0, more_slots)), constant_values=sentinel),
        np.pad(coords, ((0, 0), (0, more_rows), (0, more_slots)), constant_values=np.inf),
    )
    return eqx.tree_at(
        lambda g: (g.cells, g.leaf_map, g.candidate_index, g.candidate_points),
        grid,
        jax.device_put(padded),
    )


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
