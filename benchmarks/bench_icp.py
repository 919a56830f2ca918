"""ICP latency and multi-start throughput against Open3D and small_gicp, in one run.

Usage: python benchmarks/bench_icp.py [--data DIR] [--starts 64] [--iterations 40]

Clouds: PCL's milk.pcd (a real Kinect scan of a milk carton) voxel-downsampled to 4 mm
(~3.7k points) is the source; the target is the same cloud moved by a known pose with
1 mm noise. Every solver runs point-to-point ICP with a 2 cm correspondence distance and
exactly ``--iterations`` iterations (convergence thresholds set to zero), from the same
starts. Times are medians over repeats after a warm-up call; jaxreg's compile time is
reported separately. The multi-start rows time ``--starts`` starts spread within 30 degrees
of the identity: jaxreg runs them in one vmapped call (its grid build included), the peers in
a Python loop. Contenders are timed in interleaved rounds (each round calls every one once),
so that a shared machine's load falls on all of them alike.
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
from _timing import DATA, interleaved_medians, print_table

import jaxreg as jr
from jaxreg.search.neighbors import build_grid

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
    parser.add_argument("--data", type=Path, default=DATA)
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

    single = {}  # name -> callable, timed interleaved with its peers
    multi = {}
    compile_s = {}

    def compiled(name, fn):
        start = time.perf_counter()
        fn()
        compile_s[name] = time.perf_counter() - start
        return fn

    grid = build_grid(scene, dist)
    single["jaxreg icp (builds its grid)"] = compiled(
        "jaxreg icp (builds its grid)",
        lambda: jax.block_until_ready(jr.icp(model, scene, **options)),
    )
    single["jaxreg icp (prebuilt grid)"] = lambda: jax.block_until_ready(
        jr.icp(model, scene, neighbors=grid, **options)
    )
    single["  grid build alone (host)"] = lambda: build_grid(scene, dist)
    multi_name = f"jaxreg multistart_icp x{args.starts} (one call)"
    multi[multi_name] = compiled(
        multi_name, lambda: jax.block_until_ready(jr.multistart_icp(model, scene, inits, **options))
    )

    peers = []
    try:
        import open3d as o3d

        reg = o3d.pipelines.registration
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.astype(np.float64)))
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scene.astype(np.float64)))
        crit = reg.ICPConvergenceCriteria(0.0, 0.0, iters)
        est = reg.TransformationEstimationPointToPoint()

        def o3d_one(init=IDENTITY):
            return reg.registration_icp(src, tgt, dist, init, est, crit)

        single["Open3D registration_icp"] = o3d_one
        multi[f"Open3D loop x{args.starts}"] = lambda: [o3d_one(m) for m in init_mats]
        peers.append(("Open3D registration_icp", f"Open3D loop x{args.starts}"))
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

        single["small_gicp ICP (prebuilt tree, 1 thread)"] = sg_one
        multi[f"small_gicp loop x{args.starts}"] = lambda: [sg_one(m) for m in init_mats]
        peers.append(
            ("small_gicp ICP (prebuilt tree, 1 thread)", f"small_gicp loop x{args.starts}")
        )
    except ImportError as err:
        print(f"small_gicp unavailable ({err}): its rows are skipped")

    t = interleaved_medians(single, args.repeats) | interleaved_medians(
        multi, max(3, args.repeats // 2)
    )
    rows = []
    for name, seconds in t.items():
        per_start = f"{seconds / args.starts * 1e3:.2f}" if name in multi else ""
        compile_col = f"{compile_s[name]:.1f}" if name in compile_s else ""
        rows.append([name, f"{seconds * 1e3:.1f}", per_start, compile_col])
    device = jax.devices()[0]
    print_table(
        f"ICP point-to-point, milk.pcd @ 4 mm ({len(model)} -> {len(scene)} points), {iters} "
        f"iterations; jax {jax.__version__} on {device.platform} ({device.device_kind}), "
        f"{os.cpu_count()} cores, {platform.machine()}; medians of interleaved rounds",
        ["solver", "median ms", "ms per start", "compile s"],
        rows,
    )
    ratios = []
    for one, loop in peers:
        peer = one.split()[0]
        for mode in ("builds its grid", "prebuilt grid"):
            ratio = t[one] / t[f"jaxreg icp ({mode})"]
            ratios.append([f"single start: {peer} / jaxreg ({mode})", f"{ratio:.2f}x"])
        ratios.append(
            [
                f"{args.starts} starts: {peer} loop / jaxreg multistart",
                f"{t[loop] / t[multi_name]:.2f}x",
            ]
        )
    if ratios:
        print_table("Speed-up of jaxreg (higher is faster)", ["comparison", "ratio"], ratios)


if __name__ == "__main__":
    main()
