"""What an error bar costs: the closed-form ICP covariance against the Monte Carlo it replaces.

Usage: python benchmarks/bench_covariance.py [--draws 200] [--repeats 3]

Data: PCL's milk.pcd, scan-to-model point-to-plane (1500 scan points re-measured with depth
noise along the camera rays, 4 mm voxel model of 3.7k points as the target, 1 cm
correspondence distance, 60 iterations at most), float32. Rows: ``icp_covariance`` on one
scan (correspondences at the converged pose, the Hessian and six reverse passes for the mixed
derivative); ``init_spread`` (13 sigma-point ICP runs in one vmapped call); and a Monte Carlo
study of ``--draws`` re-noised scans registered in one vmapped call (the grid is built once),
summarised by ``pose_statistics``. Times are medians over repeats after a compile call, whose
time is reported separately.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from _timing import DATA, median_seconds, print_table
from jaxlie import SE3, SO3

from jaxreg.io import load_points
from jaxreg.registration.icp import icp, icp_covariance, init_spread
from jaxreg.search.neighbors import build_grid, voxel_downsample
from jaxreg.search.normals import estimate_normals
from jaxreg.uncertainty import DepthNoise, pose_statistics


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()

    scan = load_points(DATA / "pcl" / "milk.pcd")
    model = voxel_downsample(scan, 0.004).astype(np.float32)
    normals = np.asarray(estimate_normals(model, k=20))
    view = scan[np.random.default_rng(0).choice(len(scan), 1500, replace=False)]
    truth = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(0.1, -0.2, 0.3), jnp.array([0.05, -0.02, 0.1])
    )
    source = truth.inverse() @ jnp.asarray(view, jnp.float32)
    noise = DepthNoise((0.0, 0.0, 0.002), base_T_camera=truth.inverse())
    grid = build_grid(model, 0.01, mask=np.linalg.norm(normals, axis=1) > 0.5)  # with a normal
    opts = dict(
        method="point_to_plane",
        target_normals=normals,
        neighbors=grid,
        max_correspondence_distance=0.01,
        max_iterations=60,
        tolerance=1e-7,
    )
    scan0 = noise.sample(jax.random.key(0), source)
    pose = icp(scan0, model, truth, **opts).pose
    init_cov = np.diag([2e-3] * 3 + [np.radians(2.0)] * 3) ** 2
    keys = jax.random.split(jax.random.key(1), args.draws)
    register = jax.jit(jax.vmap(lambda s: icp(s, model, truth, **opts)))

    def closed_form():
        return jax.block_until_ready(icp_covariance(scan0, model, pose, source_noise=noise, **opts))

    def sigma_points():
        return jax.block_until_ready(init_spread(scan0, model, pose, init_cov, **opts))

    def monte_carlo():
        scans = jax.vmap(lambda k: noise.sample(k, source))(keys)
        return jax.block_until_ready(pose_statistics(register(scans).pose).covariance)

    rows = []
    for name, fn in [
        ("icp_covariance (one scan)", closed_form),
        ("init_spread (13 sigma points)", sigma_points),
        (f"Monte Carlo ({args.draws} scans)", monte_carlo),
    ]:
        start = time.perf_counter()
        fn()
        compile_s = time.perf_counter() - start
        rows.append([name, f"{compile_s:.1f}", f"{1e3 * median_seconds(fn, args.repeats, 0):.0f}"])
    print_table(
        f"Covariance of a point-to-plane pose, milk.pcd, float32 ({platform.processor() or 'cpu'},"
        f" {os.cpu_count()} cores, {jax.default_backend()})",
        ["method", "first call s", "median ms"],
        rows,
    )


if __name__ == "__main__":
    main()
