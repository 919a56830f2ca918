"""Wrong answers and refusals of ``jaxreg.estimate_pose`` on held-out synthetic frames.

Usage: python benchmarks/bench_silent.py [--seeds 50] [--first 11400] [--distractors 3]
    [--model-points 2048]

Frames: ``tabletop_scene(seed, object=name, distractors=D)`` for every object of
``jaxreg.synth.OBJECTS`` at every seed (a RealSense D435's depth noise at 848x480; the
distractors are boxes, cans and balls: shapes like the targets'). The model is the scene's
``--model-points`` surface samples (2,048; a denser model fits the object more closely, and a
neighbour too), with the object's symmetry and the sensor's noise model. Seeds looked at while
the pipeline's candidate tests were written: 9300-9349 (9309 is a test), 9800-9849, 9900-9949,
10600-10649, 10700-10724, 11000-11049, 11100-11124, 11200-11249 and 11300-11324 (10622, 11204
and 11318 are tests); seeds 11400 onward were not. A pose reported as found is right when its
ADD-S is at most 10% of the object's diameter, else wrong; every wrong one and every refusal is
listed. The goals (silent-answers issue): no wrong pose reported as found, refusals at most 5%.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter

import numpy as np
from _timing import print_table

from jaxreg.geometry.metrics import add_s
from jaxreg.pipeline import estimate_pose
from jaxreg.synth import OBJECTS, StereoSensor, tabletop_scene


def _diameter(mesh) -> float:
    """The largest distance between two of a mesh's hull vertices (metres)."""
    hull = np.asarray(mesh.convex_hull.vertices)
    return float(np.max(np.linalg.norm(hull[:, None] - hull[None], axis=-1)))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=50, help="scenes per object")
    parser.add_argument("--first", type=int, default=11400, help="the first seed")
    parser.add_argument("--distractors", type=int, default=3)
    parser.add_argument(
        "--model-points", type=int, default=2048, help="surface samples of the model"
    )
    args = parser.parse_args()
    seeds = range(args.first, args.first + args.seeds)
    counts = {name: Counter() for name in OBJECTS}
    wrong, refused, times = [], [], []
    for seed in seeds:
        for name in OBJECTS:
            scene = tabletop_scene(
                seed, object=name, distractors=args.distractors, model_points=args.model_points
            )
            noise = StereoSensor.d435().depth_noise(scene.frame.intrinsics)
            start = time.perf_counter()
            est = estimate_pose(
                scene.frame, scene.model_points, symmetry=scene.symmetry, depth_noise=noise
            )
            times.append(time.perf_counter() - start)
            if not est.success:
                outcome = "refused"
                refused.append((seed, name, est.failed_stage, est.reason))
            else:
                error = float(add_s(scene.model_points, est.pose, scene.truth))
                diameter = _diameter(scene.model)
                outcome = "wrong" if error > 0.1 * diameter else "right"
                if outcome == "wrong":
                    wrong.append((seed, name, error, diameter))
            counts[name][outcome] += 1
            print(f"seed {seed} {name}: {outcome}", file=sys.stderr, flush=True)
    total = Counter()
    for c in counts.values():
        total.update(c)
    frames = sum(total.values())
    rows = [
        [name, c["right"], c["wrong"], c["refused"]] for name, c in counts.items()
    ] + [["all", total["right"], total["wrong"], total["refused"]]]
    print_table(
        f"{frames} held-out frames (seeds {seeds[0]}-{seeds[-1]} x {len(OBJECTS)} objects, "
        f"{args.distractors} distractors); median {np.median(times) * 1e3:.0f} ms a frame "
        "(the first compiles)",
        ["object", "found, right", "found, wrong", "refused"],
        rows,
    )
    print_table(
        "Wrong poses reported as found (ADD-S > 10% of the diameter)",
        ["seed", "object", "ADD-S mm", "diameter mm"],
        [[s, n, f"{e * 1e3:.1f}", f"{d * 1e3:.0f}"] for s, n, e, d in wrong] or [["none"] * 4],
    )
    print_table(
        "Refusals",
        ["seed", "object", "stage", "reason"],
        [[s, n, st, r[:150]] for s, n, st, r in refused] or [["none"] * 4],
    )
    print_table(
        "Goals",
        ["goal", "measured", "met"],
        [
            ["no wrong pose reported as found", f"{total['wrong']} wrong", total["wrong"] == 0],
            ["refusals <= 5%", f"{total['refused'] / frames:.1%}",
             total["refused"] <= 0.05 * frames],
        ],
    )  # fmt: skip


if __name__ == "__main__":
    main()
