"""Closed-form ICP covariance against Monte Carlo on a real scan (milk.pcd).

Three studies, each registering a few hundred re-noised copies of a scan with vmapped ICP and
comparing the per-axis spread with `icp_covariance` evaluated on the first copy alone:

(a) point-to-plane, scan-to-model: 1500 raw Kinect points of the carton (source, expressed in
    a frame where the camera sits at truth^-1) re-measured with depth noise along each camera
    ray (sigma_z = 2 mm * z^2, 1.0-1.6 mm here), registered to the 4 mm voxel model (target,
    normals from the model);
(b) the same with point-to-point;
(c) point-to-plane, model-to-scene: the noisy scan is the *target*, in a robot base frame
    through a hand-eye transform, its normals re-estimated from every noisy copy (the target
    is traced, so ICP uses brute-force matching);
(d) the Monte Carlo cloud of (a) in (vx, vy) with the predicted 1- and 2-sigma ellipses.

Prints the ratios predicted / measured and writes out/covariance_vs_monte_carlo.png/.csv/.txt
(units: mm and degrees).
Run: python paper_figs/fig_covariance_vs_monte_carlo.py [--draws 300] (a few minutes on CPU).
"""

import argparse
import textwrap
import time

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from _common import DATA, save
from jaxlie import SE3, SO3

from jaxreg.io import load_points
from jaxreg.registration.icp import icp, icp_covariance
from jaxreg.search.neighbors import build_grid, voxel_downsample
from jaxreg.search.normals import estimate_normals
from jaxreg.uncertainty import DepthNoise, pose_statistics

AXES = ["vx", "vy", "vz", "wx", "wy", "wz"]
UNITS = np.array([1e3] * 3 + [180 / np.pi] * 3)  # mm and degrees
TRUTH = SE3.from_rotation_and_translation(
    SO3.from_rpy_radians(0.1, -0.2, 0.3), jnp.array([0.05, -0.02, 0.1])
)
OPTIONS = dict(max_correspondence_distance=0.01, max_iterations=60, tolerance=1e-7)


def draw_by_draw(register, clouds, *args) -> SE3:
    """``register(cloud, *args).pose`` for each of the ``(D, N, 3)`` clouds, stacked ``(D,)``.

    One compiled unbatched ICP called per draw: on CPU, compiling ICP vmapped over the draws
    took minutes, these calls take seconds."""
    return SE3(jnp.stack([register(cloud, *args).pose.wxyz_xyz for cloud in clouds]))


def scan_to_model(scan, method, draws):
    """Studies (a) and (b): returns (predicted sigma, measured sigma, MC deviations)."""
    model = voxel_downsample(scan, 0.004).astype(np.float32)
    normals = np.asarray(estimate_normals(model, k=20)) if method == "point_to_plane" else None
    rng = np.random.default_rng(0)
    view = scan[rng.choice(len(scan), 1500, replace=False)].astype(np.float32)
    source = TRUTH.inverse() @ view
    noise = DepthNoise((0.0, 0.0, 0.002), base_T_camera=TRUTH.inverse())
    grid = build_grid(model, OPTIONS["max_correspondence_distance"])
    opts = dict(OPTIONS, method=method, target_normals=normals)
    keys = jax.random.split(jax.random.key(0), draws)
    scans = jax.vmap(lambda k: noise.sample(k, source))(keys)
    run = jax.jit(lambda s, m, g: icp(s, m, TRUTH, neighbors=g, **opts))
    poses = draw_by_draw(run, scans, model, grid)
    stats = pose_statistics(poses)
    first = SE3(poses.wxyz_xyz[0])
    cov = icp_covariance(scans[0], model, first, source_noise=noise, neighbors=grid, **opts)
    deviations = np.asarray((stats.mean.inverse() @ poses).log())
    return (
        np.sqrt(np.diag(np.asarray(cov))),
        np.sqrt(np.diag(np.asarray(stats.covariance))),
        deviations,
        np.asarray(cov),
    )


def model_to_scene(scan, draws):
    """Study (c): the noisy scan as the target in the base frame, normals re-estimated."""
    rng = np.random.default_rng(0)
    view = scan[rng.choice(len(scan), 1500, replace=False)].astype(np.float32)
    base_T_camera = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(2.5, 0.1, -0.4), jnp.array([0.4, 0.1, 0.9])
    )
    target = base_T_camera @ view
    model = voxel_downsample(scan, 0.006).astype(np.float32)
    source = np.asarray(TRUTH.inverse() @ base_T_camera @ model)
    noise = DepthNoise((0.0, 0.0, 0.002), base_T_camera=base_T_camera)
    eye = base_T_camera.translation()
    opts = dict(OPTIONS, method="point_to_plane")

    @jax.jit
    def register(t, source, eye):
        return icp(
            source, t, TRUTH, target_normals=estimate_normals(t, k=20, viewpoint=eye), **opts
        )

    keys = jax.random.split(jax.random.key(0), draws)
    targets = jax.vmap(lambda k: noise.sample(k, target))(keys)
    poses = draw_by_draw(register, targets, source, eye)
    stats = pose_statistics(poses)
    first = SE3(poses.wxyz_xyz[0])
    normals0 = estimate_normals(targets[0], k=20, viewpoint=eye)
    cov = icp_covariance(
        source, targets[0], first, target_normals=normals0, target_noise=noise, **opts
    )
    return np.sqrt(np.diag(np.asarray(cov))), np.sqrt(np.diag(np.asarray(stats.covariance)))


def bars(ax, predicted, measured, title):
    x = np.arange(6)
    ax.bar(x - 0.2, measured * UNITS, 0.4, label="Monte Carlo")
    ax.bar(x + 0.2, predicted * UNITS, 0.4, label="icp_covariance")
    for i in range(6):
        ax.text(
            x[i] + 0.2,
            predicted[i] * UNITS[i],
            f"{predicted[i] / measured[i]:.2f}",
            ha="center",
            va="bottom",
            fontsize=7,
        )
    ax.set_xticks(x, [f"{a}\n({'mm' if i < 3 else 'deg'})" for i, a in enumerate(AXES)])
    ax.set_yscale("log")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)


def ellipse(ax, cov2, scale, **style):
    lam, vec = np.linalg.eigh(cov2)
    angle = np.linspace(0, 2 * np.pi, 200)
    circle = np.stack([np.cos(angle), np.sin(angle)])
    pts = vec @ (np.sqrt(lam)[:, None] * circle) * scale
    ax.plot(pts[0], pts[1], **style)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=300)
    parser.add_argument(
        "--target-draws",
        type=int,
        default=100,
        help="draws for study (c), whose brute-force matching is slower",
    )
    args = parser.parse_args()
    scan = load_points(DATA / "pcl" / "milk.pcd")
    start = time.perf_counter()
    plane = scan_to_model(scan, "point_to_plane", args.draws)
    point = scan_to_model(scan, "point_to_point", args.draws)
    scene = model_to_scene(scan, args.target_draws)
    print(f"{time.perf_counter() - start:.0f} s")
    print("predicted / Monte Carlo sigma per axis " + " ".join(f"{a:>5}" for a in AXES))
    for name, (pred, meas) in [
        (f"(a) point-to-plane, scan noise, {args.draws} draws ", plane[:2]),
        (f"(b) point-to-point, scan noise, {args.draws} draws ", point[:2]),
        (f"(c) point-to-plane, scene noise, {args.target_draws} draws", scene),
    ]:
        print(f"{name:<39} " + " ".join(f"{r:5.2f}" for r in pred / meas))

    fig, axes = plt.subplots(1, 4, figsize=(17, 4))
    bars(axes[0], *plane[:2], "(a) point-to-plane, noisy scan to model")
    bars(axes[1], *point[:2], "(b) point-to-point, noisy scan to model")
    bars(axes[2], *scene, "(c) point-to-plane, model to noisy scene (normals re-estimated)")
    dev, cov = plane[2], plane[3]
    ax = axes[3]
    ax.scatter(dev[:, 0] * 1e3, dev[:, 1] * 1e3, s=4, alpha=0.5, label="Monte Carlo")
    for k, style in [(1, "-"), (2, "--")]:
        ellipse(ax, cov[:2, :2] * 1e6, k, color="C1", ls=style, label=f"predicted {k} sigma")
    ax.set_xlabel("vx (mm)")
    ax.set_ylabel("vy (mm)")
    ax.set_aspect("equal", "datalim")
    ax.set_title("(d) study (a), right perturbation about the Karcher mean", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()

    studies = [
        ("a", "point_to_plane, scan noise", args.draws, plane[:2]),
        ("b", "point_to_point, scan noise", args.draws, point[:2]),
        ("c", "point_to_plane, scene noise", args.target_draws, scene),
    ]
    rows = [
        [label, name, draws, axis, float(pred[i] * UNITS[i]), float(meas[i] * UNITS[i]),
         float(pred[i] / meas[i])]
        for label, name, draws, (pred, meas) in studies
        for i, axis in enumerate(AXES)
    ]  # fmt: skip
    ratio = {label: pred / meas for label, _, _, (pred, meas) in studies}
    span = lambda r: f"{r.min():.2f}-{r.max():.2f}"  # noqa: E731
    lines = [
        "Closed-form ICP covariance (icp_covariance) against Monte Carlo on milk.pcd (Kinect), "
        "depth noise sigma_z = 2 mm z^2 along each camera ray.",
        "Lesson: error bars for a system this full of unmodelled effects are honestly obtained "
        "empirically (the repeatability study). Measured, for the one effect that is modelled "
        f"(depth noise), predicted / {args.draws}-draw Monte Carlo sigma per axis (vx vy vz wx "
        f"wy wz): point-to-plane {span(ratio['a'])} (within "
        f"{100 * np.abs(ratio['a'] - 1).max():.0f}%); point-to-point {span(ratio['b'])} (the "
        f"closed form is overconfident there); model-to-scene with re-estimated normals "
        f"{span(ratio['c'])} ({args.target_draws} draws; the normals' noise is not modelled). "
        "Even where it matches, it covers depth noise only: segmentation, partial views and "
        "calibration bias are what the empirical tiers measure.",
    ]
    caption = "\n".join(textwrap.fill(line, 100) for line in lines)
    header = ["study", "method_noise", "draws", "axis", "predicted", "monte_carlo", "ratio"]
    save(fig, "covariance_vs_monte_carlo", header, rows, caption)


if __name__ == "__main__":
    main()
