"""Pixels to pose with the caller's own mask: ``estimate_pose(frame, model, mask=...)`` on
synthetic tabletop frames of every object, with the true instance mask and with masks on the
wrong object.

Usage: python benchmarks/bench_mask.py [--seeds 12] [--first-seed 200] [--table]

Frames: ``jaxreg.synth.tabletop_scene(seed, object=name)`` for every object and seeds
``first_seed .. first_seed + seeds - 1`` (two distractors; a RealSense D435's depth noise at
848x480); the model is 20,000 points sampled on the object's mesh, one sample per object.

* **true mask**: ``scene.mask`` (the pixels where the target is the first surface hit). Found
  is ADD-S < 5 mm (symmetry-aware); with ``--table``, a row of the same frames without a
  mask (the table route).
* **wrong mask**: each distractor's pixels (``scene.labels == 2, 3``) and the next object's
  true mask from the same seed's scene of that object (every scene centres its target, so
  that mask mostly overlaps this frame's target). Each is refused (no pose), or a pose is
  claimed: right (ADD-S < 5 mm: the mask covered enough of the target) or wrong (a confident
  wrong pose).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import trimesh
from _timing import print_table

from jaxreg.geometry.metrics import add_s
from jaxreg.pipeline import estimate_pose
from jaxreg.synth import OBJECTS, StereoSensor, tabletop_scene


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=12)
    parser.add_argument("--first-seed", type=int, default=200)
    parser.add_argument("--table", action="store_true", help="also run the table route")
    args = parser.parse_args()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    routes = ("mask", "table") if args.table else ("mask",)
    rows, wrong_rows = [], []
    for k, name in enumerate(OBJECTS):
        other = OBJECTS[(k + 1) % len(OBJECTS)]
        model = None
        errors = {"mask": [], "table": []}
        times, outcomes = [], {"refused": 0, "right": 0, "wrong": 0}
        for seed in seeds:
            scene = tabletop_scene(seed, object=name)
            if model is None:
                samples, _ = trimesh.sample.sample_surface(scene.model, 20_000, seed=k)
                model = samples.astype(np.float32)
            noise = StereoSensor.d435().depth_noise(scene.frame.intrinsics)
            options = {"symmetry": scene.symmetry, "depth_noise": noise}
            for route in routes:
                mask = scene.mask if route == "mask" else None
                start = time.perf_counter()
                est = estimate_pose(scene.frame, model, mask=mask, **options)
                if route == "mask":
                    times.append(time.perf_counter() - start)
                found = est.pose is not None
                error = float(add_s(scene.model_points, est.pose, scene.truth)) if found else np.inf
                errors[route].append(error)
            wrong = [scene.labels == 2, scene.labels == 3, tabletop_scene(seed, object=other).mask]
            for mask in wrong:
                if not mask.any():
                    continue
                est = estimate_pose(scene.frame, model, mask=mask, **options)
                if est.pose is None:
                    outcomes["refused"] += 1
                else:
                    right = float(add_s(scene.model_points, est.pose, scene.truth)) < 0.005
                    outcomes["right" if right else "wrong"] += 1
        for route in routes:
            e = np.asarray(errors[route]) * 1e3
            ms = statistics.median(times[1:] or times) * 1e3 if route == "mask" else None
            rows.append(
                [name, route, f"{np.mean(e < 5):.0%}", f"{np.median(e):.2f}",
                 f"{np.max(e):.2f}" if np.isfinite(e).all() else "no pose",
                 "" if ms is None else f"{ms:.0f}"]
            )  # fmt: skip
        wrong_rows.append([name, *map(str, outcomes.values())])
    print_table(
        f"true masks, seeds {seeds.start}-{seeds.stop - 1} (ADD-S mm)",
        ["object", "route", "found < 5 mm", "median", "worst", "median ms (mask)"],
        rows,
    )
    print_table(
        "masks on the wrong object (two distractors, another object's mask)",
        ["object", "refused", "right pose claimed", "wrong pose claimed"],
        wrong_rows,
    )


if __name__ == "__main__":
    main()
