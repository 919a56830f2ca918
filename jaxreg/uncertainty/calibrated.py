"""Error bars calibrated on a user's own object and camera: per-axis scales of a pose's error
budget fitted on frames with known truth, and a split-conformal factor on the normalised error
fitted on other frames, so that the stated level's region holds the truth on new frames of the
same kind (:func:`fit_budget_calibration`; :func:`jaxreg.studies.calibrate` runs the pipeline
on the frames).

The guarantee is split conformal prediction's: when the calibration frames and a new frame are
exchangeable (the same object, camera, scene layout and settings, drawn alike) and the new
frame's estimate succeeds as theirs did, the truth lies in the calibrated ``level`` region with
probability at least ``level`` (over the draw of the frames), whatever the budget's shape;
the per-axis scales only make the region sharper. It says nothing about frames of another
kind (another object, camera or clutter).

Conventions: errors and covariances are right perturbations ``(v, w)`` of ``base_T_object``
in the object's axes (metres, radians); a free axis (``inf`` variance) takes no part.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from jaxreg.uncertainty.budget import PoseBudget

__all__ = ["BudgetCalibration", "fit_budget_calibration"]


@dataclasses.dataclass(frozen=True)
class BudgetCalibration:
    """Per-axis scales and a conformal factor for a pose's error budget.

    Attributes:
        scales: ``(6,)`` standard-deviation scale per tangent axis ``(v, w)``.
        factor: the variance factor on the scaled budget that makes its ``level`` region
            hold the conformal quantile of the held-out frames' normalised errors.
        level: the stated coverage (0.95: the 95% region).
        fitted_frames, conformal_frames: how many frames fitted the scales and the factor.
    """

    scales: np.ndarray
    factor: float
    level: float
    fitted_frames: int
    conformal_frames: int

    def covariance(self, covariance: np.ndarray) -> np.ndarray:
        """``(6, 6)``: ``covariance`` scaled per axis and by the factor (free axes stay
        ``inf``)."""
        covariance = np.asarray(covariance, np.float64)
        scaled = covariance * np.outer(self.scales, self.scales) * self.factor
        return np.where(np.isfinite(covariance), scaled, covariance)

    def apply(self, budget: PoseBudget) -> PoseBudget:
        """``budget`` with every term calibrated (:meth:`covariance`): its total is the
        calibrated covariance."""
        terms = {name: self.covariance(term) for name, term in budget.terms.items()}
        return dataclasses.replace(budget, terms=terms)

    def save(self, path: str | Path) -> None:
        """Write the calibration as a small JSON text file."""
        Path(path).write_text(
            json.dumps(
                {
                    "scales": [float(s) for s in self.scales],
                    "factor": float(self.factor),
                    "level": float(self.level),
                    "fitted_frames": int(self.fitted_frames),
                    "conformal_frames": int(self.conformal_frames),
                },
                indent=2,
            )
            + "\n"
        )

    @classmethod
    def load(cls, path: str | Path) -> BudgetCalibration:
        """Read a file :meth:`save` wrote; ``ValueError`` names what is missing or wrong."""
        try:
            data = json.loads(Path(path).read_text())
            scales = np.asarray(data["scales"], np.float64)
            calibration = cls(
                scales, float(data["factor"]), float(data["level"]),
                int(data["fitted_frames"]), int(data["conformal_frames"]),
            )  # fmt: skip
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
            raise ValueError(f"{path} is not a budget calibration file: {error}") from error
        if scales.shape != (6,) or not np.all(np.isfinite(scales) & (scales > 0)):
            raise ValueError(f"{path}: scales must be 6 positive numbers, got {data['scales']}")
        return calibration


def _normalised(error: np.ndarray, covariance: np.ndarray) -> tuple[float, int]:
    """``error^T Sigma^-1 error`` over the finite axes of ``covariance`` and their count."""
    finite = np.isfinite(np.diag(covariance))
    if not finite.any():
        return 0.0, 0
    sub = covariance[np.ix_(finite, finite)]
    e = error[finite]
    return float(e @ np.linalg.pinv(sub) @ e), int(finite.sum())


def fit_budget_calibration(
    errors: np.ndarray, covariances: np.ndarray, level: float = 0.95
) -> BudgetCalibration:
    """A :class:`BudgetCalibration` from estimates with known truth: ``errors`` ``(N, 6)``
    (the truth's right perturbation of each estimate) and their ``covariances`` ``(N, 6, 6)``.

    The first ``N // 2`` frames fit the per-axis scales (the root mean square of each axis's
    error over its standard deviation); the others give the conformal factor: with ``n`` of
    them, the normalised errors under the scaled covariances, the ``ceil((n + 1) level)``-th
    smallest over the chi-square ``level`` quantile (at their finite axes' count). ``n`` must
    be at least ``level / (1 - level)`` (19 frames for 0.95): fewer cannot bound the level.
    """
    errors = np.asarray(errors, np.float64)
    covariances = np.asarray(covariances, np.float64)
    if errors.ndim != 2 or errors.shape[1] != 6 or covariances.shape != (len(errors), 6, 6):
        raise ValueError(
            f"errors must be (N, 6) and covariances (N, 6, 6), got {errors.shape} and "
            f"{covariances.shape}"
        )
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    half = len(errors) // 2
    needed = math.ceil(level / (1.0 - level))
    if len(errors) - half < needed:
        raise ValueError(
            f"a {level:.0%} conformal bound needs {needed} held-out frames, and half of the "
            f"frames are held out: give at least {2 * needed} successful estimates with "
            f"truth, got {len(errors)}"
        )
    variances = np.stack([np.diag(c) for c in covariances[:half]])
    usable = np.isfinite(variances) & (variances > 0)
    ratios = np.where(usable, errors[:half] ** 2 / np.where(usable, variances, 1.0), np.nan)
    scales = np.ones(6)
    seen = usable.any(0)
    scales[seen] = np.sqrt(np.nanmean(ratios[:, seen], axis=0))
    scales = np.clip(scales, 1e-3, 1e3)
    held = [
        _normalised(e, c * np.outer(scales, scales))
        for e, c in zip(errors[half:], covariances[half:], strict=True)
    ]
    scores = np.sort([d2 for d2, _ in held])
    rank = math.ceil((len(scores) + 1) * level)
    dof = max(int(np.median([k for _, k in held])), 1)
    factor = float(scores[rank - 1] / chi2.ppf(level, dof))
    return BudgetCalibration(scales, max(factor, 1e-12), level, half, len(scores))
