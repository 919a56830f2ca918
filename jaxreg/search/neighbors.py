"""Nearest-neighbour search with static shapes: 1-NN, kNN and fixed-capacity radius queries.

Two engines, one contract (jax-md's neighbour lists): capacities are fixed on the host,
missing neighbours are the sentinel index ``M`` (the number of target rows) with ``inf``
distance and a False mask, and overflow is reported, never silently dropped.

Both are reached through the same entry points, :func:`knn` and :func:`radius_search`, whose
target is either the points or a grid built on them; :func:`query_nearest` is the grid's 1-NN.

* **The grid** (:class:`NeighborGrid`; :func:`build_grid` on the host, then the jittable
  :func:`query_nearest`, :func:`knn` and :func:`radius_search` on it). A target indexed once
  and passed into ``jit`` / ``vmap`` as a pytree: the structure ICP queries every iteration
  while the source moves, and that many starts share. A uniform grid of cells at least
  ``max_distance`` wide covers the target's bounding box grown by ``max_distance``; each
  cell is refined as an octree until its leaves' *candidate lists* are short. A leaf lists
  only the target points that can be an answer (the nearest, one of the ``k`` nearest, or
  within ``max_distance``) for some query inside it; the pruning tests are in
  :mod:`jaxreg.search._octree`, whose compiled loops build every kind of grid. The octree is
  stored flat: each top-level cell owns a dense block of sub-cells at its deepest level, so
  a query finds its leaf with two integer gathers, reads ``capacity`` contiguous candidates
  and keeps the nearest: O(capacity) per query, independent of the target's size and of
  the octree's depth. A grid built elsewhere is checked against its target with
  :func:`validate_grid`.

  **Exactness.** For a query whose true nearest neighbour (for kNN: each of its true ``k``
  nearest; for radius queries: every point within the radius) lies within
  ``max_distance``, that point is among its leaf's candidates, so the answer is exact up to
  ties of equal distance and float rounding; neighbours beyond ``max_distance`` are
  invalid. Boxes are grown by a relative margin before every test, so float32 rounding of
  the query's leaf never breaks this. The one way to lose exactness is an explicit
  ``capacity`` that a leaf still exceeds at the maximum depth: the leaf keeps the
  candidates nearest its centre and ``grid.overflow`` is set (rebuild with a larger
  capacity). With ``capacity=None`` the host sizes it so this never happens.

  **Shapes.** Only ``k`` is static: origin, cell size, ``dims`` and ``num_points`` are
  array leaves; the candidate table's rows are padded to a power of two, the cell table to
  the cells of the cube around the target's bounding sphere (which holds every rotation of
  it), the leaf map to eight entries per table row, and the capacity is rounded up to a
  multiple of 16. Targets of similar size and extent (a scene re-captured, the same cloud
  rotated) give grids of identical shapes, so a jitted function taking the grid as an
  argument compiles once for all of them.

* **Blocked brute force** (:func:`knn`, :func:`radius_search` on the points,
  :mod:`jaxreg.core._brute`): exact and jittable with the target traced (no host step);
  the reference the grid is tested against.

Which to use (``benchmarks/bench_neighbors.py`` on milk.pcd, 13.7k points and its 4 mm
downsample of 3.7k, radius 2 cm, on the project's shared 2-core CPU, where timings vary up
to ~2x between runs):

* ICP correspondences (1-NN within ``max_correspondence_distance``, one target for every
  iteration and start): the grid. At 3.7k points it builds in ~15-30 ms and 40 dependent
  queries in one ``jit`` take ~5-15 ms, where one brute-force pass takes ~60-80 ms (a
  3.7k x 3.7k distance matrix). Reuse a grid across calls on the same target
  (``icp(..., neighbors=grid)``, :func:`jaxreg.registration.icp.multistart_icp`).
* kNN for normals (one pass, ``k`` ~ 20): :func:`jaxreg.search.normals.estimate_normals` finds the
  exact ``k`` nearest of a concrete cloud with compiled host loops
  (:func:`jaxreg.search._knn.self_knn`, about twice as fast as scipy's cKDTree build + query on
  the full milk.pcd), and falls back to brute
  force when the cloud is traced. A ``k``-NN grid (``build_grid(k=20)`` then :func:`knn` on
  it) serves jitted code that queries one target repeatedly.
* Radius neighbourhoods (features): on a concrete cloud FPFH uses ``self_knn`` capped at the
  radius (the nearest ``max_neighbors`` within it, Open3D's hybrid search); jitted code a
  radius grid (``k=None``) and :func:`radius_search` on it.
* On GPUs brute force's distance matrix is one cheap matrix product.

A kd-tree in JAX was not written: its traversal is a data-dependent loop per query, which
under ``vmap`` runs every lane to the slowest lane's depth, and its leaf scans are the same
gathers the grid does after O(1) instead of O(log M) steps.

Shapes: targets are ``(M, 3)``, queries ``(N, 3)``; write queries unbatched and ``vmap``
over query sets (the grid is shared: ``in_axes=None``). Queries and target must be in the
same frame (for ICP: the source moved by the current pose, in target coordinates).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.core import _brute
from jaxreg.core._brute import check_queries, pad_slots
from jaxreg.search._grid import (
    NeighborGrid as NeighborGrid,
    build_grid as build_grid,
    pad_grid as pad_grid,
    validate_grid as validate_grid,
)

__all__ = [
    "NeighborGrid",
    "build_grid",
    "knn",
    "pad_grid",
    "query_nearest",
    "radius_search",
    "validate_grid",
    "voxel_downsample",
]

# Candidate lists this short or shorter are scanned by an unrolled loop (fast on CPU, compile
# time linear in the length); longer ones by a reduction over the candidate axis.
_UNROLL_LIMIT = 256


# --------------------------------------------------------------------------------------------
# Grid queries (jittable; vmap over query sets with the grid shared).


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
    grid: NeighborGrid,
    queries: ArrayLike,
    max_distance: ArrayLike | None = None,
    mask: Bool[ArrayLike, " M"] | None = None,
    mask_queries: Bool[ArrayLike, " N"] | None = None,
) -> tuple[Int[Array, " N"], Float[Array, " N"], Bool[Array, " N"]]:
    """Nearest target point of each query within ``max_distance`` (jittable).

    Args:
        grid: from :func:`build_grid` on the target.
        queries: ``(N, 3)`` points in the target's frame (``vmap`` for batches of query
            sets; non-finite queries are invalid).
        max_distance: ``()`` acceptance radius, default ``grid.max_distance``; clipped to it
            (exactness is guaranteed only up to ``grid.max_distance``). May be traced, e.g.
            a shrinking ICP schedule.
        mask: ``(M,)`` target rows that may be an answer (``None``: every row the grid
            indexes); may be traced, e.g. the target points facing a sensor at the current
            pose. The answer is the nearest allowed point among the query's leaf's
            candidates: the exact nearest allowed point when it is on that list (always when
            the nearest point overall is allowed); where the list holds only points the mask
            excludes, none (the leaf lists the points that can be nearest overall, not the
            nearest of every subset).
        mask_queries: ``(N,)`` the queries ``mask`` applies to (default all); the others may
            take any row.

    Returns:
        ``indices (N,)`` into the target rows (sentinel ``grid.num_points`` when invalid),
        ``sq_dists (N,)`` squared distances (``inf`` when invalid) and ``valid (N,)``: a
        target point lies within ``max_distance``. Exact for valid queries (ties broken
        arbitrarily) unless ``grid.overflow``.
    """
    queries = check_queries(queries)
    leaf, inside = _leaf(grid, queries)
    d2 = _candidate_sq_dists(grid, queries, leaf)
    if mask is not None:
        allowed = (
            jnp.asarray(mask).at[grid.candidate_index[leaf]].get(mode="fill", fill_value=False)
        )
        if mask_queries is not None:
            allowed |= ~jnp.asarray(mask_queries)[:, None]
        d2 = jnp.where(allowed, d2, jnp.inf)
    best, slot = _nearest_slot(d2)
    valid = inside & (best <= _radius2(grid, max_distance, best.dtype))
    index = jnp.where(valid, grid.candidate_index[leaf, slot], grid.num_points)
    out_dtype = jnp.result_type(queries.dtype, grid.candidate_points.dtype)
    sq = jnp.where(valid, best, jnp.inf).astype(out_dtype)
    return index, sq, valid


def _grid_knn(grid: NeighborGrid, queries: Array, k: int, max_distance) -> tuple:
    """:func:`knn` on a grid (``queries`` checked)."""
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
    return pad_slots(index, sq, mask, k, grid.num_points)


def _grid_radius(grid: NeighborGrid, queries: Array, radius, capacity: int) -> tuple:
    """:func:`radius_search` on a grid (``queries`` checked)."""
    if grid.k is not None:
        raise ValueError("radius_search needs a grid built with k=None (unpruned lists)")
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
    return *pad_slots(index, sq, mask, capacity, grid.num_points), count > capacity


# --------------------------------------------------------------------------------------------
# kNN and radius search, on points (brute force) or on a grid.


def knn(
    queries: ArrayLike,
    target: ArrayLike | NeighborGrid,
    k: int,
    *,
    max_distance: ArrayLike | None = None,
    mask: ArrayLike | None = None,
    block: int | None = None,
) -> tuple[Int[Array, "N k"], Float[Array, "N k"], Bool[Array, "N k"]]:
    """The ``k`` nearest target points of each query (jittable).

    Args:
        queries: ``(N, 3)`` in the target's frame; non-finite rows get no neighbours.
        target: the ``(M, 3)`` target points, searched by blocked brute force (exact; they
            may be traced), or a :class:`NeighborGrid` built on them with ``k`` or more
            (or ``k=None``), exact within ``max_distance`` unless ``grid.overflow``.
        k: static number of neighbours (a query that is a target point counts itself).
        max_distance: optional ``()`` radius: neighbours beyond it are masked out. On a grid
            it defaults to, and is clipped to, ``grid.max_distance``.
        mask: ``(M,)`` optional validity of target points (non-finite points are invalid
            too); brute force only (a grid holds the points it was built on).
        block: static queries per brute-force block; ``block * M`` distances are held at
            once (default: about 4M, 16 MB in float32).

    Returns:
        ``indices (N, k)``, ``sq_dists (N, k)`` nearest first, ``mask (N, k)``. Missing
        neighbours (fewer than ``k`` valid points, beyond ``max_distance``) have the sentinel
        index ``M`` and ``inf`` distance. Distances are exact; brute force screens candidates
        with a matrix product, so neighbours whose distances tie to ~1e-4 relative (float32)
        may come in either order.

    Raises:
        ValueError: ``queries`` not ``(N, 3)``, ``k`` above the grid's, or ``mask`` or
            ``block`` with a grid.
    """
    if isinstance(target, NeighborGrid):
        _grid_only(mask, block)
        return _grid_knn(target, check_queries(queries), k, max_distance)
    return _brute.knn(queries, target, k, max_distance=max_distance, mask=mask, block=block)


def radius_search(
    queries: ArrayLike,
    target: ArrayLike | NeighborGrid,
    radius: ArrayLike,
    capacity: int,
    *,
    mask: ArrayLike | None = None,
    block: int | None = None,
) -> tuple[Int[Array, "N c"], Float[Array, "N c"], Bool[Array, "N c"], Bool[Array, " N"]]:
    """All target points within ``radius`` of each query, up to ``capacity`` (jittable).

    Args:
        queries: ``(N, 3)`` in the target's frame; non-finite rows get no neighbours.
        target: the ``(M, 3)`` target points (blocked brute force; they may be traced), or a
            :class:`NeighborGrid` built on them with ``k=None`` (its lists unpruned).
        radius: ``()`` search radius (may be traced); on a grid clipped to
            ``grid.max_distance``.
        capacity: static neighbour slots per query.
        mask: ``(M,)`` optional validity of target points; brute force only.
        block: static queries per brute-force block (see :func:`knn`).

    Returns:
        ``indices (N, capacity)`` and ``sq_dists (N, capacity)`` nearest first,
        ``mask (N, capacity)``, and ``overflow (N,)``: more than ``capacity`` points lie
        within ``radius`` (the nearest ``capacity`` are kept). Padding is the sentinel ``M``
        with ``inf`` distance.

    Raises:
        ValueError: ``queries`` not ``(N, 3)``, a grid built with ``k`` set, or ``mask`` or
            ``block`` with a grid.
    """
    if isinstance(target, NeighborGrid):
        _grid_only(mask, block)
        return _grid_radius(target, check_queries(queries), radius, capacity)
    return _brute.radius_search(queries, target, radius, capacity, mask=mask, block=block)


def _grid_only(mask, block) -> None:
    if mask is not None or block is not None:
        raise ValueError(
            "mask and block apply to a target given as points; a grid holds the points it "
            "was built on (build it on the valid ones)"
        )


# --------------------------------------------------------------------------------------------
# Host helpers.


def cell_codes(cells: np.ndarray) -> np.ndarray:
    """``(K,)`` int64 codes of the integer cells ``(K, 3)``, ordered as the cells are
    (lexicographically, x-major): ``np.unique`` of the codes groups and orders the cells as
    ``np.unique(cells, axis=0)`` does, an order of magnitude faster. Host-side numpy."""
    cells = np.asarray(cells, np.int64)
    if len(cells) == 0:
        return np.zeros(0, np.int64)
    key = cells - cells.min(0)
    dims = key.max(0) + 1
    if np.prod(dims.astype(np.float64)) >= 2.0**62:  # no room for one int64 per cell
        return np.unique(cells, axis=0, return_inverse=True)[1].reshape(-1)
    return (key[:, 0] * dims[1] + key[:, 1]) * dims[2] + key[:, 2]


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
    key = cell_codes(np.floor((pts - origin) / voxel_size))  # x-major voxel order
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = [np.bincount(inverse, pts[:, i], len(counts)) for i in range(3)]
    return (np.stack(sums, 1) / counts[:, None]).astype(dtype)
