"""Do the error bars cover the real error? ``jaxreg.studies.calibration_study`` on synthetic
tabletop frames that nothing in the project tunes on (seeds 5000 onward, every object).

Usage: python benchmarks/bench_calibration.py [--seeds 30] [--first 5000]

Each frame: ``tabletop_scene(seed, object=...)`` with a RealSense D435's depth noise at
848x480, ``estimate_pose`` with the sensor's noise model and the object's symmetry. The goals
(error-bar issue): the truth inside the 95% region (6-dof and translation) on 85-99% of frames
overall and on most frames of each object; median predicted translation sigma at most 3x the
median actual error; no NaN covariance; the mean predicted grasp chance within 0.1 of the
observed success rate at a 2 mm margin per side over at least 100 frames (the chance is
compared on the frames with a pose).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from _timing import print_table

from jaxreg.studies import calibration_study

SEED0 = 5000


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=30, help="scenes per object")
    parser.add_argument(
        "--first", type=int, default=SEED0, help="the first seed (fresh seeds for a check)"
    )
    args = parser.parse_args()
    start = time.perf_counter()
    first = args.first
    study = calibration_study(seeds=range(first, first + args.seeds))
    seconds = time.perf_counter() - start
    found = study.found()
    print(
        f"\n{len(study.frames)} frames (seeds {first}-{first + args.seeds - 1} x "
        f"{len({f.object for f in study.frames})} objects), {len(found)} poses found, "
        f"{seconds:.0f} s in all"
    )
    print("\nCoverage and sharpness per object\n")
    print(study.table())
    nan = sum(np.any(np.isnan(f.covariance)) for f in found)
    predicted, observed = study.grasp()
    rows = [
        [f"{m * 1e3:.0f}", f"{p:.3f}", f"{o:.3f}", f"{p - o:+.3f}"]
        for m, p, o in zip(study.margins, predicted, observed, strict=True)
    ]
    print_table(
        f"Grasp chance from the budget vs observed success ({len(found)} frames)",
        ["margin mm/side", "mean predicted", "observed", "difference"],
        rows,
    )
    two = int(np.argmin(np.abs(study.margins - 0.002)))
    print_table(
        "Goals",
        ["goal", "measured", "met"],
        [
            ["95% region covers 85-99% (6-dof)", f"{study.coverage(0.95):.1%}",
             0.85 <= study.coverage(0.95) <= 0.99],
            ["95% region covers 85-99% (translation)", f"{study.coverage(0.95, None, True):.1%}",
             0.85 <= study.coverage(0.95, None, True) <= 0.99],
            ["median sigma <= 3x median error", f"{study.sharpness():.2f}x",
             study.sharpness() <= 3],
            ["no NaN covariance", f"{nan} with NaN", nan == 0],
            ["grasp chance within 0.1 at 2 mm", f"{predicted[two] - observed[two]:+.3f}",
             abs(predicted[two] - observed[two]) <= 0.1 and len(study.frames) >= 100],
        ],
    )  # fmt: skip


if __name__ == "__main__":
    main()
