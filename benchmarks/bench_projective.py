"""Projective association against the neighbour grid and Open3D: a model registered into a
real depth frame from a start a few millimetres off (a tracking step), in one run.

Usage: python benchmarks/bench_projective.py [--data PATH] [--starts 3] [--no-open3d]

Frames: every YCB-Video frame ``jaxreg.io.read_ycbv(PATH)`` reads (default the shipped ones,
Asus Xtion, 640 x 480), every annotated object. Each start is the dataset's pose moved by
5 mm and 3 degrees in a random direction (seeded). The source is the model's points facing
the camera at the start (their outward normals from ``estimate_normals``), the target the
frame's points in the camera frame with ``organized_normals``; point-to-plane, 15 mm pairs,
at most 30 iterations, trimmed to the best 80% of the pairs.

* jaxreg projective: ``icp(..., association=ProjectiveAssociation(intrinsics))`` on the whole
  ``(480, 640, 3)`` image (no crop, no grid).
* jaxreg grid: ``icp`` on the frame's points within the model's radius plus 5 cm of the start's
  model centre (the grid built in the call).
* Open3D: ``registration_icp`` point-to-plane on the same crop and normals.

ADD-S against the dataset's pose (good to a few millimetres itself) says whether each landed;
the last line gives the projective answer's ADD-S from the grid's. Times are medians over the
starts of every instance, each call warm (a first call on the same arrays before it), the
contenders interleaved start by start.
"""

from __future__ import annotations

import argparse
import platform
import time
from functools import partial
from pathlib import Path

import jax
import numpy as np
from _timing import DATA, print_table
from bench_real import diameter, open3d_unless

import jaxreg as jr
from jaxreg.geometry.lie import se3_exp

DISTANCE, ITERATIONS, TRIM = 0.015, 30, 0.8
STEP_M, STEP_DEG = 0.005, 3.0
REACH = 0.05


def outward_normals(points: np.ndarray) -> np.ndarray:
    """Unit normals ``(M, 3)`` of model points, turned away from their centroid (those
    ``estimate_normals`` turns toward it, negated)."""
    return -np.asarray(jr.estimate_normals(points, k=20, viewpoint=points.mean(0)))


def start_pose(truth: jr.SE3, rng) -> jr.SE3:
    """``truth`` moved by ``STEP_M`` and ``STEP_DEG`` along random directions."""
    v, w = rng.normal(size=3), rng.normal(size=3)
    tangent = np.concatenate(
        [STEP_M * v / np.linalg.norm(v), np.radians(STEP_DEG) * w / np.linalg.norm(w)]
    )
    return truth @ se3_exp(np.asarray(tangent, np.float32))


def timed(fn):
    start = time.perf_counter()
    pose = fn()
    return np.asarray(pose), (time.perf_counter() - start) * 1e3


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA / "ycbv")
    parser.add_argument("--starts", type=int, default=3, help="starts per instance")
    parser.add_argument("--no-open3d", action="store_true")
    args = parser.parse_args()
    if not args.data.exists():
        raise SystemExit(f"no YCB-Video frames at {args.data}: pass --data or set JAXREG_DATA")
    o3d = open3d_unless(args.no_open3d)
    rng = np.random.default_rng(0)
    rows = {"jaxreg projective": [], "jaxreg grid": [], "Open3D": []}
    apart = []
    print(f"{platform.machine()}, {jax.default_backend()}, jax {jax.__version__}")
    for frame_record in jr.io.read_ycbv(args.data):
        frame = frame_record.frame
        image = np.asarray(frame.camera_points(), np.float32)
        normals = np.asarray(jr.organized_normals(image), np.float32)
        flat, flat_normals = image.reshape(-1, 3), normals.reshape(-1, 3)
        finite = np.isfinite(flat[:, 0]) & (np.linalg.norm(flat_normals, axis=1) > 0.5)
        association = jr.ProjectiveAssociation(frame.intrinsics)
        for instance in frame_record.instances:
            points = np.asarray(instance.model_points, np.float32)
            model_normals = outward_normals(points)
            size, centre = diameter(points), points.mean(0)
            radius = float(np.linalg.norm(points - centre, axis=1).max())
            for _ in range(args.starts):
                start = start_pose(instance.truth, rng)
                matrix = np.asarray(start.as_matrix(), np.float64)
                eye = -matrix[:3, :3].T @ matrix[:3, 3]  # the camera in object coordinates
                facing = np.einsum("ij,ij->i", model_normals, eye - points) > 0
                source = points[facing]
                here = matrix[:3, :3] @ centre + matrix[:3, 3]
                near = finite & (np.linalg.norm(flat - here, axis=1) < radius + REACH)
                cropped = (flat[near], flat_normals[near])
                contenders = {
                    "jaxreg projective": partial(
                        jaxreg_icp, source, (image, normals), start, association
                    ),
                    "jaxreg grid": partial(jaxreg_icp, source, cropped, start, None),
                }
                if o3d is not None:
                    contenders["Open3D"] = partial(open3d_icp, o3d, source, cropped, matrix)
                for fn in contenders.values():
                    fn()  # compiles for a new size; the timed call below is warm
                answers = {}
                for name, fn in contenders.items():
                    pose, ms = timed(fn)
                    adds = float(jr.add_s(points, jr.SE3.from_matrix(pose), instance.truth))
                    rows[name].append((adds * 1e3, adds < 0.1 * size, ms))
                    answers[name] = pose
                apart.append(
                    1e3 * float(jr.add_s(
                        points, jr.SE3.from_matrix(answers["jaxreg projective"]),
                        jr.SE3.from_matrix(answers["jaxreg grid"]),
                    ))
                )  # fmt: skip
    summary = []
    for name, values in rows.items():
        if not values:
            continue
        adds, landed, ms = (np.asarray(column) for column in zip(*values, strict=True))
        summary.append([
            name, len(values), f"{np.median(adds):.2f}", f"{landed.mean():.0%}",
            f"{np.median(ms):.1f}",
        ])  # fmt: skip
    print_table(
        f"Model into a real frame from {STEP_M * 1e3:g} mm / {STEP_DEG:g} deg off "
        f"({len(apart)} starts)",
        ["method", "starts", "median ADD-S mm", "within 10% of the diameter", "median ms"],
        summary,
    )
    medians = {row[0]: float(row[4]) for row in summary}
    speed = medians["jaxreg projective"]
    ratios = [["projective vs grid", f"{medians['jaxreg grid'] / speed:.2f}x"]]
    if "Open3D" in medians:
        ratios.append(
            ["projective vs Open3D", f"{medians['Open3D'] / speed:.2f}x"]
        )
    print_table("Speed-up of projective association (higher is faster)", ["comparison", "ratio"],
                ratios)  # fmt: skip
    print(
        f"\nprojective answer from the grid's: median ADD-S {np.median(apart):.2f} mm, "
        f"largest {np.max(apart):.2f} mm"
    )


def jaxreg_icp(source, target, start, association) -> np.ndarray:
    """jaxreg's point-to-plane ICP of ``source`` into ``target`` ``(points, normals)`` from
    ``start`` (``SE3``): the pose ``(4, 4)``, projective when ``association`` is given."""
    points, normals = target
    result = jr.icp(
        source, points, start, method="point_to_plane", target_normals=normals,
        max_correspondence_distance=DISTANCE, max_iterations=ITERATIONS, trim_fraction=TRIM,
        association=association,
    )  # fmt: skip
    return jax.block_until_ready(result.pose.as_matrix())


def open3d_icp(o3d, source, target, start: np.ndarray) -> np.ndarray:
    """Open3D's point-to-plane ICP of ``source`` into ``target`` ``(points, normals)`` from
    ``start`` (4, 4), the same distance and iteration bound (Open3D does not trim)."""
    points, normals = target
    reg = o3d.pipelines.registration
    moving = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source.astype(np.float64)))
    fixed = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    fixed.normals = o3d.utility.Vector3dVector(normals.astype(np.float64))
    fit = reg.registration_icp(
        moving, fixed, DISTANCE, start, reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(max_iteration=ITERATIONS),
    )  # fmt: skip
    return np.asarray(fit.transformation)


if __name__ == "__main__":
    main()
