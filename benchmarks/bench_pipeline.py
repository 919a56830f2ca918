"""Pixels to pose on synthetic tabletop frames: jaxreg.estimate_pose beside an Open3D pipeline.

Usage: python benchmarks/bench_pipeline.py [--seeds 50] [--first-seed 0] [--no-open3d]

Frames: ``jaxreg.synth.tabletop_scene(seed, object=OBJECTS[seed % 4])`` for seeds 0..N-1 (box,
mug, cylinder, container in turn; two distractors; a RealSense D435's depth noise at 848x480).
The model is 20,000 points sampled on the object's mesh (one sample per object, as a user
keeps one model per object), the same for both pipelines. Success
is ADD-S < 5 mm against the known pose (ADD-S forgives the objects' symmetries).

* jaxreg: ``estimate_pose`` with its defaults and the D435's depth noise model; each frame is
  run once untimed (a new candidate count may compile) and once timed: the per-stage
  milliseconds are those of the timed run.
* Open3D (0.18+): the classical pipeline with the same thresholds: ``segment_plane`` (8 mm,
  3 points, 1000 iterations), the plane's inliers removed and points within 1 cm of it
  dropped, ``cluster_dbscan`` (eps 1.5 cm, 10 points) on a 4 mm voxel grid, clusters no wider
  than the model, and for each: FPFH (radius 2 cm) + RANSAC (mutual matching, 6 mm, 100k
  iterations, confidence 0.999) of the model to the cluster, point-to-plane ICP (6 mm); the
  cluster with the highest ICP fitness wins. Timed once per frame after a first frame.

The two run interleaved frame by frame, so the machine's load falls on both alike.
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import jax
import numpy as np
import trimesh
from _timing import print_table

from jaxreg.geometry.metrics import add_s
from jaxreg.pipeline import STAGES, estimate_pose
from jaxreg.synth import OBJECTS, StereoSensor, tabletop_scene


def _model(scene, obj: str) -> np.ndarray:
    points, _ = trimesh.sample.sample_surface(scene.model, 20_000, seed=OBJECTS.index(obj))
    return points.astype(np.float32)


def run_jaxreg(scene, model, noise):
    symmetry = scene.symmetry
    estimate_pose(scene.frame, model, symmetry=symmetry, depth_noise=noise)  # untimed
    start = time.perf_counter()
    est = estimate_pose(scene.frame, model, symmetry=symmetry, depth_noise=noise)
    total = (time.perf_counter() - start) * 1e3
    stages = {name: getattr(est.stages.get(name), "ms", None) for name in STAGES}
    return est.pose, total, stages, est.failed_stage


def run_open3d(o3d, scene, model):
    reg = o3d.pipelines.registration
    start = time.perf_counter()
    points = np.asarray(scene.frame.points()).reshape(-1, 3)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[np.isfinite(points[:, 0])]))
    cloud = cloud.voxel_down_sample(0.004)
    plane, inliers = cloud.segment_plane(0.008, 3, 1000)
    rest = cloud.select_by_index(inliers, invert=True)
    xyz = np.asarray(rest.points)
    normal, offset = np.asarray(plane[:3]), plane[3]
    eye = np.asarray(scene.frame.base_T_camera.translation())
    side = np.sign(eye @ normal + offset)
    rest = rest.select_by_index(np.nonzero(side * (xyz @ normal + offset) > 0.01)[0])
    labels = np.asarray(rest.cluster_dbscan(eps=0.015, min_points=10))
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model)).voxel_down_sample(0.004)
    source.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=0.02, max_nn=100)
    source_fpfh = reg.compute_fpfh_feature(source, search)
    radius = np.linalg.norm(np.asarray(source.points) - source.get_center(), axis=1).max()
    best, best_fitness = None, -1.0
    for k in range(labels.max() + 1 if labels.size else 0):
        target = rest.select_by_index(np.nonzero(labels == k)[0])
        pts = np.asarray(target.points)
        if len(pts) < 30 or np.linalg.norm(pts - pts.mean(0), axis=1).max() > radius + 0.02:
            continue
        target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
        target_fpfh = reg.compute_fpfh_feature(target, search)
        coarse = reg.registration_ransac_based_on_feature_matching(
            source, target, source_fpfh, target_fpfh, True, 0.006,
            reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
             reg.CorrespondenceCheckerBasedOnDistance(0.006)],
            reg.RANSACConvergenceCriteria(100_000, 0.999),
        )  # fmt: skip
        fine = reg.registration_icp(
            source, target, 0.006, coarse.transformation, reg.TransformationEstimationPointToPlane()
        )
        if fine.fitness > best_fitness:
            best, best_fitness = fine.transformation, fine.fitness
    return best, (time.perf_counter() - start) * 1e3


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--first-seed", type=int, default=0, help="e.g. 100: a held-out set")
    parser.add_argument("--no-open3d", action="store_true")
    args = parser.parse_args()
    o3d = None
    if not args.no_open3d:
        try:
            import open3d as o3d
        except (ImportError, OSError) as err:
            print(f"Open3D unavailable ({err}): jaxreg only")
    print(f"{platform.processor() or platform.machine()}, {jax.devices()[0].platform}, "
          f"jax {jax.__version__}, {args.seeds} frames")  # fmt: skip
    print("per frame: seed  object  jaxreg ADD-S mm  failed stage  jaxreg ms  Open3D ADD-S mm")
    from jaxlie import SE3

    rows, ours, theirs, stage_ms, totals, o3d_ms, failures = [], [], [], [], [], [], []
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        obj = OBJECTS[seed % len(OBJECTS)]
        scene = tabletop_scene(seed, object=obj)
        model = _model(scene, obj)
        noise = StereoSensor.d435().depth_noise(scene.frame.intrinsics)
        pose, total, stages, failed = run_jaxreg(scene, model, noise)
        err = float(add_s(scene.model_points, pose, scene.truth)) * 1e3 if pose else np.inf
        ours.append(err)
        if seed > args.first_seed:
            totals.append(total)
            stage_ms.append(stages)
        failures.append(failed)
        o3d_err = None
        if o3d is not None:
            matrix, ms = run_open3d(o3d, scene, model)
            if seed > args.first_seed:
                o3d_ms.append(ms)
            o3d_err = np.inf
            if matrix is not None:
                est = SE3.from_matrix(np.asarray(matrix, np.float32))
                o3d_err = float(add_s(scene.model_points, est, scene.truth)) * 1e3
            theirs.append(o3d_err)
        rows.append([seed, obj, f"{err:.2f}", failed or "-", f"{total:.0f}",
                     "" if o3d_err is None else f"{o3d_err:.2f}"])  # fmt: skip
        print("  ".join(str(c) for c in rows[-1]), flush=True)

    def summary(errors):
        errors = np.asarray(errors)
        return (f"{np.mean(errors < 5):.0%}", f"{np.median(errors):.2f}",
                f"{np.mean(errors[np.isfinite(errors)]):.2f}")  # fmt: skip

    table = [["jaxreg", *summary(ours), f"{statistics.median(totals):.0f}"]]
    if theirs:
        table.append(["Open3D", *summary(theirs), f"{statistics.median(o3d_ms):.0f}"])
    print_table(
        "Pose from one frame (ADD-S < 5 mm is a success; ms: median warm per frame)",
        ["pipeline", "success", "median ADD-S mm", "mean finite ADD-S mm", "ms"],
        table,
    )
    per_stage = [
        [name, f"{statistics.median([s[name] for s in stage_ms if s[name] is not None]):.1f}"]
        for name in STAGES
    ]
    print_table("jaxreg per-stage median warm ms", ["stage", "ms"], per_stage)
    failed = {name: failures.count(name) for name in STAGES if failures.count(name)}
    print(f"\njaxreg failed stages: {failed or 'none'}")


if __name__ == "__main__":
    main()
