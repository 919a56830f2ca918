"""Compiled host loops (numba) that build :class:`jaxreg.search.neighbors.NeighborGrid`'s octree.

The grid's octree is built here for every kind of grid (1-NN, kNN, radius): the loops run
over target points and octree nodes, and need no ``(pairs, 27)`` temporaries, so a build
costs a few milliseconds per thousand points. They are compiled on the first build on a
machine and cached on disk (``__pycache__``).

Coordinates are float64 relative to the grid origin; a node at refinement ``level`` of
top-level cell ``c`` with sub-cell ``s`` is the box ``[(c 2^level + s) e, (c 2^level + s + 1) e]``
with ``e = h / 2^level``, grown by ``margin`` on every side before any test (so that float32
rounding of the query's choice of leaf never drops a candidate).

A target point ``p`` is a candidate of a node unless

* it is farther than ``max_distance`` (``r2`` squared, margin included) from the grown box, or
* (1-NN grids) one of its witnesses ``q`` (its nearest points,
  :func:`jaxreg.search._knn.self_knn`) is strictly closer than ``p`` to every point of the grown
  box: the box lies beyond the bisecting plane of ``p`` and ``q``, so no query in it has
  ``p`` as its nearest; or
* (kNN grids, ``k > 1``) it is farther from the grown box than the ``k``-th smallest
  farthest-corner distance of the node's candidates: ``k`` points are then closer than ``p``
  to every query in the box.

Each test can only keep a point that exact reasoning would drop, never the reverse, so every
true neighbour within ``max_distance`` of a query is among its leaf's candidates. Radius
grids (``k=None``) apply the first test alone.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "counting_sort",
    "kth_smallest",
    "leaf_tables",
    "no_witnesses",
    "split_nodes",
    "stencil_cells",
    "top_level_nodes",
    "witnesses",
]

_CACHE = dict(cache=True, nogil=True)


@numba.njit(**_CACHE)
def counting_sort(key: np.ndarray, num_keys: int):
    """Points grouped by integer ``key < num_keys``: the order that sorts them (stable) and
    ``start (num_keys + 1,)``, so that key ``k``'s points are ``order[start[k]:start[k + 1]]``.
    Also compiled into :mod:`jaxreg.search._knn`'s cached pass, whose cache a change here does not
    invalidate."""
    start = np.zeros(num_keys + 1, np.int64)
    for k in key:
        start[k + 1] += 1
    for k in range(num_keys):
        start[k + 1] += start[k]
    cursor = start[:-1].copy()
    order = np.empty(key.size, np.int64)
    for p in range(key.size):
        order[cursor[key[p]]] = p
        cursor[key[p]] += 1
    return order, start


@numba.njit
def kth_smallest(a: np.ndarray, kth: int) -> float:
    """The ``kth`` smallest (from 0) of the non-NaN values ``a``: ``np.partition(a, kth)[kth]``
    by a quickselect that reorders ``a``, compiled in a fraction of the time numba takes for
    ``np.partition``. Also compiled into :mod:`jaxreg.search._knn`'s cached pass."""
    lo, hi = 0, a.size - 1
    while lo < hi:
        pivot = a[(lo + hi) >> 1]
        i, j = lo, hi
        while i <= j:  # [lo, j] <= pivot <= [i, hi]; between them, the pivot's equals
            while a[i] < pivot:
                i += 1
            while a[j] > pivot:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if kth <= j:
            hi = j
        elif kth >= i:
            lo = i
        else:
            break
    return a[kth]


@numba.njit(**_CACHE)
def witnesses(x: np.ndarray, near: np.ndarray, margin: float):
    """Bisector half-spaces of each point against its witnesses ``near (n, K)``.

    The box ``[lo, lo + e]^3`` grown by ``margin`` lies strictly beyond the bisector of ``p``
    and its witness ``q`` (``d = q - p``, ``mid = (p + q) / 2``) when its minimum of
    ``x . d``, ``lo . d + e neg - margin |d|_1`` with ``neg = sum_i min(d_i, 0)``, exceeds
    ``mid . d``. Returns ``d`` as ``(n, 3, K)`` (witnesses last, for vectorised tests),
    ``neg (n, K)`` and ``level = mid . d + margin |d|_1`` ``(n, K)``.
    """
    n, count = near.shape
    wd = np.empty((n, 3, count))
    neg = np.zeros((n, count))
    level = np.zeros((n, count))
    for p in range(n):
        for j in range(count):
            q = near[p, j] if near[p, j] < n else p  # itself: a witness that never prunes
            for i in range(3):
                d = x[q, i] - x[p, i]
                wd[p, i, j] = d
                neg[p, j] += min(d, 0.0)
                level[p, j] += 0.5 * (x[q, i] * x[q, i] - x[p, i] * x[p, i]) + margin * abs(d)
    return wd, neg, level


def no_witnesses(n: int):
    """Witness arrays with no witnesses (kNN and radius grids): nothing is pruned by them."""
    return np.zeros((n, 3, 0)), np.zeros((n, 0)), np.zeros((n, 0))


@numba.njit(inline="always")
def _within(x, p, lx, ly, lz, edge, margin, r2) -> bool:
    """Point ``p`` lies within ``sqrt(r2)`` of the box ``[l, l + edge]^3`` grown by ``margin``."""
    gx = max(lx - margin - x[p, 0], x[p, 0] - (lx + edge + margin), 0.0)
    gy = max(ly - margin - x[p, 1], x[p, 1] - (ly + edge + margin), 0.0)
    gz = max(lz - margin - x[p, 2], x[p, 2] - (lz + edge + margin), 0.0)
    return gx * gx + gy * gy + gz * gz <= r2


@numba.njit(inline="always")
def _beyond(p, lx, ly, lz, edge, wd, neg, level) -> bool:
    """Some witness of ``p`` is strictly closer than ``p`` to all of the grown box (see
    :func:`witnesses`; never with no witnesses); no branch inside the loop, so it
    vectorises over witnesses."""
    worst = -np.inf
    for j in range(neg.shape[1]):
        v = lx * wd[p, 0, j] + ly * wd[p, 1, j] + lz * wd[p, 2, j] + edge * neg[p, j]
        worst = max(worst, v - level[p, j])
    return worst > 0.0


@numba.njit(inline="always")
def _keeps(x, p, lx, ly, lz, edge, margin, r2, wd, neg, level) -> bool:
    """Point ``p`` stays a candidate of the box ``[l, l + edge]^3`` (module docstring)."""
    return _within(x, p, lx, ly, lz, edge, margin, r2) and not _beyond(
        p, lx, ly, lz, edge, wd, neg, level
    )


@numba.njit(inline="always")
def _prune_kth(x, out, first, last, lx, ly, lz, edge, margin, k, far):
    """Drops from ``out[first:last]`` (one node's candidates) every point farther from the
    grown box than the ``k``-th smallest farthest-corner distance among them, compacting in
    place; returns the new end. ``far`` is scratch of length ``>= last - first``."""
    count = last - first
    if k < 2 or count <= k:
        return last
    for j in range(count):
        p = out[first + j]
        fx = max(x[p, 0] - (lx - margin), lx + edge + margin - x[p, 0])
        fy = max(x[p, 1] - (ly - margin), ly + edge + margin - x[p, 1])
        fz = max(x[p, 2] - (lz - margin), lz + edge + margin - x[p, 2])
        far[j] = fx * fx + fy * fy + fz * fz
    bound = kth_smallest(far[:count], k - 1)
    end = first
    for j in range(count):
        p = out[first + j]
        if _within(x, p, lx, ly, lz, edge, margin, bound):
            out[end] = p
            end += 1
    return end


@numba.njit(**_CACHE)
def stencil_cells(cell, dims):
    """The top-level cells within the 27-cell stencil of an occupied one, and the points
    grouped by cell: ``(order, start, node_top)`` (:func:`counting_sort` of the cells'
    linear ids, x-major; ``node_top (L,)`` ascending), for :func:`top_level_nodes`."""
    d1, d2 = dims[1], dims[2]
    lin = (cell[:, 0] * d1 + cell[:, 1]) * d2 + cell[:, 2]
    order, start = counting_sort(lin, dims[0] * d1 * d2)
    near = np.zeros(dims[0] * d1 * d2, np.bool_)
    for c in range(dims[0] * d1 * d2):
        if start[c + 1] > start[c]:
            cx, cy, cz = c // (d1 * d2), (c // d2) % d1, c % d2
            for ax in range(max(cx - 1, 0), min(cx + 2, dims[0])):
                for ay in range(max(cy - 1, 0), min(cy + 2, d1)):
                    row = (ax * d1 + ay) * d2
                    near[row + max(cz - 1, 0) : row + min(cz + 2, d2)] = True
    return order, start, np.flatnonzero(near)


@numba.njit(**_CACHE)
def top_level_nodes(x, order, start, node_top, dims, h, margin, r2, wd, neg, level, k):
    """Candidates of the top-level cells ``node_top`` (some of :func:`stencil_cells`).

    Args:
        x: ``(n, 3)`` points relative to the grid origin; order, start: from
            :func:`stencil_cells`; node_top: ``(L,)`` linear cell ids; dims: ``(3,)``
            cells per axis; h: cell edge; wd, neg, level: :func:`witnesses` (or
            :func:`no_witnesses`); k: the kNN pruning's ``k`` (0 or 1: none).

    Returns:
        ``counts (L,)`` and ``pid``: the candidates of node ``i`` are
        ``pid[starts[i] : starts[i] + counts[i]]`` with ``starts`` the exclusive cumulative
        sum of ``counts``.
    """
    d1, d2 = dims[1], dims[2]
    counts = np.zeros(node_top.size, np.int64)
    pid = np.empty(27 * x.shape[0], np.int64)  # a point lies in at most 27 stencils
    far = np.empty(x.shape[0])
    total = 0
    for i in range(node_top.size):
        c = node_top[i]
        cx, cy, cz = c // (d1 * d2), (c // d2) % d1, c % d2
        lx, ly, lz = cx * h, cy * h, cz * h
        before = total
        for ax in range(max(cx - 1, 0), min(cx + 2, dims[0])):
            for ay in range(max(cy - 1, 0), min(cy + 2, d1)):
                # The cells along z are consecutive keys: one sorted run.
                k = (ax * d1 + ay) * d2
                for j in range(start[k + max(cz - 1, 0)], start[k + min(cz + 2, d2)]):
                    p = order[j]
                    if _keeps(x, p, lx, ly, lz, h, margin, r2, wd, neg, level):
                        pid[total] = p
                        total += 1
        total = _prune_kth(x, pid, before, total, lx, ly, lz, h, margin, k, far)
        counts[i] = total - before
    return counts, pid[:total]


@numba.njit(inline="always")
def _child_gaps(c, lo0, lo1, edge, margin):
    """Squared gaps from coordinate ``c`` to the grown intervals ``[lo0, lo0 + edge]`` and
    ``[lo1, lo1 + edge]`` of the two children along one axis (as in :func:`_within`)."""
    g0 = max(lo0 - margin - c, c - (lo0 + edge + margin), 0.0)
    g1 = max(lo1 - margin - c, c - (lo1 + edge + margin), 0.0)
    return g0 * g0, g1 * g1


@numba.njit(inline="always")
def _child_witness_max(p, lx0, lx1, ly0, ly1, lz0, lz1, edge, wd, neg, level):
    """:func:`_beyond`'s largest witness margin for the 8 children of a node (octant order),
    whose lower corners take ``lx0`` or ``lx1`` along x (and so on): per witness 6 products
    and 8 sums, the same operations in the same order as 8 separate calls."""
    w0 = w1 = w2 = w3 = w4 = w5 = w6 = w7 = -np.inf
    for t in range(neg.shape[1]):
        ax0, ax1 = lx0 * wd[p, 0, t], lx1 * wd[p, 0, t]
        ay0, ay1 = ly0 * wd[p, 1, t], ly1 * wd[p, 1, t]
        az0, az1 = lz0 * wd[p, 2, t], lz1 * wd[p, 2, t]
        shift, lev = edge * neg[p, t], level[p, t]
        v00, v01, v10, v11 = ax0 + ay0, ax0 + ay1, ax1 + ay0, ax1 + ay1
        w0 = max(w0, v00 + az0 + shift - lev)
        w1 = max(w1, v00 + az1 + shift - lev)
        w2 = max(w2, v01 + az0 + shift - lev)
        w3 = max(w3, v01 + az1 + shift - lev)
        w4 = max(w4, v10 + az0 + shift - lev)
        w5 = max(w5, v10 + az1 + shift - lev)
        w6 = max(w6, v11 + az0 + shift - lev)
        w7 = max(w7, v11 + az1 + shift - lev)
    return w0, w1, w2, w3, w4, w5, w6, w7


@numba.njit(**_CACHE)
def split_nodes(x, corner, counts, pid, split, edge, margin, r2, wd, neg, level, k):
    """Candidates of the 8 children of every node with ``split`` set.

    Each parent candidate is tested against all 8 children at once: the tests of
    :func:`_keeps` are sums of per-axis terms, and a child's terms are one of two values
    per axis, so a witness costs 6 products and 8 sums instead of 8 full tests (the same
    floating-point operations in the same order: the lists are those of child-by-child
    tests).

    Args:
        corner: ``(L, 3)`` integer box corner of each node in units of its own edge
            (``2 edge``); counts, pid: the nodes' candidates as from
            :func:`top_level_nodes`; split: ``(L,)``; edge: the children's edge; the rest
            as for :func:`top_level_nodes`.

    Returns:
        ``counts (8 S,)`` and ``pid`` of the children, ordered by split parent, then octant
        (bit 2 = x, bit 1 = y, bit 0 = z).
    """
    starts = np.cumsum(counts) - counts
    parents = np.flatnonzero(split)
    out_counts = np.zeros(8 * parents.size, np.int64)
    out = np.empty(8 * counts[parents].sum(), np.int64)
    widest = counts.max() if counts.size else 0
    far = np.empty(widest)
    child = np.empty((8, widest), np.int64)
    filled = np.zeros(8, np.int64)
    keep = np.empty(8, np.bool_)
    total = 0
    for rank in range(parents.size):
        a = parents[rank]
        lx0, ly0, lz0 = 2 * corner[a, 0] * edge, 2 * corner[a, 1] * edge, 2 * corner[a, 2] * edge
        lx1 = (2 * corner[a, 0] + 1) * edge
        ly1 = (2 * corner[a, 1] + 1) * edge
        lz1 = (2 * corner[a, 2] + 1) * edge
        filled[:] = 0
        for j in range(starts[a], starts[a] + counts[a]):
            p = pid[j]
            gx0, gx1 = _child_gaps(x[p, 0], lx0, lx1, edge, margin)
            gy0, gy1 = _child_gaps(x[p, 1], ly0, ly1, edge, margin)
            gz0, gz1 = _child_gaps(x[p, 2], lz0, lz1, edge, margin)
            w = _child_witness_max(p, lx0, lx1, ly0, ly1, lz0, lz1, edge, wd, neg, level)
            keep[0] = (gx0 + gy0 + gz0 <= r2) & (w[0] <= 0.0)
            keep[1] = (gx0 + gy0 + gz1 <= r2) & (w[1] <= 0.0)
            keep[2] = (gx0 + gy1 + gz0 <= r2) & (w[2] <= 0.0)
            keep[3] = (gx0 + gy1 + gz1 <= r2) & (w[3] <= 0.0)
            keep[4] = (gx1 + gy0 + gz0 <= r2) & (w[4] <= 0.0)
            keep[5] = (gx1 + gy0 + gz1 <= r2) & (w[5] <= 0.0)
            keep[6] = (gx1 + gy1 + gz0 <= r2) & (w[6] <= 0.0)
            keep[7] = (gx1 + gy1 + gz1 <= r2) & (w[7] <= 0.0)
            for octant in range(8):
                child[octant, filled[octant]] = p
                filled[octant] += keep[octant]
        for octant in range(8):
            lx = lx1 if octant & 4 else lx0
            ly = ly1 if octant & 2 else ly0
            lz = lz1 if octant & 1 else lz0
            before = total
            out[total : total + filled[octant]] = child[octant, : filled[octant]]
            total += filled[octant]
            total = _prune_kth(x, out, before, total, lx, ly, lz, edge, margin, k, far)
            out_counts[8 * rank + octant] = total - before
    return out_counts, out[:total]


@numba.njit
def _stable_argsort(values):
    """``np.argsort(values, kind="stable")`` of non-NaN ``values``: a bottom-up merge sort
    (numba compiles it in a fraction of the time of its own ``argsort``)."""
    n = values.size
    idx = np.arange(n)
    tmp = np.empty(n, np.int64)
    width = 1
    while width < n:
        for lo in range(0, n, 2 * width):
            mid, hi = min(lo + width, n), min(lo + 2 * width, n)
            i, j = lo, mid
            for out in range(lo, hi):
                if i < mid and (j == hi or values[idx[i]] <= values[idx[j]]):
                    tmp[out] = idx[i]
                    i += 1
                else:
                    tmp[out] = idx[j]
                    j += 1
        idx, tmp = tmp, idx
        width *= 2
    return idx


@numba.njit(**_CACHE)
def leaf_tables(nodes, counts, leaf, pid, cell_depth, dims, h, x, points, target_rows, shape):
    """The grid's tables from the nodes of every refinement level (see ``NeighborGrid``).

    Args:
        nodes: ``(L, 5)`` every node of every level, level by level: top-level cell
            (linear, x-major), sub-cell coordinates and level; counts: ``(L,)`` its
            candidates, which are ``pid`` in node order; leaf: ``(L,)`` it is not split.
        cell_depth: ``(prod(dims),)`` refinement depth of each top-level cell; h: its edge.
        x: ``(n, 3)`` float64 points relative to the grid origin; points: the same in the
            grid's dtype; target_rows: ``(n,)`` their target rows.
        shape: ``(num_rows, capacity, sentinel, truncate)``: table rows (at least 1 + the
            non-empty leaves), slots per row, the padding index, and whether some leaf has
            more than ``capacity`` candidates; then every leaf's candidates are ordered by
            distance to its centre (float32, as stored) and cut to ``capacity``.

    Returns:
        ``cells (prod(dims), 2)`` int32 block offset and depth, ``leaf_map`` int32 (entry 0
        and unused entries: row 0, the empty leaf), ``index (num_rows, capacity)`` int32
        and ``coords (3, num_rows, capacity)`` (``inf`` padding). Non-empty leaves take
        rows 1, 2, ... in node order.
    """
    num_rows, capacity, sentinel, truncate = shape
    d1, d2 = dims[1], dims[2]
    n_cells = dims[0] * d1 * d2
    used = np.zeros(n_cells, np.bool_)
    for i in range(nodes.shape[0]):
        if leaf[i] and counts[i] > 0:
            used[nodes[i, 0]] = True
    cells = np.zeros((n_cells, 2), np.int32)
    size = 1
    for c in range(n_cells):
        if used[c]:
            cells[c, 0] = size
            cells[c, 1] = cell_depth[c]
            size += 8 ** cell_depth[c]
    leaf_map = np.zeros(size, np.int32)
    index = np.full((num_rows, capacity), sentinel, np.int32)
    coords = np.full((3, num_rows, capacity), np.inf, points.dtype)
    dist = np.empty(counts.max() if counts.size else 0)
    row = 0
    first = 0
    for i in range(nodes.shape[0]):
        count = counts[i]
        first += count
        if not leaf[i] or count == 0:
            continue
        row += 1
        top, level = nodes[i, 0], nodes[i, 4]
        corner = ((top // (d1 * d2)), (top // d2) % d1, top % d2)
        order = np.arange(first - count, first)
        if truncate:  # keep the candidates nearest the leaf's centre
            edge = np.float32(h / 2**level)
            for j in range(count):
                total = 0.0
                for a in range(3):
                    centre = np.float32((corner[a] * 2**level + nodes[i, 1 + a] + 0.5) * edge)
                    total += (x[pid[order[j]], a] - centre) ** 2
                dist[j] = total
            order = order[_stable_argsort(dist[:count])]
        for slot in range(min(count, capacity)):
            q = pid[order[slot]]
            index[row, slot] = target_rows[q]
            for a in range(3):
                coords[a, row, slot] = points[q, a]
        # The leaf spans 2^extra sub-cells per axis of its top-level cell's block.
        depth = cells[top, 1]
        side = 1 << (depth - level)
        full = 1 << depth
        for u in range(nodes[i, 1] * side, (nodes[i, 1] + 1) * side):
            for v in range(nodes[i, 2] * side, (nodes[i, 2] + 1) * side):
                entry = cells[top, 0] + (u * full + v) * full + nodes[i, 3] * side
                leaf_map[entry : entry + side] = row
    return cells, leaf_map, index, coords
