"""Repeatability tiers: noise is the small problem, a hand-eye bias the large one, and moving the
camera is what reveals it.

A box seen by a D435-class camera (synthetic, 640x360) through a hand-eye calibration that is
off by 4.9 mm and 1 degree; the three-tier study of ``jaxreg.studies.repeatability`` with every
pose from ``jaxreg.estimate_pose`` (segment, lift, register: what a user gets): 8
re-measurements of the frozen scene, 8 re-placements, 3 viewpoints x 4 re-measurements.
Left: each estimate's position error (base x, y) from the truth, tiers 1 and 2 in grey and
black, tier 3 coloured by viewpoint, the grasp margin dashed (jaws along base y). Middle, and
zoomed on the right: tier 3 again after ``estimate_hand_eye_correction`` (Gauss-Newton through
the lift and ICP) corrected the hand-eye: the viewpoint clusters coincide on the truth.
Run: python paper_figs/fig_repeatability.py   (a few minutes: the pipeline compiles)
"""

import textwrap

import matplotlib.pyplot as plt
import numpy as np
from _common import save

from jaxreg.studies import repeatability
from jaxreg.studies._repeatability import TIERS
from jaxreg.uncertainty import grasp_success_probability

PLANTED = np.r_[[0.004, -0.002, 0.002], np.radians(1.0) * np.array([0.6, -0.8, 0.0])]
COLOURS = ("tab:blue", "tab:orange", "tab:green")


def main():
    study = repeatability(0, hand_eye_bias=PLANTED, replacements=8, closing_axis=(0.0, 1.0, 0.0))
    fix = study.correct_hand_eye()
    mm = 1e3
    found = np.asarray(study.found)
    tier, view = np.asarray(study.tier)[found], np.asarray(study.view)[found]
    truth = np.asarray(study.truth.translation())[found]
    before = (np.asarray(study.poses.translation())[found] - truth) * mm
    after = (np.asarray(fix.poses_after.translation()) - truth[tier == 2]) * mm

    fig, axes = plt.subplots(1, 3, figsize=(13.5, 4.6))
    span = np.abs(np.r_[before[:, :2].ravel(), after[:, :2].ravel()]).max() + 1.5
    ax = axes[0]
    ax.scatter(*before[tier == 0, :2].T, s=18, c="0.6", label=f"{TIERS[0]} (tier 1)")
    ax.scatter(*before[tier == 1, :2].T, s=18, c="k", marker="s", label=f"{TIERS[1]} (tier 2)")
    for v in range(3):
        sel = (tier == 2) & (view == v)
        ax.scatter(*before[sel, :2].T, s=26, c=COLOURS[v], marker="^", label=f"viewpoint {v}")
    ax.set_title("reported hand-eye (4.9 mm, 1.0 deg off)", fontsize=10)
    for ax, title in ((axes[1], "hand-eye corrected by gradient"), (axes[2], "corrected, zoomed")):
        for v in range(3):
            sel = np.asarray(study.view_labels) == v
            ax.scatter(*after[sel, :2].T, s=26, c=COLOURS[v], marker="^", label=f"viewpoint {v}")
        ax.set_title(title, fontsize=10)
    margin = float(study.margin) * mm
    for ax, half in zip(axes, (span, span, 1.0), strict=True):
        ax.axhline(0, c="0.85", lw=0.8, zorder=0)
        ax.axvline(0, c="0.85", lw=0.8, zorder=0)
        for edge in (-margin, margin):
            ax.axhline(edge, c="tab:red", ls="--", lw=0.8, zorder=0)
        ax.plot(0, 0, "r+", ms=14, mew=2, label="truth")
        ax.set_xlim(-half, half)
        ax.set_ylim(-half, half)
        ax.set_aspect("equal")
        ax.set_xlabel("position error, base x (mm)")
    axes[0].plot([], [], c="tab:red", ls="--", lw=0.8, label="grasp margin (jaws along y)")
    axes[0].set_ylabel("position error, base y (mm)")
    axes[0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()

    # Grasp success along the jaws (base y) of the viewpoint tier before and after.
    lateral_after = after[:, 1] / mm
    p_after = float(
        grasp_success_probability(lateral_after.std(ddof=1), lateral_after.mean(), study.margin)
    )
    sigma1 = np.asarray(study.frozen.translation_sigma) * mm
    sigma2 = np.asarray(study.replacement.translation_sigma) * mm
    groups, post = study.viewpoint.groups, fix.after.groups
    offsets = np.linalg.norm(np.asarray(groups.translation_offset), axis=1) * mm
    within = np.asarray(groups.translation_sigma).max() * mm
    bias1 = np.linalg.norm(np.asarray(study.translation_bias[0])) * mm
    error = np.asarray(fix.tangent) + PLANTED
    p = np.asarray(study.grasp_success)
    fires = {True: "fires", False: "is silent"}
    lines = [
        "Repeatability tiers (synthetic D435 at 640x360, box, hand-eye off by 4.9 mm / 1.0 deg).",
        f"Lesson: tier 1 spread is typically 0.3-1 mm and 0.2-0.5 deg. Measured: sigma x, y, z "
        f"= {sigma1[0]:.2f}, {sigma1[1]:.2f}, {sigma1[2]:.2f} mm, rotation spread "
        f"{float(study.frozen.rotation_spread_deg):.2f} deg (jaxreg.estimate_pose, no clutter; "
        f"a pose in {found.sum()} of {found.size} frames).",
        f"Lesson: re-placement doubles or triples the spread. Measured: {sigma2.max():.2f} vs "
        f"{sigma1.max():.2f} mm on the largest axis ({sigma2.max() / sigma1.max():.1f}x), "
        f"rotation spread {float(study.replacement.rotation_spread_deg):.2f} vs "
        f"{float(study.frozen.rotation_spread_deg):.2f} deg.",
        f"Lesson: tier 3 shows per-viewpoint clusters, individually tight but mutually offset "
        f"by millimetres. Measured: within-view sigma <= {within:.2f} mm, viewpoint means "
        f"{', '.join(f'{o:.1f}' for o in offsets)} mm from the common mean; the bias test "
        f"{fires[bool(groups.bias_detected)]} (offset/sigma up to "
        f"{np.asarray(groups.offset_ratio).max():.0f}).",
        f"Lesson: the dominant error is a repeatable calibration bias that does not average "
        f"away. Measured: tier 1 sits {bias1:.1f} mm from the truth with {sigma1.max():.2f} mm "
        f"of noise. Predicted grasp success along the jaws ({margin:.1f} mm margin): "
        f"{100 * p[0]:.1f}% (tier 1), {100 * p[2]:.1f}% (tier 3), {100 * p_after:.1f}% (tier 3 "
        f"after the correction).",
        f"Correction by Gauss-Newton through lift + ICP ({int(fix.iterations)} steps): the views "
        f"disagree by {float(fix.disagreement_before) * mm:.2f} -> "
        f"{float(fix.disagreement_after) * mm:.2f} mm RMS; the planted error is recovered to "
        f"{np.linalg.norm(error[:3]) * mm:.2f} mm and {np.degrees(np.linalg.norm(error[3:])):.3f}"
        f" deg; afterwards the bias test {fires[bool(post.bias_detected)]} (offsets up to "
        f"{np.abs(np.asarray(post.translation_offset)).max() * mm:.2f} mm and "
        f"{np.abs(np.asarray(post.rotation_offset_deg)).max():.2f} deg, offset/sigma up to "
        f"{np.asarray(post.offset_ratio).max():.1f}: "
        f"{'a bias beyond' if bool(fix.bias_left) else 'nothing beyond'} the 0.5 mm / 0.5 deg "
        "resolution, the size of the registration's own view-dependent bias).",
    ]
    caption = "\n".join(textwrap.fill(line, 100) for line in lines)
    header = ["tier", "viewpoint", "stage", "error_x_mm", "error_y_mm", "error_z_mm"]
    rows = [
        [TIERS[t], int(v), "reported", *map(float, e)]
        for t, v, e in zip(tier, view, before, strict=True)
    ]
    rows += [
        [TIERS[2], int(v), "corrected", *map(float, e)]
        for v, e in zip(np.asarray(study.view_labels), after, strict=True)
    ]
    save(fig, "repeatability", header, rows, caption)


if __name__ == "__main__":
    main()
