"""Calibrated error bars (jaxreg.uncertainty.calibrated, jaxreg.studies.calibrate): the
split-conformal factor's coverage on fresh draws, the per-axis scales, the file, the errors."""

import numpy as np
import pytest
from scipy.stats import chi2

import jaxreg as jr
from jaxreg.uncertainty.budget import PoseBudget
from jaxreg.uncertainty.calibrated import BudgetCalibration, fit_budget_calibration


def _draws(rng, count, truth_sigma, stated_sigma):
    """Errors drawn with per-axis ``truth_sigma`` ``(6,)`` while the stated covariance says
    ``stated_sigma``: ``(count, 6)`` errors and ``(count, 6, 6)`` covariances."""
    errors = rng.normal(size=(count, 6)) * truth_sigma
    covariances = np.tile(np.diag(np.asarray(stated_sigma, float) ** 2), (count, 1, 1))
    return errors, covariances


def test_the_calibrated_region_covers_the_stated_level_on_fresh_draws():
    """Bars 3x too narrow on translation and 2x too wide on rotation: uncalibrated, the 95%
    region holds far fewer; calibrated on 200 draws, fresh draws fall inside ~95% of the
    time, and the scales recover the axes' shape."""
    rng = np.random.default_rng(0)
    truth = np.array([3e-3, 3e-3, 3e-3, 0.01, 0.01, 0.01])
    stated = np.array([1e-3, 1e-3, 1e-3, 0.02, 0.02, 0.02])
    errors, covariances = _draws(rng, 200, truth, stated)
    calibration = fit_budget_calibration(errors, covariances, 0.95)
    ratio = calibration.scales * np.sqrt(calibration.factor)
    assert np.allclose(ratio[:3], 3.0, rtol=0.3) and np.allclose(ratio[3:], 0.5, rtol=0.3)
    fresh, fresh_cov = _draws(rng, 4000, truth, stated)
    bound = chi2.ppf(0.95, 6)

    def inside(cov):
        pairs = zip(fresh, cov, strict=True)
        return np.mean([e @ np.linalg.solve(c, e) <= bound for e, c in pairs])

    assert inside(fresh_cov) < 0.5
    covered = inside([calibration.covariance(c) for c in fresh_cov])
    assert 0.92 <= covered <= 0.99


def test_free_axes_stay_free_and_the_budget_is_scaled_term_by_term():
    calibration = BudgetCalibration(np.full(6, 2.0), 1.5, 0.95, 20, 20)
    term = np.diag([1.0, 1, 1, 1, 1, np.inf])
    budget = PoseBudget({"depth": term, "fit": term}, np.array([0, 0, 0, 0, 0, 1], bool), None,
                        np.zeros(6))  # fmt: skip
    scaled = calibration.apply(budget)
    assert np.allclose(np.diag(scaled.terms["depth"])[:5], 6.0)
    assert np.isinf(scaled.terms["depth"][5, 5])


def test_a_calibration_file_round_trips_and_a_bad_one_is_refused(tmp_path):
    calibration = BudgetCalibration(np.arange(1.0, 7.0), 1.7, 0.9, 12, 13)
    path = tmp_path / "bars.json"
    calibration.save(path)
    back = BudgetCalibration.load(path)
    assert np.array_equal(back.scales, calibration.scales)
    counts = (back.factor, back.level, back.fitted_frames, back.conformal_frames)
    assert counts == (1.7, 0.9, 12, 13)
    path.write_text('{"scales": [1, 2], "factor": 1, "level": 0.9, "fitted_frames": 1, '
                    '"conformal_frames": 1}')  # fmt: skip
    with pytest.raises(ValueError, match="6 positive numbers"):
        BudgetCalibration.load(path)
    path.write_text("not json")
    with pytest.raises(ValueError, match="not a budget calibration file"):
        BudgetCalibration.load(path)


def test_too_few_frames_for_the_level_are_refused_naming_how_many():
    rng = np.random.default_rng(1)
    errors, covariances = _draws(rng, 20, np.ones(6), np.ones(6))
    with pytest.raises(ValueError, match="at least 38"):
        fit_budget_calibration(errors, covariances, 0.95)
    with pytest.raises(ValueError, match=r"\(N, 6\)"):
        fit_budget_calibration(errors[:, :3], covariances, 0.95)


def test_calibrate_runs_the_pipeline_and_counts_only_posed_frames():
    """Two synthetic frames: both posed, far too few for a 95% bound, so the study says how
    many it needs; mismatched lengths are refused."""
    scenes = [jr.synth.tabletop_scene(seed, object="cylinder") for seed in (0, 1)]
    frames = [s.frame for s in scenes]
    truths = [s.truth for s in scenes]
    with pytest.raises(ValueError, match="38 successful estimates with truth, got 2"):
        jr.studies.calibrate(frames, truths, scenes[0].model_points, symmetry=scenes[0].symmetry)
    with pytest.raises(ValueError, match="got 2 frames and 1 truths"):
        jr.studies.calibrate(frames, truths[:1], scenes[0].model_points)
