"""Calibrate the pipeline's error bars on frames of the user's own object and camera with known
truth (:func:`calibrate`): the estimates' errors against their budgets, turned into a
:class:`~jaxreg.uncertainty.calibrated.BudgetCalibration` that
``estimate_pose(..., calibration=)`` and ``track(..., calibration=)`` apply."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from jaxlie import SE3

from jaxreg.geometry.metrics import Symmetry, canonicalise
from jaxreg.pipeline.estimate import estimate_pose
from jaxreg.uncertainty.calibrated import BudgetCalibration, fit_budget_calibration

__all__ = ["calibrate"]


def _pose(truth) -> SE3:
    return truth if isinstance(truth, SE3) else SE3.from_matrix(np.asarray(truth, np.float64))


def calibrate(
    frames: Sequence[Any],
    truths: Sequence[Any],
    model_points,
    *,
    model_normals=None,
    symmetry: Symmetry | None = None,
    level: float = 0.95,
    **estimate_options,
) -> BudgetCalibration:
    """A :class:`~jaxreg.uncertainty.calibrated.BudgetCalibration` from frames with known
    truth.

    Args:
        frames: ``RGBDFrame`` each, or ``(frame, mask)`` pairs: synthetic frames rendered
            from the user's mesh and sensor (:mod:`jaxreg.synth`), or annotated real frames
            (YCB-Video's, a BOP split's).
        truths: each frame's ``base_T_object``, ``SE3`` or ``(4, 4)``.
        model_points, model_normals, symmetry: the model as ``estimate_pose`` takes it; a
            symmetry's turns of the truth count as the truth.
        level: the coverage the calibrated region states.
        estimate_options: more keywords of :func:`jaxreg.estimate_pose` (``depth_noise=``,
            settings).

    The frames are estimated in their order; the successful estimates' first half fits the
    per-axis scales and the second half the conformal factor
    (:func:`~jaxreg.uncertainty.calibrated.fit_budget_calibration`), so the frames should come
    in no particular order (shuffle a sequence that drifts). Refused frames take no part: the
    guarantee holds for frames the pipeline poses. ``ValueError`` when too few are posed.
    """
    if len(frames) != len(truths):
        raise ValueError(f"got {len(frames)} frames and {len(truths)} truths")
    errors, covariances = [], []
    for item, truth in zip(frames, truths, strict=True):
        frame, mask = item if isinstance(item, tuple) else (item, None)
        est = estimate_pose(
            frame, model_points, mask=mask, model_normals=model_normals, symmetry=symmetry,
            **estimate_options,
        )  # fmt: skip
        if not est.success:
            continue
        true = _pose(truth)
        if symmetry is not None:
            true = canonicalise(true, est.pose, symmetry)
        errors.append(np.asarray((est.pose.inverse() @ true).log(), np.float64))
        covariances.append(np.asarray(est.covariance, np.float64))
    return fit_budget_calibration(np.array(errors).reshape(-1, 6),
                                  np.array(covariances).reshape(-1, 6, 6), level)  # fmt: skip
