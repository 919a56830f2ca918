"""Throughput of batched weighted Kabsch against a numpy loop, batched numpy SVD and scipy.

Usage: python benchmarks/bench_kabsch.py [--problems 10000] [--points 1000]

Every solver gets the same float32 problems (random rotations, 1 mm noise); the table gives
the median time per call over interleaved rounds (each round times every solver once, so a
shared machine's load falls on all alike), problems per second, the ratio to jaxreg, and the
worst rotation error against the truth, so a fast-but-wrong peer is visible.
"""

from __future__ import annotations

import argparse
import platform

import jax
import numpy as np
from _timing import interleaved_medians, print_table

import jaxreg as jr


def numpy_kabsch(src, dst, w):
    """The textbook SVD solution, one problem at a time."""
    wn = w / w.sum()
    a = src - wn @ src
    b = dst - wn @ dst
    u, _, vt = np.linalg.svd((a * wn[:, None]).T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def numpy_batched_kabsch(src, dst, w):
    """The SVD solution with numpy's stacked SVD over the whole batch."""
    wn = w / w.sum(-1, keepdims=True)
    a = src - np.einsum("bn,bnd->bd", wn, src)[:, None]
    b = dst - np.einsum("bn,bnd->bd", wn, dst)[:, None]
    u, _, vt = np.linalg.svd(np.einsum("bn,bni,bnj->bij", wn, a, b))
    d = np.sign(np.linalg.det(np.einsum("bji,bkj->bik", vt, u)))
    vt[:, 2] *= d[:, None]
    return np.einsum("bji,bkj->bik", vt, u)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=int, default=10_000)
    parser.add_argument("--points", type=int, default=1_000)
    parser.add_argument(
        "--loop-problems",
        type=int,
        default=1_000,
        help="problems timed in the per-problem Python loops (then scaled)",
    )
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    b, n = args.problems, args.points

    key_r, key_p, key_n = jax.random.split(jax.random.key(0), 3)
    rot = jr.SO3.sample_uniform(key_r, batch_axes=(b,))
    r_true = np.asarray(rot.as_matrix(), np.float32)
    src = np.asarray(jax.random.normal(key_p, (b, n, 3)) * 0.05, np.float32)
    dst = np.einsum("bij,bnj->bni", r_true, src) + np.float32(0.001) * np.asarray(
        jax.random.normal(key_n, (b, n, 3)), np.float32
    )
    w = np.ones((b, n), np.float32)
    src_d, dst_d, w_d = jax.device_put((src, dst, w))

    solve = jax.jit(lambda s, d, ww: jr.kabsch(s, d, ww).rotation().as_matrix())
    r_jax = np.asarray(solve(src_d, dst_d, w_d))
    m = min(args.loop_problems, b)
    r_loop = np.stack([numpy_kabsch(src[i], dst[i], w[i]) for i in range(m)])
    r_np = numpy_batched_kabsch(src, dst, w)
    contenders = {
        "jax": lambda: solve(src_d, dst_d, w_d).block_until_ready(),
        "loop": lambda: [numpy_kabsch(src[i], dst[i], w[i]) for i in range(m)],
        "batched": lambda: numpy_batched_kabsch(src, dst, w),
    }
    try:
        from scipy.spatial.transform import Rotation

        def scipy_loop():
            return [
                Rotation.align_vectors(dst[i] - dst[i].mean(0), src[i] - src[i].mean(0))[0]
                for i in range(m)
            ]

        contenders["scipy"] = scipy_loop
    except ImportError:
        print("scipy not installed (peers extra): its row is skipped")
    # Interleaved rounds: every contender is timed once per round (shared, loaded machine).
    t = interleaved_medians(contenders, args.repeats)
    t_jax = t["jax"]
    t_loop = t["loop"] * b / m
    t_np = t["batched"]

    rows = []

    def err(r, ref):
        # atan2(|axis part|, cos) of the relative rotation, in float64: arccos of the trace
        # alone loses half the digits near 0 (~0.03 deg of noise for float32 matrices).
        rel = np.einsum("bji,bjk->bik", r.astype(np.float64), ref[: len(r)].astype(np.float64))
        skew = rel - np.swapaxes(rel, 1, 2)
        sin = np.linalg.norm(skew[:, [2, 0, 1], [1, 2, 0]], axis=1) / 2
        cos = (np.trace(rel, axis1=1, axis2=2) - 1) / 2
        return np.degrees(np.arctan2(sin, cos)).max()

    def row(name, t, r):
        rows.append(
            [name, f"{t * 1e3:.1f}", f"{b / t:,.0f}", f"{t / t_jax:.1f}x", f"{err(r, r_true):.4f}"]
        )

    row("jaxreg.kabsch (jit, batched)", t_jax, r_jax)
    row(f"numpy SVD loop (timed on {m}, scaled)", t_loop, r_loop)
    row("numpy batched SVD", t_np, r_np)
    if "scipy" in t:
        r_sp = np.stack([r.as_matrix() for r in contenders["scipy"]()])
        row(f"scipy align_vectors loop (timed on {m}, scaled)", t["scipy"] * b / m, r_sp)

    print_table(
        f"Kabsch throughput: {b:,} problems x {n:,} points, float32, "
        f"{jax.devices()[0].platform} ({platform.processor() or platform.machine()})",
        ["solver", "median ms", "problems/s", "time vs jaxreg", "max rot err deg"],
        rows,
    )


if __name__ == "__main__":
    main()
