"""Pixels to pose with the caller's own mask: ``estimate_pose(frame, model, mask=...)`` on
synthetic tabletop frames of every object, with the true instance mask and with masks on the
wrong object.

Usage: python benchmarks/bench_mask.py [--seeds 12] [--first-seed 200]

Frames: ``jaxreg.synth.tabletop_scene(seed, object=name)`` for every object and seeds
``first_seed .. first_seed + seeds - 1`` (two distractors; a RealSense D435's depth noise at
848x480); the model is 20,000 points sampled on the object's mesh, one sample per object.

* **true mask**: ``scene.mask`` (the pixels where the target is the first surface hit). Found
  is ADD-S < 5 mm (symmetry-aware); the table row is the same frames without a mask.
* **wrong mask**: each distractor's pixels (``scene.labels == 2, 3``) and the next object's
  true mask from the same seed's scene of that object. A pose claimed there is a confident
  wrong pose; the table says how many were refused (no pose) and how many claimed.
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
    args = parser.parse_args()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    rows, wrong_rows = [], []
    for k, name in enumerate(OBJECTS):
        other = OBJECTS[(k + 1) % len(OBJECTS)]
        model = None
        errors = {"mask": [], "table": []}
        times, refused, claimed = [], 0, 0
        for seed in seeds:
            scene = tabletop_scene(seed, object=name)
            if model is None:
                samples, _ = trimesh.sample.sample_surface(scene.model, 20_000, seed=k)
                model = samples.astype(np.float32)
            noise = StereoSensor.d435().depth_noise(scene.frame.intrinsics)
            options = {"symmetry": scene.symmetry, "depth_noise": noise}
            for route, mask in (("mask", scene.mask), ("table", None)):
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
                refused += est.pose is None
                claimed += est.pose is not None
        for route in ("mask", "table"):
            e = np.asarray(errors[route]) * 1e3
            rows.append(
                [name, route, f"{np.mean(e < 5):.0%}", f"{np.median(e):.2f}",
                 f"{np.max(e):.2f}" if np.isfinite(e).all() else "no pose"]
            )  # fmt: skip
        rows[-2].append(f"{statistics.median(times[1:] or times) * 1e3:.0f}")
        rows[-1].append("")
        wrong_rows.append([name, str(refused), str(claimed)])
    print_table(
        f"true masks, seeds {seeds.start}-{seeds.stop - 1} (ADD-S mm)",
        ["object", "route", "found < 5 mm", "median", "worst", "median ms (mask)"],
        rows,
    )
    print_table(
        "masks on the wrong object (two distractors, another object's mask)",
        ["object", "refused", "pose claimed"],
        wrong_rows,
    )


if __name__ == "__main__":
    main()
