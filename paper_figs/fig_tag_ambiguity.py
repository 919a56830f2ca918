"""Planar-tag ambiguity: a 45 mm tag at 0.55 m seen by a 600 px camera, its four corners
with 0.2 px noise, solved by ``jaxreg.solve_pnp_planar`` (both IPPE candidates, refined).

Left: the ambiguity ratio (second candidate's reprojection RMSE over the best's) and the
fraction of noise draws whose best candidate is the flipped one, against the tag's tilt.
Right: Monte Carlo spread of the best pose at 25 degrees of tilt, per axis of the camera
(x, y in the image plane, z the depth) and per rotation axis of the tag.
Run: python paper_figs/fig_tag_ambiguity.py
"""

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np
from _common import save

import jaxreg as jr

K = jnp.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
SIZE, DEPTH, SIGMA_PX, DRAWS = 0.045, 0.55, 0.2, 400
TILTS = [0.0, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 50.0, 60.0]


def draws(tilt_deg, key):
    corners = jr.tag_object_points(SIZE)
    truth = jr.SE3.from_rotation_and_translation(
        jr.SO3.from_rpy_radians(np.deg2rad(tilt_deg), np.deg2rad(tilt_deg / 2), 0.3),
        jnp.array([0.02, -0.01, DEPTH]),
    )
    pixels = jr.camera.project(truth @ corners, K)
    noisy = pixels + SIGMA_PX * jax.random.normal(key, (DRAWS, 4, 2))
    result = jr.solve_pnp_planar(jnp.broadcast_to(corners, (DRAWS, 4, 3)), noisy, K)
    return truth, result


def main():
    key = jax.random.key(0)
    rows, ratio_med, flipped = [], [], []
    for tilt in TILTS:
        truth, result = draws(tilt, jax.random.fold_in(key, int(tilt)))
        err = np.rad2deg(np.asarray(jr.rotation_error(result.pose, truth)))
        ratio = np.asarray(result.ambiguity_ratio)
        ratio_med.append(float(np.median(ratio)))
        flipped.append(float(np.mean(err > 2 * max(tilt, 5.0) / 2 + 5.0)))
        rows.append(["tilt", tilt, ratio_med[-1], flipped[-1], float(np.median(err))])
    truth, result = draws(25.0, jax.random.fold_in(key, 999))
    best = result.pose
    t = np.asarray(best.translation() - truth.translation()) * 1e3
    w = np.asarray((truth.inverse() @ best).rotation().log())
    err = np.rad2deg(np.asarray(jr.rotation_error(best, truth)))
    keep = err < 10  # the spread of the right branch
    t_sigma, w_sigma = t[keep].std(0), np.rad2deg(w[keep].std(0))
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    left.semilogy(TILTS, ratio_med, "o-", label="median ambiguity ratio")
    left.set_xlabel("tag tilt (deg)")
    left.set_ylabel("ambiguity ratio")
    twin = left.twinx()
    twin.plot(TILTS, flipped, "s--", color="C1", label="best candidate flipped")
    twin.set_ylabel("fraction of draws flipped")
    left.legend(loc="upper left", fontsize=8)
    twin.legend(loc="upper right", fontsize=8)
    labels = ["x (image)", "y (image)", "z (depth)"]
    right.bar(np.arange(3) - 0.2, t_sigma, 0.4, label="translation sigma (mm)")
    right.bar(np.arange(3) + 0.2, w_sigma, 0.4, label="rotation sigma (deg), tag axes")
    right.set_xticks(np.arange(3), labels)
    right.set_yscale("log")
    right.legend(fontsize=8)
    right.set_title(f"25 deg tilt, {keep.sum()} draws on the right branch", fontsize=9)
    fig.tight_layout()
    rows += [["sigma_25deg", a, float(ts), float(ws), ""]
             for a, ts, ws in zip("xyz", t_sigma, w_sigma, strict=True)]  # fmt: skip
    in_plane = float(np.mean(t_sigma[:2]))
    caption = (
        "Planar-tag ambiguity (45 mm tag, 0.55 m, 600 px focal length, 0.2 px corner noise). "
        "Lesson's claims: sub-millimetre in-plane position noise; depth and out-of-plane "
        "rotation several times noisier; a genuine two-fold flip near fronto-parallel, which a "
        f"good solver reports. Measured at 25 deg: in-plane sigma {in_plane:.2f} mm, depth "
        f"sigma {t_sigma[2]:.2f} mm ({t_sigma[2] / in_plane:.1f}x); rotation sigma about the "
        f"tag's x, y, z axes {w_sigma[0]:.2f}, {w_sigma[1]:.2f}, {w_sigma[2]:.2f} deg. Median "
        f"ambiguity ratio {ratio_med[0]:.2f} fronto-parallel, {ratio_med[-1]:.1f} at "
        f"{TILTS[-1]:.0f} deg; the best candidate is the flipped one in {flipped[1]:.0%} of the "
        f"draws at {TILTS[1]:.0f} deg and {flipped[-1]:.0%} at {TILTS[-1]:.0f} deg."
    )
    save(fig, "tag_ambiguity", ["kind", "tilt_or_axis", "ratio_or_sigma_mm",
                                "flipped_or_sigma_deg", "median_rotation_error_deg"],
         rows, caption)  # fmt: skip


if __name__ == "__main__":
    main()
