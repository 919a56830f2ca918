"""The lesson's one-line experiment: ICP on its 6 cm cube from the identity, the scene turned
15 degrees (inside the basin) and 60 degrees (outside), with 2 mm noise.

Left: the inlier RMSE per iteration of both runs (the wrong one converges just as calmly).
Right: 256 starts at each offset about random axes (``jaxreg.studies.basin_sweep``): final
rotation error against final residual; confidently wrong starts (ICP converged, pose wrong)
are the ones whose residual gives nothing away.
Run: python paper_figs/fig_15_vs_60.py
"""

import jax
import matplotlib.pyplot as plt
import numpy as np
from _common import save

import jaxreg as jr
from jaxreg.studies import basin_sweep, lesson_cube

OPTIONS = dict(max_correspondence_distance=0.02, max_iterations=40)


def main():
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4.2))
    rows, single = [], {}
    for angle in (15.0, 60.0):
        model, scene, truth = lesson_cube(angle)
        result = jr.icp(model, scene, **OPTIONS)
        t_err, r_err = jr.pose_error(result.pose, truth)
        single[angle] = (
            float(np.rad2deg(r_err)), float(t_err) * 1e3, float(result.inlier_rmse) * 1e3,
            float(result.inlier_fraction), int(result.iterations), result.status_message(),
        )  # fmt: skip
        history = np.asarray(result.rmse_history) * 1e3
        left.plot(np.arange(1, len(history) + 1), history, "o-", ms=3,
                  label=f"{angle:g} deg: ends {single[angle][0]:.1f} deg wrong")  # fmt: skip
        # the same offset about random axes
        sweep = basin_sweep(
            model, scene, truth, angles_deg=[angle], samples_per_angle=256,
            key=jax.random.key(1), **OPTIONS,
        )  # fmt: skip
        err = np.asarray(sweep.rotation_error_deg).ravel()
        rmse = np.asarray(sweep.inlier_rmse).ravel() * 1e3
        wrong = np.asarray(sweep.confidently_wrong).ravel()
        right.scatter(rmse[~wrong], err[~wrong], s=8, label=f"{angle:g} deg starts")
        right.scatter(rmse[wrong], err[wrong], s=14, marker="x",
                      label=f"{angle:g} deg: converged but wrong ({wrong.mean():.0%})")  # fmt: skip
        rows += [["random_axis", angle, float(e), float(r), bool(w)]
                 for e, r, w in zip(err, rmse, wrong, strict=True)]  # fmt: skip
        rows.append(["about_z_from_identity", angle, single[angle][0], single[angle][2], ""])
    left.set_xlabel("iteration")
    left.set_ylabel("inlier RMSE (mm)")
    left.set_title("lesson's run: from the identity, scene turned about z", fontsize=9)
    left.legend(fontsize=8)
    right.set_xlabel("final inlier RMSE (mm)")
    right.set_ylabel("final rotation error (deg)")
    right.set_yscale("log")
    right.set_title("256 random axes per offset", fontsize=9)
    right.legend(fontsize=7)
    fig.tight_layout()
    a, b = single[15.0], single[60.0]
    caption = (
        "Lesson's claim: at 15 deg ICP recovers the rotation to 0.3 deg; at 60 deg it settles "
        "more than 80 deg wrong while reporting an innocuous 4 mm residual. Measured (jaxreg.icp,"
        f" 2 cm, 40 iterations): 15 deg -> {a[0]:.2f} deg and {a[1]:.1f} mm off, residual "
        f"{a[2]:.2f} mm, inlier fraction {a[3]:.2f} ({a[4]} iterations); 60 deg -> {b[0]:.1f} "
        f"deg wrong, {b[1]:.1f} mm off, residual {b[2]:.2f} mm, inlier fraction {b[3]:.2f} "
        f"({b[4]} iterations, status: {b[5].split(':')[0]})."
    )
    save(fig, "15_vs_60", ["run", "angle_deg", "rotation_error_deg", "inlier_rmse_mm",
                           "confidently_wrong"], rows, caption)  # fmt: skip


if __name__ == "__main__":
    main()
