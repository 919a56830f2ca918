"""The grid's 1-NN query: XLA's vectorised gathers against a compiled scalar loop (numba).

Usage: python benchmarks/bench_query_kernel.py [--data DIR] [--repeats 7]

The question is whether ICP's neighbour query (``jaxreg.search.neighbors.query_nearest``,
which XLA compiles to gathers vectorised over queries) would run faster as a compiled CPU
kernel called from the traced program. This times the kernel at its best, called directly
from Python on numpy arrays (no custom-call or callback overhead, which a real integration
would add per ICP iteration), against the jitted XLA query on the same grid and queries:
milk.pcd at 4 mm (3.7k points, padded to 4096) moved by ``S`` starts (``jr.rotation_inits``
within 30 degrees, as ``bench_icp.py``), the grid of ``jr.icp`` (capacity 48) and of
``jr.multistart_icp`` (capacity 24). The numba loop is written to give the same answers as
the XLA query (same float32 arithmetic for the leaf, the first slot on ties); the script
checks that every index agrees before timing. Reported: nanoseconds per query, medians of
interleaved rounds, with the load average (the machine is shared).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numba
import numpy as np
from _timing import DATA, print_table

import jaxreg as jr
from jaxreg.registration.solver import ICPOptions, apply_pose, prepare
from jaxreg.search.neighbors import query_nearest


def _kernel(origin, cell_size, max_distance, dims, cells, leaf_map, cand_index, cand_points,
            num_points, queries, distance, out_index):  # fmt: skip
    """``query_nearest``'s index for queries ``(B, N, 3)`` and radii ``(B,)``, one query per
    trip of the outer loop (``numba.prange`` in the threaded variant)."""
    batch, n = queries.shape[0], queries.shape[1]
    cap = cand_index.shape[1]
    for t in numba.prange(batch * n):
        b = t // n
        i = t - b * n
        qx, qy, qz = queries[b, i, 0], queries[b, i, 1], queries[b, i, 2]
        ux = (qx - origin[0]) / cell_size
        uy = (qy - origin[1]) / cell_size
        uz = (qz - origin[2]) / cell_size
        leaf = 0
        inside = False
        if np.isfinite(ux) and np.isfinite(uy) and np.isfinite(uz):
            fx, fy, fz = np.floor(ux), np.floor(uy), np.floor(uz)
            if 0 <= fx < dims[0] and 0 <= fy < dims[1] and 0 <= fz < dims[2]:
                inside = True
                cid = (int(fx) * dims[1] + int(fy)) * dims[2] + int(fz)
                side = 1 << cells[cid, 1]
                scale = np.float32(side)
                sx = min(max(int(np.floor((ux - fx) * scale)), 0), side - 1)
                sy = min(max(int(np.floor((uy - fy) * scale)), 0), side - 1)
                sz = min(max(int(np.floor((uz - fz) * scale)), 0), side - 1)
                leaf = leaf_map[cells[cid, 0] + (sx * side + sy) * side + sz]
        px, py, pz = cand_points[0, leaf], cand_points[1, leaf], cand_points[2, leaf]
        dx, dy, dz = px[0] - qx, py[0] - qy, pz[0] - qz
        best = dx * dx + dy * dy + dz * dz
        slot = 0
        for j in range(1, cap):
            dx, dy, dz = px[j] - qx, py[j] - qy, pz[j] - qz
            d = dx * dx + dy * dy + dz * dz
            if d < best:
                best, slot = d, j
        r = min(distance[b], max_distance)
        found = inside and best <= r * r
        out_index[b, i] = cand_index[leaf, slot] if found else num_points


SERIAL = numba.njit(cache=True)(_kernel)
THREADED = numba.njit(cache=True, parallel=True)(_kernel)


def _case(problem, inits, repeats: int) -> list[list[str]]:
    """Rows of one grid and batch of starts: every contender's time per query."""
    grid = problem.grid
    query = jax.jit(jax.vmap(lambda g, q, d: query_nearest(g, q, d)[0], (None, 0, 0)))
    queries = jax.vmap(lambda p: apply_pose(p, problem.source))(inits)
    radii = jnp.full(queries.shape[0], 0.02, jnp.float32)
    fields = ("origin", "cell_size", "max_distance", "dims", "cells", "leaf_map",
              "candidate_index", "candidate_points", "num_points")  # fmt: skip
    host = [np.asarray(getattr(grid, f)) for f in fields]
    host = [x[()] if x.ndim == 0 else x for x in host]  # scalars as numpy scalars
    host_queries, host_radii = np.asarray(queries), np.asarray(radii)
    out = np.empty(host_queries.shape[:2], np.int32)
    expected = np.asarray(query(grid, queries, radii))
    contenders = {
        "XLA query_nearest (jit, vmap)": lambda: jax.block_until_ready(query(grid, queries, radii)),
        "numba loop, one thread": lambda: SERIAL(*host, host_queries, host_radii, out),
        "numba loop, prange": lambda: THREADED(*host, host_queries, host_radii, out),
    }
    for name, fn in contenders.items():
        fn()
        if not name.startswith("XLA") and not np.array_equal(out, expected):
            raise SystemExit(f"{name} disagrees with query_nearest")
    times = {name: [] for name in contenders}
    for _ in range(repeats):
        for name, fn in contenders.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    n = host_queries.shape[0] * host_queries.shape[1]
    xla = statistics.median(times["XLA query_nearest (jit, vmap)"])
    label = f"{host_queries.shape[0]} x {host_queries.shape[1]}, capacity {grid.capacity}"
    return [
        [label, name, f"{statistics.median(t) / n * 1e9:.0f}", f"{statistics.median(t) / xla:.2f}"]
        for name, t in times.items()
    ]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    pcd = args.data / "pcl" / "milk.pcd"
    if not pcd.is_file():
        raise SystemExit(f"milk.pcd not found under {args.data}/pcl: pass --data or JAXREG_DATA")
    points = jr.voxel_downsample(jr.io.load_points(pcd), 0.004).astype(np.float32)
    turn = np.array([[1, -0.05, 0], [0.05, 1, 0], [0, 0, 1]], np.float32)
    moved = points @ turn.T + np.float32(0.005)
    inits = jr.rotation_inits(points, moved, 64, around=jr.SE3.identity(), max_angle=0.5236)
    options = ICPOptions(tolerance=0.0)
    rows = []
    for capacity, starts in ((None, 1), (24, 64)):  # jr.icp's grid; jr.multistart_icp's
        extra = {} if capacity is None else dict(grid_capacity=capacity)
        problem, _, _ = prepare(points, moved, options, **extra)
        rows += _case(problem, jr.SE3(inits.wxyz_xyz[:starts]), args.repeats)
    print_table(
        f"Grid 1-NN query, milk.pcd @ 4 mm; jax {jax.__version__}, numba {numba.__version__}, "
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}; medians of "
        f"{args.repeats} interleaved rounds, every index checked equal",
        ["queries", "contender", "ns per query", "time vs XLA"],
        rows,
    )


if __name__ == "__main__":
    main()
