"""Planar PnP on thousands of tags: one batched jaxreg call against an OpenCV loop, same run.

Usage: python benchmarks/bench_pnp.py [--sizes 2000] [--repeats 15] [--max-iterations 100 30]

Views: a 45 mm square tag facing the camera at 0.5-0.6 m, tilted up to 40 degrees, any in-plane
spin, 0.2 px Gaussian corner noise, a 640x480 camera with f = 600 px; float32 (jaxreg's default).
jaxreg solves all tags in one jitted call (both IPPE candidates per tag; with refinement, both
are polished by Levenberg-Marquardt); its compile time is reported separately. Every contender
is timed in interleaved rounds (each round calls each once) and the medians are reported, with
the ratio to the OpenCV loop of the same stage (unrefined to unrefined, refined to refined).
OpenCV runs ``solvePnPGeneric(SOLVEPNP_IPPE_SQUARE)`` per tag in a Python loop, which returns
the two unrefined IPPE candidates; the refined OpenCV row adds ``solvePnPRefineLM`` on both.
jaxreg's Levenberg-Marquardt steps an eighth of the candidates at a time, the first ones still
running (median 5 steps; a few candidates in flat valleys need up to ~40), so the
refined rows are repeated per ``--max-iterations`` budget and count the candidates that ran out
of steps (flagged ``PnPStatus.max_iterations``). OpenCV's ``solvePnPRefineLM`` stops after at
most 20 steps by default, without saying whether it converged.
"""

from __future__ import annotations

import argparse
import functools
import platform
import time

import jax
import numpy as np
from _timing import interleaved_medians, print_table

from jaxreg import PnPStatus, solve_pnp_planar, tag_object_points

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
TAG = 0.045


def tag_views(n: int, seed: int = 0) -> np.ndarray:
    """Noisy corner pixels (n, 4, 2) of random tag views."""
    rng = np.random.default_rng(seed)
    corners = np.asarray(tag_object_points(TAG), np.float64)
    images = np.empty((n, 4, 2))
    for i in range(n):
        axis = np.array([*rng.normal(size=2), 0.0])
        axis *= np.deg2rad(rng.uniform(0.0, 40.0)) / np.linalg.norm(axis)
        R = (
            rodrigues(axis)
            @ np.diag([1.0, -1.0, -1.0])
            @ rodrigues([0, 0, rng.uniform(-np.pi, np.pi)])
        )
        t = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.5, 0.6)])
        Xc = corners @ R.T + t
        images[i] = (Xc[:, :2] / Xc[:, 2:3]) @ K[:2, :2].T + K[:2, 2]
    return images + rng.normal(scale=0.2, size=images.shape)


def rodrigues(rotvec) -> np.ndarray:
    rotvec = np.asarray(rotvec, np.float64)
    theta = np.linalg.norm(rotvec)
    if theta < 1e-12:
        return np.eye(3)
    k = rotvec / theta
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * kx + (1 - np.cos(theta)) * kx @ kx


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[2000])
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--max-iterations", type=int, nargs="+", default=[100, 30])
    args = parser.parse_args()
    try:
        import cv2
    except ImportError:
        cv2 = None
        print("OpenCV not installed (pip install 'jaxreg[peers]'): timing jaxreg only")

    corners = np.asarray(tag_object_points(TAG), np.float64)
    rows = []
    for n in args.sizes:
        images = tag_views(n)
        contenders, compile_s, results = {}, {}, {}
        if cv2 is not None:

            def cv_loop(refine, images=images):
                for img in images:
                    _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                        corners, img, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
                    )
                    if refine:
                        for r, t in zip(rvecs, tvecs, strict=True):
                            cv2.solvePnPRefineLM(corners, img, K, None, r, t)

            contenders["OpenCV IPPE_SQUARE loop"] = functools.partial(cv_loop, False)
            contenders["OpenCV IPPE_SQUARE + RefineLM x2 loop"] = functools.partial(cv_loop, True)
        for refine, max_iterations in [(False, 1)] + [(True, m) for m in args.max_iterations]:
            solve = jax.jit(
                lambda img, refine=refine, max_iterations=max_iterations: solve_pnp_planar(
                    corners, img, K, refine=refine, max_iterations=max_iterations
                )
            )
            name = (
                f"jaxreg IPPE + LM x2 (max_iterations={max_iterations}), batched"
                if refine
                else "jaxreg IPPE, batched"
            )
            start = time.perf_counter()
            results[name] = jax.block_until_ready(solve(images))
            compile_s[name] = time.perf_counter() - start
            contenders[name] = lambda solve=solve, images=images: jax.block_until_ready(
                solve(images)
            )
        # Interleaved rounds: each contender timed once per round, so load falls on all alike.
        t = interleaved_medians(contenders, args.repeats)
        for name, seconds in t.items():
            refined = "LM" in name or "Refine" in name
            peer = "OpenCV IPPE_SQUARE + RefineLM x2 loop" if refined else "OpenCV IPPE_SQUARE loop"
            ratio = f"{t[peer] / seconds:.2f}" if peer in t else "-"
            steps, flagged = "-", "-"
            if name in results and refined:
                c = results[name].candidates
                steps = int(np.max(c.iterations))
                flagged = int(np.sum(c.status == PnPStatus.max_iterations))
            comp = f"{compile_s[name]:.1f}" if name in compile_s else "-"
            rows.append([n, name, f"{seconds * 1e3:.1f}", comp, ratio, steps, flagged])
    device = jax.devices()[0]
    print_table(
        f"Planar PnP, 45 mm tag at 0.5-0.6 m, 0.2 px noise; jax {jax.__version__} on "
        f"{device.platform} ({device.device_kind}), {platform.processor() or platform.machine()}"
        + (f", OpenCV {cv2.__version__}" if cv2 is not None else ""),
        [
            "tags",
            "method",
            "ms (median)",
            "compile s",
            "speed vs OpenCV (same stage)",
            "max LM steps",
            "candidates out of steps",
        ],
        rows,
    )


if __name__ == "__main__":
    main()
