"""Wrong answers and refusals of ``jaxreg.estimate_pose`` on held-out synthetic frames.

Usage: python benchmarks/bench_silent.py [--seeds 50] [--first 13500] [--distractors 3]
    [--model-points 2048]

Frames: ``tabletop_scene(seed, object=name, distractors=D)`` for every object of
``jaxreg.synth.OBJECTS`` at every seed (a RealSense D435's depth noise at 848x480; the
distractors are boxes, cans and balls: shapes like the targets'). The model is the scene's
``--model-points`` surface samples (2,048; a denser model fits the object more closely, and a
neighbour too), with the object's symmetry and the sensor's noise model. Seeds looked at while
the pipeline's candidate tests were written: 9300-9349 (9309 is a test), 9800-9849, 9900-9949,
10600-10649, 10700-10724, 11000-11049, 11100-11124, 11200-11249 and 11300-11324 (10622, 11204
and 11318 are tests), 11400-11449, 11700-11749, 12000-12029 (the twins' fits, the colour cue's
first look at 12000-12009), 12500-12549 and 13000-13049 (the colour cue's touching neighbours);
the default seeds, 13500 onward, were not looked at before this script's table. A pose reported
as found is right when its ADD-S is at most 10% of the object's diameter, else wrong; every wrong
one and every refusal is listed. Every frame is posed twice: from depth alone, and with the
model's colours (``model_colors``: the target's paint, as a textured model gives it; the
distractors are painted at random, so a look-alike may share the paint). The goals
(silent-answers issue): no wrong pose reported as found, refusals at most 5%.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np
from _timing import print_table

from jaxreg.geometry.metrics import add_s, diameter
from jaxreg.pipeline import estimate_pose
from jaxreg.synth import OBJECTS, StereoSensor, tabletop_scene


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=50, help="scenes per object")
    parser.add_argument("--first", type=int, default=13500, help="the first seed")
    parser.add_argument("--distractors", type=int, default=3)
    parser.add_argument(
        "--model-points", type=int, default=2048, help="surface samples of the model"
    )
    args = parser.parse_args()
    seeds = range(args.first, args.first + args.seeds)
    modes = ("depth only", "with the model's colours")
    counts = {(mode, name): Counter() for mode in modes for name in OBJECTS}
    wrong, refused, times = [], [], []
    for seed in seeds:
        for name in OBJECTS:
            scene = tabletop_scene(
                seed, object=name, distractors=args.distractors, model_points=args.model_points
            )
            noise = StereoSensor.d435().depth_noise(scene.frame.intrinsics)
            for mode, colors in zip(modes, (None, scene.model_colors), strict=True):
                start = time.perf_counter()
                est = estimate_pose(
                    scene.frame, scene.model_points, symmetry=scene.symmetry, depth_noise=noise,
                    model_colors=colors,
                )  # fmt: skip
                times.append(time.perf_counter() - start)
                if not est.success:
                    outcome = "refused"
                    refused.append((mode, seed, name, est.failed_stage, est.reason))
                else:
                    error = float(add_s(scene.model_points, est.pose, scene.truth))
                    size = diameter(scene.model.vertices)
                    outcome = "wrong" if error > 0.1 * size else "right"
                    if outcome == "wrong":
                        wrong.append((mode, seed, name, error, size))
                counts[mode, name][outcome] += 1
    totals = {mode: Counter() for mode in modes}
    rows = []
    for (mode, name), c in counts.items():
        totals[mode].update(c)
        rows.append([mode, name, c["right"], c["wrong"], c["refused"]])
    rows += [[mode, "all", t["right"], t["wrong"], t["refused"]] for mode, t in totals.items()]
    frames = sum(totals[modes[0]].values())
    print_table(
        f"{frames} held-out frames (seeds {seeds[0]}-{seeds[-1]} x {len(OBJECTS)} objects, "
        f"{args.distractors} distractors), each posed from depth alone and with the model's "
        f"colours; median {np.median(times) * 1e3:.0f} ms a pose (the first compiles)",
        ["model", "object", "found, right", "found, wrong", "refused"],
        rows,
    )
    print_table(
        "Wrong poses reported as found (ADD-S > 10% of the diameter)",
        ["model", "seed", "object", "ADD-S mm", "diameter mm"],
        [[m, s, n, f"{e * 1e3:.1f}", f"{d * 1e3:.0f}"] for m, s, n, e, d in wrong]
        or [["none"] * 5],
    )
    print_table(
        "Refusals",
        ["model", "seed", "object", "stage", "reason"],
        [[m, s, n, st, r[:150]] for m, s, n, st, r in refused] or [["none"] * 5],
    )
    goals = []
    for mode, t in totals.items():
        goals += [
            [f"no wrong pose reported as found, {mode}", f"{t['wrong']} wrong", t["wrong"] == 0],
            [f"refusals <= 5%, {mode}", f"{t['refused'] / frames:.1%}",
             t["refused"] <= 0.05 * frames],
        ]  # fmt: skip
    print_table("Goals", ["goal", "measured", "met"], goals)


if __name__ == "__main__":
    main()
