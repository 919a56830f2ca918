"""Nearest-neighbour engines on milk.pcd: the grid, blocked brute force, scipy, Open3D.

Usage: python benchmarks/bench_neighbors.py [--data DIR] [--radius 0.02] [--repeats 30]
       [--cases icp normals]
(DIR defaults to $JAXREG_DATA/pcl, else ../shared/data/pcl beside the repository)

Prints one table (median milliseconds of repeated runs, after a warm-up call that compiles).
The ICP case: target = milk.pcd voxel-downsampled at 4 mm (~3.7k points) and in full
(13.7k), queries = the same cloud moved by a small pose plus 1 mm noise (a source near
convergence), 1-NN within the radius. "grid build + 40 queries" is what one ICP call spends
on correspondences; Open3D's ``registration_icp`` with 40 iterations (its kd-tree build, 40
1-NN passes and 40 Kabsch solves) is the end-to-end reference, timed in the same run. The
normals case: kNN with k = 20 and normals on the downsampled and the full cloud; the last row
of each times ``estimate_normals`` against Open3D's ``estimate_normals`` + orientation in
interleaved rounds. Peers (scipy, open3d) are optional and skipped when missing.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _timing import DATA, interleaved_medians

from jaxreg.io import load_points
from jaxreg.search.neighbors import (
    build_grid,
    knn,
    query_nearest,
    voxel_downsample,
)
from jaxreg.search.normals import estimate_normals

ROWS: list[tuple[str, str, float, str]] = []


def timed(fn, repeats: int) -> float:
    """Median wall time in ms of ``fn()`` (results blocked on), after one warm-up call."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t)
    return 1e3 * statistics.median(times)


def row(case: str, engine: str, ms: float, note: str = "") -> None:
    ROWS.append((case, engine, ms, note))
    print(f"  {case:<28} {engine:<44} {ms:10.2f}  {note}", flush=True)


def icp_case(target: np.ndarray, radius: float, repeats: int) -> None:
    rng = np.random.default_rng(0)
    angle = np.radians(3.0)
    rot = np.array(
        [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    )
    centre = target.mean(0)
    source = (target - centre) @ rot.T + centre + [0.004, -0.003, 0.002]
    source = (source + rng.normal(0, 0.001, source.shape)).astype(np.float32)
    case = f"1-NN {len(source)}x{len(target)}"

    build_ms = timed(lambda: build_grid(target, radius).origin, max(5, repeats // 3))
    grid = build_grid(target, radius)
    row(
        case,
        "grid build (host, once per target)",
        build_ms,
        f"r={radius} capacity={grid.capacity} depth={grid.depth} {grid.nbytes / 1e6:.1f} MB",
    )
    query = jax.jit(query_nearest)
    q = jnp.asarray(source)
    row(case, "grid query (jit)", timed(lambda: query(grid, q), repeats))

    @jax.jit
    def forty(grid, q):  # 40 dependent queries, as ICP's loop makes them
        def body(_, x):
            _, _, valid = query_nearest(grid, x)
            return x + 1e-9 * jnp.where(valid[:, None], grid.origin, 0)

        return jax.lax.fori_loop(0, 40, body, q)

    forty_ms = timed(lambda: forty(grid, q), repeats)
    row(case, "grid 40 chained queries (one jit)", forty_ms)
    row(
        case,
        "grid build + 40 queries",
        timed(lambda: forty(build_grid(target, radius), q), max(5, repeats // 3)),
        "what one ICP call spends on correspondences",
    )
    starts = jnp.asarray(
        np.stack([source + rng.normal(0, 0.002, source.shape) for _ in range(64)]).astype(
            np.float32
        )
    )
    batched = jax.jit(jax.vmap(query_nearest, in_axes=(None, 0)))
    ms = timed(lambda: batched(grid, starts), max(3, repeats // 5))
    row(case, "grid 64 query sets (vmap, one call)", ms, f"{ms / 64:.3f} ms per set")
    brute = jax.jit(lambda q, t: knn(q, t, 1, max_distance=radius))
    t = jnp.asarray(target)
    row(case, "brute force knn k=1 (jit)", timed(lambda: brute(q, t), max(3, repeats // 5)))

    try:
        from scipy.spatial import cKDTree
    except ImportError:
        print("  (scipy missing: cKDTree rows skipped)")
    else:
        row(case, "scipy cKDTree build", timed(lambda: cKDTree(target), repeats))
        tree = cKDTree(target)
        row(
            case,
            "scipy cKDTree query",
            timed(lambda: tree.query(source, distance_upper_bound=radius), repeats),
        )
    try:
        import open3d as o3d
    except ImportError:
        print("  (open3d missing: Open3D rows skipped)")
        return
    tcloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target.astype(np.float64)))
    scloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source.astype(np.float64)))
    row(case, "open3d KDTreeFlann build", timed(lambda: o3d.geometry.KDTreeFlann(tcloud), repeats))
    row(
        case,
        "open3d compute_point_cloud_distance",
        timed(lambda: np.asarray(scloud.compute_point_cloud_distance(tcloud)), repeats),
        "kd-tree build + one 1-NN pass",
    )
    reg = o3d.pipelines.registration
    never = reg.ICPConvergenceCriteria(relative_fitness=0, relative_rmse=0, max_iteration=40)
    point_to_point = reg.TransformationEstimationPointToPoint()
    row(
        case,
        "open3d registration_icp, 40 iterations",
        timed(
            lambda: reg.registration_icp(scloud, tcloud, radius, np.eye(4), point_to_point, never),
            max(5, repeats // 3),
        ),
        "kd-tree build + 40 x (1-NN + Kabsch)",
    )


def normals_case(points: np.ndarray, repeats: int) -> None:
    case = f"kNN k=20 / normals {len(points)}"
    p = jnp.asarray(points)
    reps = max(3, repeats // 10)
    row(
        case,
        "estimate_normals (default: host kNN + PCA)",
        timed(lambda: estimate_normals(points, 20), reps),
        "concrete cloud: exact kNN by compiled host loops",
    )
    normals = jax.jit(lambda x: estimate_normals(x, 20))
    row(case, "estimate_normals under jit (brute knn + PCA)", timed(lambda: normals(p), reps))
    brute = jax.jit(lambda x: knn(x, x, 20))
    row(case, "brute force knn (jit)", timed(lambda: brute(p), reps))
    spacing = float(np.median(np.sqrt(np.asarray(knn(p[:256], p, 2)[1][:, 1]))))
    radius = 6 * spacing
    grid_ms = timed(lambda: build_grid(points, radius, k=20).origin, 3)
    grid = build_grid(points, radius, k=20)
    query = jax.jit(knn, static_argnums=2)
    found = float(query(p, grid, 20)[2].all(1).mean())
    row(case, "grid build k=20", grid_ms, f"r={radius * 1e3:.1f} mm capacity={grid.capacity}")
    row(case, "grid knn (jit)", timed(lambda: query(p, grid, 20), reps), f"{found:.1%} full")
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        pass
    else:
        row(
            case,
            "scipy cKDTree build + query",
            timed(lambda: cKDTree(points).query(points, 20), reps),
        )
    try:
        import open3d as o3d
    except ImportError:
        return
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))

    def o3d_normals():
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        cloud.orient_normals_towards_camera_location(np.zeros(3))
        return np.asarray(cloud.normals)

    row(case, "open3d estimate_normals + orient", timed(o3d_normals, reps))
    # The comparison that matters, timed in interleaved rounds so load falls on both alike.
    t = interleaved_medians(
        {
            "ours": lambda: jax.block_until_ready(estimate_normals(points, 20)),
            "open3d": o3d_normals,
        },
        max(7, reps),
    )
    row(
        case,
        "interleaved: estimate_normals / open3d",
        1e3 * t["ours"],
        f"open3d {1e3 * t['open3d']:.2f} ms: jaxreg {t['open3d'] / t['ours']:.2f}x Open3D's speed",
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA / "pcl", help="default $JAXREG_DATA/pcl")
    parser.add_argument("--radius", type=float, default=0.02)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument(
        "--cases", nargs="+", choices=["icp", "normals"], default=["icp", "normals"]
    )
    args = parser.parse_args()
    full = load_points(args.data / "milk.pcd")
    target = voxel_downsample(full, 0.004)
    print(f"milk.pcd: {len(full)} points, {len(target)} after 4 mm voxels; {jax.devices()[0]}")
    print(f"  {'case':<28} {'engine':<44} {'median ms':>10}")
    if "icp" in args.cases:
        icp_case(target, args.radius, args.repeats)
        icp_case(full, args.radius, args.repeats)
    if "normals" in args.cases:
        normals_case(target, args.repeats)
        normals_case(full, args.repeats)


if __name__ == "__main__":
    main()
