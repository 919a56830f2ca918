"""ICP latency and multi-start throughput against Open3D and small_gicp, in one run.

Usage: python benchmarks/bench_icp.py [--data DIR] [--starts 64] [--iterations 40]

Clouds: PCL's milk.pcd (a real Kinect scan of a milk carton) voxel-downsampled to 4 mm
(~3.7k points) is the source; the target is the same cloud moved by a known pose with
1 mm noise. Every solver runs point-to-point ICP with a 2 cm correspondence distance and
exactly ``--iterations`` iterations (convergence thresholds set to zero), from the same
starts. Times are medians over repeats after a warm-up call; jaxreg's compile time is
reported separately. The multi-start rows time ``--starts`` starts spread within 30 degrees
of the identity: jaxreg runs them in one vmapped call (its grid build included), the peers in
a Python loop.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _timing import median_seconds, print_table

import jaxreg as jr
from jaxreg.neighbors import build_grid

IDENTITY = np.eye(4)


def load_clouds(data: Path):
    model = jr.voxel_downsample(jr.io.load_points(data / "pcl" / "milk.pcd"), 0.004)
    model = model.astype(np.float32)
    truth = jr.SE3.from_rotation_and_translation(
        jr.SO3.from_rpy_radians(0.05, -0.08, 0.1), jnp.array([0.01, -0.005, 0.008])
    )
    rng = np.random.default_rng(0)
    scene = np.asarray(truth @ model) + rng.normal(0, 0.001, model.shape).astype(np.float32)
    return model, scene.astype(np.float32), truth


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default_data = os.environ.get(
        "JAXREG_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"
    )
    parser.add_argument("--data", type=Path, default=Path(default_data))
    parser.add_argument("--starts", type=int, default=64)
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    if not (args.data / "pcl" / "milk.pcd").is_file():
        raise SystemExit(
            f"milk.pcd not found under {args.data}/pcl: pass --data or set JAXREG_DATA"
        )
    model, scene, truth = load_clouds(args.data)
    iters, dist = args.iterations, 0.02
    inits = jr.rotation_inits(
        model, scene, args.starts, around=jr.SE3.identity(), max_angle=np.deg2rad(30.0)
    )
    init_mats = np.asarray(inits.as_matrix(), np.float64)
    options = dict(max_correspondence_distance=dist, max_iterations=iters, tolerance=0.0)

    rows = []

    def add(name, seconds, per_start=None, compile_s=None):
        rows.append(
            [
                name,
                f"{seconds * 1e3:.1f}",
                "" if per_start is None else f"{per_start * 1e3:.2f}",
                "" if compile_s is None else f"{compile_s:.1f}",
            ]
        )
        return seconds

    # jaxreg, single start: with the grid built in the call, and with a prebuilt grid.
    start = time.perf_counter()
    jax.block_until_ready(jr.icp(model, scene, **options))
    compile_single = time.perf_counter() - start
    t_single = add(
        "jaxreg icp (builds its grid)",
        median_seconds(
            lambda: jax.block_until_ready(jr.icp(model, scene, **options)), args.repeats
        ),
        compile_s=compile_single,
    )
    grid = build_grid(scene, dist)
    t_prebuilt = add(
        "jaxreg icp (prebuilt grid)",
        median_seconds(
            lambda: jax.block_until_ready(jr.icp(model, scene, neighbors=grid, **options)),
            args.repeats,
        ),
    )
    t_build = add(
        "  of which grid build (host)",
        median_seconds(lambda: build_grid(scene, dist), args.repeats),
    )
    start = time.perf_counter()
    jax.block_until_ready(jr.multistart_icp(model, scene, inits, **options))
    compile_multi = time.perf_counter() - start
    t_multi = median_seconds(
        lambda: jax.block_until_ready(
            jr.multistart_icp(model, scene, inits, **options)
        ),
        max(3, args.repeats // 2),
    )
    add(
        f"jaxreg multistart_icp x{args.starts} (one call)",
        t_multi,
        t_multi / args.starts,
        compile_multi,
    )

    peers = {}
    try:
        import open3d as o3d

        reg = o3d.pipelines.registration
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.astype(np.float64)))
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scene.astype(np.float64)))
        crit = reg.ICPConvergenceCriteria(0.0, 0.0, iters)
        est = reg.TransformationEstimationPointToPoint()

        def o3d_one(init=IDENTITY):
            return reg.registration_icp(src, tgt, dist, init, est, crit)

        peers["Open3D"] = add("Open3D registration_icp", median_seconds(o3d_one, args.repeats))
        t = median_seconds(lambda: [o3d_one(m) for m in init_mats], max(3, args.repeats // 2))
        peers["Open3D loop"] = add(f"Open3D loop x{args.starts}", t, t / args.starts)
    except ImportError as err:
        print(f"open3d unavailable ({err}): its rows are skipped")
    try:
        import small_gicp

        s_src = small_gicp.PointCloud(model.astype(np.float64))
        s_tgt = small_gicp.PointCloud(scene.astype(np.float64))
        tree = small_gicp.KdTree(s_tgt, num_threads=1)

        def sg_one(init=IDENTITY, tree=tree):
            return small_gicp.align(
                s_tgt,
                s_src,
                tree,
                init,
                registration_type="ICP",
                max_correspondence_distance=dist,
                max_iterations=iters,
                rotation_epsilon=0.0,
                translation_epsilon=0.0,
                num_threads=1,
            )

        peers["small_gicp"] = add(
            "small_gicp ICP (prebuilt tree, 1 thread)", median_seconds(sg_one, args.repeats)
        )
        t = median_seconds(lambda: [sg_one(m) for m in init_mats], max(3, args.repeats // 2))
        peers["small_gicp loop"] = add(f"small_gicp loop x{args.starts}", t, t / args.starts)
    except ImportError as err:
        print(f"small_gicp unavailable ({err}): its rows are skipped")

    device = jax.devices()[0]
    print_table(
        f"ICP point-to-point, milk.pcd @ 4 mm ({len(model)} -> {len(scene)} points), {iters} "
        f"iterations; jax {jax.__version__} on {device.platform} ({device.device_kind}), "
        f"{os.cpu_count()} cores, {platform.machine()}",
        ["solver", "median ms", "ms per start", "compile s"],
        rows,
    )
    ratios = []
    for peer in ("Open3D", "small_gicp"):
        if peer in peers:
            ratios.append(
                [f"single start: {peer} / jaxreg (builds grid)", f"{peers[peer] / t_single:.2f}x"]
            )
            ratios.append(
                [
                    f"single start: {peer} / jaxreg (prebuilt grid)",
                    f"{peers[peer] / t_prebuilt:.2f}x",
                ]
            )
        if f"{peer} loop" in peers:
            ratios.append(
                [
                    f"{args.starts} starts: {peer} loop / jaxreg multistart",
                    f"{peers[peer + ' loop'] / t_multi:.2f}x",
                ]
            )
    if ratios:
        print_table("Speed-up of jaxreg (higher is faster)", ["comparison", "ratio"], ratios)
    del t_build


if __name__ == "__main__":
    main()
