"""Every YCB-Video object on a synthetic table: the shapes the shipped real frames do not hold
(a banana, scissors, clamps, a bowl, a drill, a marker, ...), posed from PoseCNN's point model
with a segmenter's mask that bleeds onto the background.

Usage: python benchmarks/bench_shapes.py [--data PATH] [--seeds A B] [--grow PIXELS]

Scenes: each of the 21 point models (``jaxreg.io.read_ycbv_models``, ``$JAXREG_DATA/ycbv/models``
by default) is given a surface by Open3D's Poisson reconstruction (depth 8, normals from 20
neighbours oriented consistently and outward, the 3% least supported vertices dropped) and
stood on the largest face of its convex hull; ``jaxreg.synth.tabletop_scene(seed, mesh=...)``
renders it 0.5-1.1 m from a RealSense D435 (its noise, 848x480) with two distractors. The
rendered surface is not the model (the reconstruction smooths edges and may close openings: a
mug's or a bowl's), as a real object is not its scan.

jaxreg: ``estimate_pose(frame, points, mask=grown, depth_noise=noise)``, the model the 2,620
points and ``grown`` the true mask dilated by ``--grow`` pixels (background and table at its
edges). Scores as ``bench_real.py``'s: posed means found with ADD-S < 10% of the diameter, a
wrong success found with more; the box centre's error against the reported 95% region (no
allowance: the synthetic truth is exact, but the surface is the reconstruction's).
Seeds ``--seeds A B`` (default 100 103; nothing was tuned on seeds from 100).
"""

from __future__ import annotations

import argparse
import collections
import time
from pathlib import Path

import numpy as np
import trimesh
from _timing import DATA, print_table
from bench_real import centre_coverage, centre_error, diameter, open3d_unless, reason_group
from scipy import ndimage

import jaxreg as jr
from jaxreg.synth import StereoSensor, tabletop_scene


def surface(o3d, points: np.ndarray) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A mesh through ``points`` ``(M, 3)`` (metres) by Poisson reconstruction (see the
    module docstring), turned to rest on its convex hull's largest face (z up), and that
    turn ``(3, 3)``."""
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    cloud.orient_normals_consistent_tangent_plane(15)
    normals = np.asarray(cloud.normals)
    if np.mean(np.sum((points - points.mean(0)) * normals, axis=1)) < 0:
        cloud.normals = o3d.utility.Vector3dVector(-normals)
    mesh, support = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(cloud, depth=8)
    support = np.asarray(support)
    mesh.remove_vertices_by_mask(support < np.quantile(support, 0.03))
    out = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.triangles))
    hull = trimesh.convex.convex_hull(points)
    down = hull.facets_normal[int(np.argmax(hull.facets_area))]
    turn = trimesh.geometry.align_vectors(down, [0.0, 0.0, -1.0])
    return out.apply_transform(turn), turn[:3, :3]


def run(name, mesh, model, seed, grow, sensor) -> dict:
    """One scene of ``mesh`` with the model ``model`` ``(M, 3)`` in the mesh's frame."""
    scene = tabletop_scene(seed, mesh=mesh, distance=(0.5, 1.1), sensor=sensor)
    noise = sensor.depth_noise(scene.frame.intrinsics)
    grown = ndimage.binary_dilation(scene.mask, iterations=grow) if grow else scene.mask
    start = time.perf_counter()
    est = jr.estimate_pose(scene.frame, model, mask=grown, depth_noise=noise)
    row = {"object": name, "seed": seed, "ms": (time.perf_counter() - start) * 1e3}
    if not est.success:
        return row | {"outcome": "refused", "reason": est.reason}
    width = diameter(model)
    adds = float(jr.add_s(model, est.pose, scene.truth))
    found, truth = (np.asarray(p.as_matrix(), np.float64) for p in (est.pose, scene.truth))
    centre = 0.5 * (model.min(0) + model.max(0)).astype(np.float64)
    error = centre_error(found, truth, centre)
    _, inside, _ = centre_coverage(error, found[:3, :3], np.asarray(est.covariance), centre)
    return row | {
        "outcome": "posed" if adds < 0.1 * width else "wrong",
        "adds_mm": adds * 1e3,
        "centre_mm": float(np.linalg.norm(error)) * 1e3,
        "inside": inside,
        "equivalent": len(est.equivalent_poses),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA / "ycbv" / "models")
    parser.add_argument("--seeds", type=int, nargs=2, default=(100, 103), metavar=("A", "B"))
    parser.add_argument("--grow", type=int, default=3, help="mask dilation (pixels)")
    args = parser.parse_args()
    if not args.data.exists():
        raise SystemExit(f"no YCB-Video models at {args.data}: pass --data or set JAXREG_DATA")
    o3d = open3d_unless(False)
    if o3d is None:
        raise SystemExit("the scenes' surfaces need Open3D (Poisson reconstruction)")
    sensor = StereoSensor.d435()
    rows = []
    for name, points in jr.io.read_ycbv_models(args.data).items():
        mesh, turn = surface(o3d, points)
        model = (points @ turn.T).astype(np.float32)
        for seed in range(*args.seeds):
            rows.append(run(name, mesh, model, seed, args.grow, sensor))
            r = rows[-1]
            print(name, seed, r["outcome"], f"{r.get('adds_mm', float('nan')):.1f} mm",
                  r.get("reason", ""), flush=True)  # fmt: skip
    table = []
    for name in dict.fromkeys(r["object"] for r in rows):
        mine = [r for r in rows if r["object"] == name]
        table.append(_summary(name, mine))
    table.append(_summary("all", rows))
    print_table(
        f"YCB-Video's 21 objects on a synthetic table, seeds {args.seeds[0]}-{args.seeds[1] - 1}, "
        f"masks grown by {args.grow} px (posed: ADD-S < 10% of the diameter)",
        ["object", "scenes", "posed", "wrong", "refused", "centre inside 95%", "median ms"],
        table,
    )
    refusals = collections.Counter(reason_group(r["reason"]) for r in rows if "reason" in r)
    print_table("Refusals by reason", ["reason", "count"], [[k, v] for k, v in refusals.items()])


def _summary(name: str, rows: list[dict]) -> list[object]:
    posed = [r for r in rows if r["outcome"] == "posed"]
    inside = sum(r["inside"] for r in posed)
    return [
        name, len(rows), len(posed), sum(r["outcome"] == "wrong" for r in rows),
        sum(r["outcome"] == "refused" for r in rows),
        f"{inside}/{len(posed)}" if posed else "-", f"{np.median([r['ms'] for r in rows]):.0f}",
    ]  # fmt: skip


if __name__ == "__main__":
    main()
