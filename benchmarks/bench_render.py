"""Synthetic RGB-D tabletop scenes (jaxreg.synth) at 848x480 on the CPU.

Usage: python benchmarks/bench_render.py [--seeds 7] [--repeats 3] [--object mug]

Tables:

1. ``tabletop_scene`` end to end (meshes, ray cast, sensor noise, shading, the JAX frame and the
   model's surface samples), ``noise=False`` and ``noise=True`` timed in alternation: for each
   seed the median of ``--repeats`` calls, then the median and the range of those over the
   seeds. One untimed call first pays for imports and JAX's first dispatches.
2. The stages of one noisy scene (table, target, two boxes; camera 0.6 m away, 50 degrees up):
   the raw ray cast of the 407,040 pixel rays (Embree through embreex, scene build included and
   alone), ``render`` (the cast plus float64 depth on the hit faces, labels, normals, albedo),
   ``StereoSensor.measure`` (the noise model, including the second cast from the right imager)
   and ``Rendering.shade``; Open3D's ``RaycastingScene.cast_rays`` on the same triangles and
   rays as the peer when open3d imports. All interleaved, medians of ``--repeats`` rounds.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np
import trimesh
from _timing import interleaved_medians, print_table
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from jaxreg import synth


def scene_times(seeds: int, repeats: int, name: str) -> list[list[str]]:
    synth.tabletop_scene(0, object=name)  # imports, first JAX dispatches
    per_seed: dict[str, list[float]] = {"noise=False": [], "noise=True": []}
    for seed in range(seeds):
        times = interleaved_medians(
            {
                "noise=False": lambda s=seed: synth.tabletop_scene(s, object=name, noise=False),
                "noise=True": lambda s=seed: synth.tabletop_scene(s, object=name, noise=True),
            },
            repeats=repeats,
            warmup=0,
        )
        for key, value in times.items():
            per_seed[key].append(value)
    return [
        [
            f"tabletop_scene({name}, {key})",
            f"{1e3 * statistics.median(values):.0f}",
            f"{1e3 * min(values):.0f}-{1e3 * max(values):.0f}",
        ]
        for key, values in per_seed.items()
    ]


def stage_scene(name: str):
    model, _ = synth.object_mesh(name)
    table = trimesh.creation.box((1.2, 0.8, 0.04)).apply_translation((0, 0, -0.02))
    target = model.copy().apply_translation((0, 0, model.bounds[1, 2]))
    boxes = [
        trimesh.creation.box((0.08, 0.06, 0.1)).apply_translation((x, y, 0.05))
        for x, y in ((-0.15, 0.12), (-0.1, -0.18))
    ]
    elevation, azimuth = np.radians(50.0), np.radians(20.0)
    eye = 0.6 * np.array(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ]
    )
    pose = synth.look_at(eye + (0, 0, 0.05), (0, 0, 0.05))
    return [table, target, *boxes], pose


def stage_times(name: str, repeats: int) -> list[list[str]]:
    meshes, pose = stage_scene(name)
    sensor = synth.StereoSensor.d435()
    intrinsics = sensor.intrinsics()
    colors = np.array([[0.5, 0.4, 0.3], [0.8, 0.2, 0.2], [0.3, 0.6, 0.3], [0.2, 0.3, 0.7]])
    merged = trimesh.util.concatenate(meshes)
    vertices, faces = merged.vertices.astype(np.float32), merged.faces.astype(np.int32)
    rays = np.asarray(intrinsics.pixel_rays(), np.float64).reshape(-1, 3) @ pose[:3, :3].T
    directions = (rays / np.linalg.norm(rays, axis=1, keepdims=True)).astype(np.float32)
    origins = np.broadcast_to(pose[:3, 3].astype(np.float32), directions.shape).copy()

    def embree_scene():
        scene = rtcore_scene.EmbreeScene()
        TriangleMesh(scene=scene, vertices=vertices, indices=faces)
        return scene

    built = embree_scene()
    rendering = synth.render(meshes, intrinsics, pose, colors)
    rng = np.random.default_rng(0)
    fns = {
        "embree scene build": embree_scene,
        "embree cast (407k rays)": lambda: built.run(origins, directions),
        "render (build + cast + depth, labels, normals)": lambda: synth.render(
            meshes, intrinsics, pose, colors
        ),
        "StereoSensor.measure (noise, right-imager cast)": lambda: sensor.measure(rendering, rng),
        "Rendering.shade": rendering.shade,
    }
    hits = built.run(origins, directions) >= 0
    peer_note = "open3d not installed"
    try:
        import open3d as o3d

        o3d_scene = o3d.t.geometry.RaycastingScene()
        o3d_scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(faces.astype(np.uint32)))
        o3d_rays = o3d.core.Tensor(np.hstack([origins, directions]))
        o3d_scene.cast_rays(o3d_rays)  # builds its BVH on first use
        fns["open3d RaycastingScene.cast_rays (peer)"] = lambda: o3d_scene.cast_rays(o3d_rays)
        theirs = o3d_scene.cast_rays(o3d_rays)["primitive_ids"].numpy()
        agree = np.mean((theirs != o3d_scene.INVALID_ID) == hits)
        peer_note = f"open3d {o3d.__version__}: hit/miss agrees on {100 * agree:.3f}% of rays"
    except ImportError:
        pass
    times = interleaved_medians(fns, repeats=repeats)
    rows = [[stage, f"{1e3 * seconds:.1f}"] for stage, seconds in times.items()]
    return rows, f"{len(faces)} triangles, {hits.mean():.0%} of rays hit; {peer_note}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=7)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--object", default="mug", choices=synth.OBJECTS)
    args = parser.parse_args()
    print(
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"load average {os.getloadavg()[0]:.1f} at start; 848x480 (D435 default)"
    )
    start = time.perf_counter()
    print_table(
        f"tabletop_scene, ms: median over {args.seeds} seeds of per-seed medians of {args.repeats}",
        ["call", "median ms", "range ms"],
        scene_times(args.seeds, args.repeats, args.object),
    )
    rows, note = stage_times(args.object, max(args.repeats, 5))
    print_table(f"stages of one noisy scene, ms ({note})", ["stage", "median ms"], rows)
    print(f"\n(total {time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
