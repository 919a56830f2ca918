"""Global registration, FPFH and RANSAC, against Open3D on the real Kinect scene, in one run.

Usage: python benchmarks/bench_global.py [--data DIR] [--voxel 0.005] [--repeats 5]

Clouds: PCL's milk.pcd (the carton cut from the capture) handed over in an arbitrary pose is
the source; the whole milk_cartoon_all_small_clorox.pcd Kinect capture is the target. Both
are voxel-downsampled (``--voxel``), and both libraries get the same points and normals
(Open3D's, KNN 30). FPFH: radius 5 voxels, 100 neighbours, both clouds. RANSAC: mutual
matching, edge-length 0.9 and distance checks, 1.5 voxels, confidence 0.999, at most 100,000
hypotheses; its time includes the descriptor matching, as Open3D's does. Contenders are
timed in interleaved rounds (medians); jaxreg's compile is its first call, reported apart.
The pose error of each RANSAC result against the known pose is printed too (an initialiser:
centimetres are expected before ICP).
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

from jaxreg.geometry.metrics import pose_error
from jaxreg.io import load_points
from jaxreg.registration.ransac import ransac_registration
from jaxreg.search.features import fpfh
from jaxreg.search.neighbors import voxel_downsample

HANDED = (1.0, -2.0, 0.5), (0.3, -0.2, 0.5)  # roll-pitch-yaw (rad), offset (m) of the model


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--voxel", type=float, default=0.005)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    pcl = args.data / "pcl"
    if not (pcl / "milk_cartoon_all_small_clorox.pcd").is_file():
        raise SystemExit(f"the Kinect scene is not under {pcl}: pass --data or set JAXREG_DATA")
    import open3d as o3d
    from jaxlie import SE3, SO3

    reg = o3d.pipelines.registration
    voxel = args.voxel
    handed = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(*HANDED[0]), jnp.array(HANDED[1])
    )
    truth = handed.inverse()
    model = np.asarray(handed.apply(jnp.asarray(load_points(pcl / "milk.pcd"))))
    scene = load_points(pcl / "milk_cartoon_all_small_clorox.pcd")
    points = [voxel_downsample(c, voxel).astype(np.float64) for c in (model, scene)]
    clouds = [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)) for p in points]
    for cloud in clouds:
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(30))
    normals = [np.asarray(c.normals) for c in clouds]
    f32 = [p.astype(np.float32) for p in points]
    n32 = [n.astype(np.float32) for n in normals]
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
    distance = 1.5 * voxel

    def ours_fpfh():
        features = [fpfh(p, n, radius=5 * voxel).histograms for p, n in zip(f32, n32, strict=True)]
        return jax.block_until_ready(features)

    def o3d_fpfh():
        return [reg.compute_fpfh_feature(c, search) for c in clouds]

    ours_features, o3d_features = ours_fpfh(), o3d_fpfh()

    def ours_ransac(seed=0):
        result = ransac_registration(
            *f32, *ours_features, max_correspondence_distance=distance,
            key=jax.random.PRNGKey(seed),
        )  # fmt: skip
        return jax.block_until_ready(result)

    checkers = [
        reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
        reg.CorrespondenceCheckerBasedOnDistance(distance),
    ]

    def o3d_ransac():
        return reg.registration_ransac_based_on_feature_matching(
            *clouds, *o3d_features, True, distance, reg.TransformationEstimationPointToPoint(False),
            3, checkers, reg.RANSACConvergenceCriteria(100_000, 0.999),
        )  # fmt: skip

    start = time.perf_counter()
    ours = ours_ransac()
    compile_s = time.perf_counter() - start
    theirs = o3d_ransac()
    times = interleaved_medians(
        {"fpfh jaxreg": ours_fpfh, "fpfh open3d": o3d_fpfh,
         "ransac jaxreg": ours_ransac, "ransac open3d": o3d_ransac},
        repeats=args.repeats,
    )  # fmt: skip

    def errors(pose):
        t, r = pose_error(pose, truth)
        return f"{float(t) * 1e3:.1f} mm", f"{np.degrees(float(r)):.2f} deg"

    theirs_pose = SE3.from_matrix(jnp.asarray(theirs.transformation, jnp.float32))
    print(
        f"source {len(points[0])} points, target {len(points[1])} points (voxel {voxel} m); "
        f"{os.cpu_count()} cores, {platform.machine()}, jax {jax.__version__} "
        f"{jax.devices()[0].platform}, open3d {o3d.__version__}; medians of {args.repeats} "
        f"interleaved rounds; jaxreg RANSAC first call (compile) {compile_s:.2f} s"
    )
    print_table(
        "FPFH (both clouds) and RANSAC (matching included)",
        ["stage", "jaxreg s", "open3d s", "open3d / jaxreg"],
        [
            [stage, f"{times[stage + ' jaxreg']:.3f}", f"{times[stage + ' open3d']:.3f}",
             f"{times[stage + ' open3d'] / times[stage + ' jaxreg']:.2f}"]
            for stage in ("fpfh", "ransac")
        ],
    )  # fmt: skip
    print_table(
        "RANSAC result against the known pose",
        ["library", "translation", "rotation", "hypotheses", "status"],
        [
            ["jaxreg", *errors(ours.pose), int(ours.iterations), ours.status_message()[:40]],
            ["open3d", *errors(theirs_pose), "n/a", f"fitness {theirs.fitness:.2f}"],
        ],
    )


if __name__ == "__main__":
    main()
