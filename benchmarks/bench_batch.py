"""Throughput of many frames: ``jaxreg.estimate_poses`` (one call, frames concurrently, one
per core) against a loop of ``jaxreg.estimate_pose`` over the same frames.

Usage: python benchmarks/bench_batch.py [--frames 8] [--object box] [--repeats 3]

Frames: synthetic tabletop scenes (``jaxreg.synth.tabletop_scene``, seeds 100 on, two
distractors, a RealSense D435's depth noise) of one object, registered against its mesh's
20,000 surface samples. After a warm-up of both (compilation excluded), the two contenders
are timed in interleaved rounds; frames per second are the frames over the median seconds.
Every frame's pose from the batched call is checked equal to the loop's.
"""

from __future__ import annotations

import argparse
import os
import platform

import jax
import numpy as np
from _timing import interleaved_medians, print_table

import jaxreg as jr
from jaxreg.synth import tabletop_scene
from jaxreg.synth._meshes import surface_points


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=8)
    parser.add_argument("--object", default="box")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    scenes = [tabletop_scene(100 + i, object=args.object) for i in range(args.frames)]
    frames = [s.frame for s in scenes]
    model, symmetry = surface_points(scenes[0].model), scenes[0].symmetry

    def loop():
        return [jr.estimate_pose(f, model, symmetry=symmetry) for f in frames]

    def batched():
        return jr.estimate_poses(frames, model, symmetry=symmetry)

    ours, theirs = batched(), loop()
    for a, b in zip(ours, theirs, strict=True):
        if not np.array_equal(np.asarray(a.pose.wxyz_xyz), np.asarray(b.pose.wxyz_xyz)):
            raise SystemExit("estimate_poses and estimate_pose disagree on a frame")
    found = sum(bool(e.success) for e in ours)
    medians = interleaved_medians(
        {"estimate_pose loop": loop, "estimate_poses (one call)": batched},
        repeats=args.repeats,
        warmup=0,
    )
    n = args.frames
    rows = [
        [name, f"{seconds:.2f}", f"{seconds / n * 1e3:.0f}", f"{n / seconds:.2f}"]
        for name, seconds in medians.items()
    ]
    print_table(
        f"Pixels to pose, {args.frames} frames of a {args.object} ({found} found); jax "
        f"{jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} cores, "
        f"{platform.machine()}, load average {os.getloadavg()[0]:.1f}; medians of "
        f"{args.repeats} interleaved rounds",
        ["contender", "seconds", "ms per frame", "frames per second"],
        rows,
    )
    ratio = medians["estimate_pose loop"] / medians["estimate_poses (one call)"]
    print(f"\nThroughput: estimate_poses / the loop {ratio:.2f}x")


if __name__ == "__main__":
    main()
