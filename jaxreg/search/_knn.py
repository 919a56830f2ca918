"""Exact k nearest neighbours of every point of a cloud among its own points (host, numba).

:func:`self_knn` returns each point's ``k`` nearest points (itself included) as ``(n, k)``
index and squared-distance tables, nearest first; :func:`knn_moments` returns instead the
covariance of each neighbourhood, ``(n, 6)``, from the same search without building the
tables. Both take ``(n, 3)`` float64 coordinates and run one pass, :func:`_knn_pass`, over
cubic cells about one ``k``-th neighbour distance wide. The search is exact; among points
at equal distance the one scanned first is kept (block order, or ring order for the points
whose neighbours lie beyond their block: :func:`_knn_pass`), so results are reproducible
bit for bit. Uses: the witnesses of 1-NN grids (:mod:`jaxreg.search._grid`), normals on concrete
clouds (:mod:`jaxreg.search.normals`) and FPFH radius neighbourhoods
(:mod:`jaxreg.search.features`).

The loops are compiled on the first call on a machine and cached on disk (``__pycache__``).
numba checks only this file's timestamp for that cache: a change to the cell sort or the
selection imported from :mod:`jaxreg.search._octree` needs ``jaxreg/__pycache__/_knn.*`` deleted
to take effect. Large clouds are searched on one thread per core (:func:`_knn_pass`).
"""

from __future__ import annotations

import numba
import numpy as np

from jaxreg.core._threads import in_pieces, num_pieces
from jaxreg.search._octree import counting_sort, kth_smallest

__all__ = ["knn_moments", "self_knn"]

_CACHE = dict(cache=True, nogil=True)
# Neighbour slots (points x k) per piece of a threaded pass: ~1 ms of work.
_GRAIN = 16_000


def self_knn(x: np.ndarray, k: int, max_distance: float = np.inf):
    """Exact ``k`` nearest points of every point of ``x`` (itself included), nearest first,
    among those closer than ``max_distance`` (a hybrid search, as Open3D's and PCL's radius
    search with a neighbour cap; the default has no radius).

    ``x`` is ``(n, 3)`` float64 (C order). Returns ``indices (n, k)`` and squared distances
    ``(n, k)``; slots without a point (fewer than ``k`` points, or within ``max_distance``)
    hold the sentinel ``n`` and ``inf``. Ties are broken by scan order (:func:`_knn_pass`).
    """
    idx, sq, _, _ = _knn_pass(x, int(k), float(max_distance), False)
    return idx, sq


def knn_moments(x: np.ndarray, k: int):
    """Covariance of each point's exact ``k`` nearest (as :func:`self_knn` finds them, in its
    order) from the same pass, without the ``(n, k)`` index and distance tables:
    ``cov (n, 6)`` with entries ``xx, xy, xz, yy, yz, zz`` of
    ``sum_j (y_j - mean)(y_j - mean)^T / count``, ``y_j`` the neighbours relative to the
    point (no cancellation far from the origin), and ``count (n,)`` int32."""
    _, _, cov, count = _knn_pass(x, int(k), np.inf, True)
    return cov, count


def _knn_pass(x, k, max_distance, moments):
    """:func:`self_knn` (``moments`` false: ``idx``, ``sq``, empty ``cov``, ``count``) or
    :func:`knn_moments` (true: empty ``idx``, ``sq``, then ``cov``, ``count``).

    :func:`_hash` sorts the points into cells, then :func:`_search` answers runs of whole
    cells, on several threads for large clouds (:func:`jaxreg.core._threads.in_pieces`): every
    cell's answers depend on its block alone, so the split never changes a bit.
    """
    n = x.shape[0]
    rows = 0 if moments else n
    idx = np.empty((rows, k), np.int64)
    sq = np.empty((rows, k))
    cov = np.zeros((n - rows, 6))
    count = np.zeros(n - rows, np.int32)
    if n == 0:
        return idx, sq, cov, count
    cells = _hash(x, k, max_distance)
    order, start, key = cells[0], cells[1], cells[4]
    # Pieces end at the first position of the cell holding each n / pieces-th point.
    pieces = num_pieces(n * k, _GRAIN)
    cuts = (np.arange(1, pieces) * n) // pieces
    bounds = np.unique(np.concatenate(([0], start[key[order[cuts]]], [n])))
    r2 = max_distance * max_distance
    in_pieces(
        lambda a, b: _search(*cells, k, r2, moments, a, b, idx, sq, cov, count),
        zip(bounds[:-1], bounds[1:], strict=True),
    )
    return idx, sq, cov, count


@numba.njit(**_CACHE)
def _hash(x, k, max_distance):
    """Points hashed into cubic cells about as wide as a sampled median ``k``-th neighbour
    distance (at most ``max_distance``), in a bounded table. Returns the counting sort's
    ``order`` and ``start``, ``xs (3, n)`` the coordinates in cell order (position ``t`` is
    point ``order[t]``; one array per axis), each point's ``cell (n, 3)`` and linear ``key
    (n,)``, and the table's ``lo (3,)`` corner, cell ``size`` and ``span (3,)``."""
    n = x.shape[0]
    lo = np.empty(3)
    hi = np.empty(3)
    for i in range(3):
        lo[i] = x[:, i].min()
        hi[i] = x[:, i].max()
    extent = max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])
    size = max(min(_median_kth(x, k), max_distance), extent / (1 << 20), 1e-30)
    span = np.empty(3, np.int64)
    while True:  # a bounded table
        for i in range(3):
            span[i] = int((hi[i] - lo[i]) / size) + 1
        if span[0] * span[1] * span[2] <= 1 << 22:
            break
        size *= 1.25
    s1, s2 = span[1], span[2]
    cell = np.empty((n, 3), np.int64)
    key = np.empty(n, np.int64)
    for p in range(n):
        for i in range(3):
            cell[p, i] = min(int((x[p, i] - lo[i]) / size), span[i] - 1)
        key[p] = (cell[p, 0] * s1 + cell[p, 1]) * s2 + cell[p, 2]
    order, start = counting_sort(key, span[0] * s1 * s2)
    xs = np.empty((3, n))
    for t in range(n):
        for i in range(3):
            xs[i, t] = x[order[t], i]
    return order, start, xs, cell, key, lo, size, span


@numba.njit(**_CACHE)
def _search(
    order, start, xs, cell, key, lo, size, span, k, r2, moments, first, stop, idx, sq, cov, count
):
    """Answers the points at cell-order positions ``first:stop`` (whole cells) into the rows
    ``order[first:stop]`` of the outputs (see :func:`_knn_pass`); ``r2`` is the squared
    ``max_distance``.

    A 3x3x3 block of cells is 9 contiguous runs of ``xs``. The points of a cell share the
    candidates of their block, copied once into a contiguous buffer; each point keeps the
    candidates within ``tau``, the smaller of (1.2 x the previous point's ``k``-th distance)
    and its distance to the block's nearest open face, by a branch-free compaction, and
    selects the ``k`` nearest of the few kept (:func:`_select`, stable): branch
    mispredictions, not arithmetic, are the cost of kNN over ~80 candidates, and a
    selection over all of them pays one per candidate. When fewer than ``k`` candidates lie
    within the block's reach, the point scans rings of cells outward instead
    (:func:`_ring_knn`). Ties are broken by scan order: block order (cells x-major, then
    input order), or ring by ring for ring searches.
    """
    n = xs.shape[1]
    s1, s2 = span[1], span[2]
    widest = 0  # the most candidates of a block of these cells: the scratch's length
    t = first
    while t < stop:
        c0, c1, c2 = cell[order[t], 0], cell[order[t], 1], cell[order[t], 2]
        m = 0
        for a0 in range(max(c0 - 1, 0), min(c0 + 2, span[0])):
            for a1 in range(max(c1 - 1, 0), min(c1 + 2, s1)):
                row = (a0 * s1 + a1) * s2
                m += start[row + min(c2 + 2, s2)] - start[row + max(c2 - 1, 0)]
        widest = max(widest, m)
        t = start[key[order[t]] + 1]
    cand = np.empty((3, widest))
    cand_t = np.empty(widest, np.int64)
    dist = np.empty(widest)
    kept_d = np.empty(widest + 1)
    kept_t = np.empty(widest + 1, np.int64)
    best_d = np.empty(k + 1)  # the k nearest, nearest first (and a slot for the rest)
    best_t = np.empty(k + 1, np.int64)
    face_lo = np.empty(3)
    face_hi = np.empty(3)
    rel = np.empty((k, 3))
    while first < stop:
        c = key[order[first]]
        last = start[c + 1]
        c0, c1, c2 = cell[order[first], 0], cell[order[first], 1], cell[order[first], 2]
        m = 0
        for a0 in range(max(c0 - 1, 0), min(c0 + 2, span[0])):
            for a1 in range(max(c1 - 1, 0), min(c1 + 2, s1)):
                row = (a0 * s1 + a1) * s2
                for t in range(start[row + max(c2 - 1, 0)], start[row + min(c2 + 2, s2)]):
                    cand[0, m], cand[1, m], cand[2, m] = xs[0, t], xs[1, t], xs[2, t]
                    cand_t[m] = t
                    m += 1
        # The block's faces that have cells beyond them (a point nearer to p than the
        # nearest such face is in the block).
        for i, ci in enumerate((c0, c1, c2)):
            face_lo[i] = lo[i] + (ci - 1) * size if ci > 0 else -np.inf
            face_hi[i] = lo[i] + (ci + 2) * size if ci + 2 < span[i] else np.inf
        guess = np.inf
        for j in range(first, last):
            px, py, pz = xs[0, j], xs[1, j], xs[2, j]
            reach = min(px - face_lo[0], py - face_lo[1], pz - face_lo[2])
            reach = min(reach, face_hi[0] - px, face_hi[1] - py, face_hi[2] - pz)
            reach_sq = reach * reach
            for t in range(m):  # vectorised: one array per axis
                dist[t] = (px - cand[0, t]) ** 2 + (py - cand[1, t]) ** 2 + (pz - cand[2, t]) ** 2
            tau = min(reach_sq, guess)
            kept = _compact(dist, cand_t, m, tau, r2, kept_d, kept_t)
            if kept < k and tau < reach_sq:
                kept = _compact(dist, cand_t, m, reach_sq, r2, kept_d, kept_t)
            if kept < k and reach_sq < r2:  # points within the radius may lie beyond
                best_d[:k] = r2
                best_t[:k] = n
                _ring_knn(xs, j, cell[order[j]], lo, size, span, start, best_t[:k], best_d[:k])
                kept = 0
                while kept < k and best_t[kept] < n:
                    kept += 1
            else:
                kept = _select(kept_d, kept_t, kept, k, best_d, best_t)
                if kept == k:
                    guess = 1.44 * best_d[k - 1]
            if moments:
                _moments(xs, j, best_t, kept, rel, cov[order[j]])
                count[order[j]] = kept
            else:
                p = order[j]
                for s in range(kept):
                    idx[p, s] = order[best_t[s]]
                    sq[p, s] = best_d[s]
                idx[p, kept:] = n
                sq[p, kept:] = np.inf
        first = last


@numba.njit
def _median_kth(x, k):
    """Median ``k``-th neighbour distance of up to 16 sample points of ``x`` (``np.median``'s
    value). Each sample's ``k``-th smallest squared distance is selected among the distances
    at most the ``k``-th smallest of every 8th (an upper bound), not among all ``n``."""
    n = x.shape[0]
    samples = min(n, 16)
    kth = np.empty(samples)
    d = np.empty(n)
    kk = min(k, n)
    stride = 8 if n >= 8 * kk else 1
    for s in range(samples):
        a = (s * (n - 1)) // max(samples - 1, 1)
        for b in range(n):
            d[b] = (x[a, 0] - x[b, 0]) ** 2 + (x[a, 1] - x[b, 1]) ** 2 + (x[a, 2] - x[b, 2]) ** 2
        bound = kth_smallest(d[::stride].copy(), kk - 1) if stride > 1 else np.inf
        m = 0
        for b in range(n):
            d[m] = d[b]
            m += d[b] <= bound
        kth[s] = np.sqrt(kth_smallest(d[:m], kk - 1))
    for s in range(1, samples):  # insertion sort of the few samples
        v, t = kth[s], s
        while t > 0 and kth[t - 1] > v:
            kth[t] = kth[t - 1]
            t -= 1
        kth[t] = v
    half = samples // 2
    return kth[half] if samples % 2 else (kth[half - 1] + kth[half]) / 2


@numba.njit(inline="always")
def _compact(dist, ids, m, tau, r2, kept_d, kept_id):
    """Copies the entries of ``dist[:m]`` (and ``ids``) that are ``<= tau`` and ``< r2`` to
    the front of ``kept_d`` / ``kept_id`` without a branch per entry; returns how many."""
    count = 0
    for t in range(m):
        kept_d[count] = dist[t]
        kept_id[count] = ids[t]
        count += (dist[t] <= tau) & (dist[t] < r2)
    return count


@numba.njit
def _select(values, ids, count, k, best, best_ids):
    """Writes the ``k`` smallest of ``values[:count]`` (and their ``ids``) to ``best`` /
    ``best_ids`` (``k + 1`` slots) in ascending order, earlier entries first among equals;
    returns ``min(count, k)``. Up to 64 entries, each goes straight to its rank (the entries
    before it that are not larger, and after it that are smaller), in branch-free loops:
    an insertion sort (beyond 64) pays a mispredicted branch per entry."""
    if count > 64:
        count = _insertion_select(values, ids, count, k)
        best[:count] = values[:count]
        best_ids[:count] = ids[:count]
        return count
    for a in range(count):
        v = values[a]
        rank = 0
        for b in range(count):
            rank += (values[b] < v) | ((values[b] == v) & (b < a))
        best[min(rank, k)] = v
        best_ids[min(rank, k)] = ids[a]
    return min(count, k)


@numba.njit(inline="always")
def _insertion_select(values, ids, count, k):
    """Moves the ``k`` smallest of ``values[:count]`` (and their ``ids``) to the front in
    ascending order, earlier entries first among equals; returns ``min(count, k)``."""
    filled = 0
    for a in range(count):
        v, i = values[a], ids[a]
        if filled < k:
            b = filled
            filled += 1
        elif v < values[k - 1]:
            b = k - 1
        else:
            continue
        _insert(values, ids, b, v, i)
    return filled


@numba.njit(inline="always")
def _insert(values, ids, slot, v, i):
    """Writes ``v`` (and its id ``i``) into the ascending ``values[:slot + 1]``, moving the
    larger entries up by one from ``slot`` (whose entry is dropped); ``v`` goes after its
    equals."""
    while slot > 0 and values[slot - 1] > v:
        values[slot] = values[slot - 1]
        ids[slot] = ids[slot - 1]
        slot -= 1
    values[slot] = v
    ids[slot] = i


@numba.njit(inline="always")
def _moments(xs, j, kept_t, kept, rel, cov):
    """Covariance ``cov (6,)`` of the points at cell-order positions ``kept_t[:kept]`` around
    position ``j`` (see :func:`knn_moments`); ``rel (k, 3)`` is scratch."""
    if kept == 0:
        return
    m0 = m1 = m2 = 0.0
    for s in range(kept):
        rel[s, 0] = xs[0, kept_t[s]] - xs[0, j]
        rel[s, 1] = xs[1, kept_t[s]] - xs[1, j]
        rel[s, 2] = xs[2, kept_t[s]] - xs[2, j]
        m0 += rel[s, 0]
        m1 += rel[s, 1]
        m2 += rel[s, 2]
    m0, m1, m2 = m0 / kept, m1 / kept, m2 / kept
    for s in range(kept):
        d0, d1, d2 = rel[s, 0] - m0, rel[s, 1] - m1, rel[s, 2] - m2
        cov[0] += d0 * d0
        cov[1] += d0 * d1
        cov[2] += d0 * d2
        cov[3] += d1 * d1
        cov[4] += d1 * d2
        cov[5] += d2 * d2
    for i in range(6):
        cov[i] /= kept


@numba.njit
def _ring_knn(xs, j, cell, lo, size, span, start, idx, best):
    """The exact ``k`` nearest of cell-order position ``j`` by rings of cells at growing
    Chebyshev distance, into its sorted short list ``idx`` / ``best`` (length ``k``, cell
    order positions), until the cells scanned hold every point within its current ``k``-th
    distance."""
    k = best.size
    cx, cy, cz = cell[0], cell[1], cell[2]
    for ring in range(max(span[0], span[1], span[2])):
        # Cells at Chebyshev distance `ring`: whole z-runs on the ring's x or y faces,
        # the two z caps elsewhere.
        # A column or cap wholly at least the k-th distance away is skipped: none of its
        # points would enter the list (the gaps are shrunk by 1e-6 cells for rounding).
        for ax in range(max(cx - ring, 0), min(cx + ring + 1, span[0])):
            gx = _gap(xs[0, j], lo[0], size, ax, span[0])
            for ay in range(max(cy - ring, 0), min(cy + ring + 1, span[1])):
                gxy = gx + _gap(xs[1, j], lo[1], size, ay, span[1])
                if gxy >= best[k - 1]:
                    continue
                row = (ax * span[1] + ay) * span[2]
                if abs(ax - cx) == ring or abs(ay - cy) == ring:
                    first = start[row + max(cz - ring, 0)]
                    last = start[row + min(cz + ring + 1, span[2])]
                    _scan(xs, j, first, last, idx, best)
                else:
                    for az in (cz - ring, cz + ring):
                        if 0 <= az < span[2]:
                            if gxy + _gap(xs[2, j], lo[2], size, az, span[2]) < best[k - 1]:
                                _scan(xs, j, start[row + az], start[row + az + 1], idx, best)
        # Every point nearer to p than the scanned block's nearest open face is scanned.
        reach_sq = np.inf
        for i in range(3):
            low, high = cell[i] - ring, cell[i] + ring + 1
            if low > 0:
                reach_sq = min(reach_sq, (xs[i, j] - lo[i] - low * size) ** 2)
            if high < span[i]:
                reach_sq = min(reach_sq, (lo[i] + high * size - xs[i, j]) ** 2)
        if best[k - 1] <= reach_sq:
            break


@numba.njit(inline="always")
def _gap(x, lo, size, c, span):
    """Squared distance along one axis from ``x`` to cell ``c``'s slab, less 1e-6 cells
    (the last cell is unbounded above, the first below: points are clamped into them)."""
    below = lo + c * size - x if c > 0 else 0.0
    above = x - (lo + (c + 1) * size) if c + 1 < span else 0.0
    gap = max(below, above, 0.0) - 1e-6 * size
    return gap * gap if gap > 0 else 0.0


@numba.njit(inline="always")
def _scan(xs, j, first, last, idx, best):
    """Inserts cell-order positions ``first:last`` into position ``j``'s sorted short list."""
    k = best.size
    px, py, pz = xs[0, j], xs[1, j], xs[2, j]
    for q in range(first, last):
        d = (px - xs[0, q]) ** 2 + (py - xs[1, q]) ** 2 + (pz - xs[2, q]) ** 2
        if d < best[k - 1]:
            _insert(best, idx, k - 1, d, q)
