"""Can the error bars be trusted? ``jaxreg.studies.calibration_study`` renders tabletop frames of
every synthetic object with the D435 sensor model, estimates each pose with
``jaxreg.estimate_pose`` (the sensor's noise model passed as ``depth_noise``) and compares the
reported covariance with the real error.

Left: reliability of the regions (observed coverage against the nominal level, 6-dof and
translation, per object and overall): a calibrated covariance lies on the diagonal. Middle:
the budget's terms per object (median translation sigma of each source). Right: the grasp
chance predicted from the whole budget against the observed success rate of a parallel-jaw
grasp across the model's narrowest axis, at margins of 1-5 mm per side.
Run: python paper_figs/fig_calibration.py [--seeds N]  (N scenes per object, default 12)
"""

import argparse

import matplotlib.pyplot as plt
import numpy as np
from _common import save
from scipy.stats import chi2

from jaxreg.studies import calibration_study
from jaxreg.uncertainty.budget import SOURCES

SEED0 = 5000  # scenes no test or default tunes on


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=12)
    args = parser.parse_args()
    study = calibration_study(seeds=range(SEED0, SEED0 + args.seeds))
    objects = sorted({f.object for f in study.frames})
    levels = np.linspace(0.05, 0.99, 40)
    fig, (left, middle, right) = plt.subplots(1, 3, figsize=(16, 4.6))
    rows = []
    for name in [*objects, None]:
        found = study.found(name)
        d2 = np.array([f.d2 for f in found])
        dof = np.array([f.dof for f in found])
        observed = [np.mean(d2 <= chi2.ppf(level, dof)) for level in levels]
        style = dict(lw=2.4, color="k") if name is None else dict(lw=1.2)
        left.plot(levels, observed, label=name or "all (6-dof)", **style)
        rows += [
            ["coverage", name or "all", float(a), float(b)]
            for a, b in zip(levels, observed, strict=True)
        ]
    d2t = np.array([f.d2_translation for f in study.found()])
    observed_t = [np.mean(d2t <= chi2.ppf(level, 3)) for level in levels]
    left.plot(levels, observed_t, "k--", label="all (translation)")
    left.plot([0, 1], [0, 1], color="0.6", lw=0.8)
    left.set_xlabel("nominal level of the region")
    left.set_ylabel("frames whose truth is inside")
    left.legend(fontsize=8)

    width = 0.8 / len(SOURCES)
    for k, source in enumerate(SOURCES):
        medians = [
            np.median([np.linalg.norm(f.sigmas[source][:3]) for f in study.found(o)]) * 1e3
            for o in objects
        ]
        middle.bar(np.arange(len(objects)) + k * width, medians, width, label=source)
        rows += [["budget", o, source, float(m)] for o, m in zip(objects, medians, strict=True)]
    errors = [np.median([f.error for f in study.found(o)]) * 1e3 for o in objects]
    middle.plot(np.arange(len(objects)) + 0.4 - width / 2, errors, "k_", ms=30, mew=2,
                label="median actual error")  # fmt: skip
    middle.set_xticks(np.arange(len(objects)) + 0.4 - width / 2, objects)
    middle.set_yscale("log")
    middle.set_ylabel("translation sigma, |diag| (mm)")
    middle.legend(fontsize=7)

    predicted, observed = study.grasp()
    margins = study.margins * 1e3
    right.plot(margins, predicted, "o-", label="mean predicted chance")
    right.plot(margins, observed, "s--", label="observed success rate")
    right.set_xlabel("margin per side (mm)")
    right.set_ylabel("grasp success")
    right.set_ylim(0, 1.02)
    right.legend(fontsize=8)
    rows += [["grasp", "all", float(m), float(p), float(o)]
             for m, p, o in zip(margins, predicted, observed, strict=True)]  # fmt: skip
    fig.tight_layout()

    found = study.found()
    two = int(np.argmin(np.abs(study.margins - 0.002)))
    caption = (
        f"Lesson's point: the error that matters is every source, not the sensor noise alone. "
        f"Measured on {len(found)}/{len(study.frames)} frames found (seeds {SEED0}-"
        f"{SEED0 + args.seeds - 1}, {', '.join(objects)}): the truth lies inside the 95% region "
        f"on {study.coverage(0.95):.0%} of frames (6-dof) and "
        f"{study.coverage(0.95, None, True):.0%} (translation); 50/90% regions cover "
        f"{study.coverage(0.5):.0%}/"
        f"{study.coverage(0.9):.0%}; median predicted translation sigma is "
        f"{study.sharpness():.2f}x the median error; at a 2 mm margin the predicted grasp "
        f"chance is {predicted[two]:.2f}, the observed rate {observed[two]:.2f}.\n\n"
        + study.table()
    )
    save(fig, "fig_calibration", ["kind", "object", "a", "b", "c"], rows, caption)


if __name__ == "__main__":
    main()
