"""The pose error budget: each term carries the error it names (a planted error of that kind
leaves the truth outside the 95% region without the term, inside with it), free directions are
free and never NaN, and a small coverage check over every object."""

import numpy as np
import pytest
from jaxlie import SE3

from jaxreg.camera import RGBDFrame
from jaxreg.geometry.metrics import canonicalise
from jaxreg.pipeline import estimate_pose
from jaxreg.uncertainty.budget import (
    SOURCES,
    combine,
    free_axes,
    mahalanobis,
    region_contains,
)


def _error(estimate, scene) -> np.ndarray:
    """The true error as a right perturbation of the estimate (object axes)."""
    truth = canonicalise(scene.truth, estimate.pose, scene.symmetry)
    return np.asarray((estimate.pose.inverse() @ truth).log(), np.float64)


def _without(budget, source: str) -> np.ndarray:
    """The budget's total less one term."""
    terms = dict(budget.terms)
    terms[source] = np.zeros((6, 6))
    return combine(terms, budget.free, budget.free_reason).total


# --------------------------------------------------------------------------------------------
# The arithmetic.


def test_free_axes_are_inf_on_the_diagonal_and_zero_beside_it():
    cov = np.full((6, 6), 0.5) + np.eye(6)
    free = np.array([False] * 5 + [True])
    out = free_axes(free, cov)
    assert np.isinf(out[5, 5]) and np.all(out[5, :5] == 0) and np.all(out[:5, 5] == 0)
    assert np.array_equal(out[:5, :5], cov[:5, :5]) and not np.any(np.isnan(out))


def test_combine_sums_psd_terms_and_regions_skip_free_axes():
    rng = np.random.default_rng(0)
    terms = {}
    for name in SOURCES:
        a = rng.normal(size=(6, 6)) * 1e-3
        terms[name] = a @ a.T
    terms["fit"] = terms["fit"] - 10 * np.eye(6) * 1e-9  # slightly indefinite: clipped
    free = np.array([False, False, False, False, False, True])
    budget = combine(terms, free, "rotation about z")
    total = budget.total
    assert np.isinf(total[5, 5]) and not np.any(np.isnan(total))
    assert np.all(np.linalg.eigvalsh(total[:5, :5]) > 0)
    for name in SOURCES:  # every term is in the total
        assert np.all(np.linalg.eigvalsh(total[:5, :5] - budget.terms[name][:5, :5]) > -1e-15)
    delta = np.array([1e-3, 0, 0, 0, 0, 3.0])  # a huge error along the free axis is no error
    d2, dof = mahalanobis(delta, total)
    assert dof == 5 and np.isfinite(d2)
    assert region_contains(np.zeros(6), total, 0.5)
    assert not region_contains(np.array([1.0, 0, 0, 0, 0, 0]), total, 0.95)
    with pytest.raises(ValueError, match="lacks the terms"):
        combine({"depth": np.eye(6)}, free, None)


def test_lateral_sigma_is_the_total_along_the_axis():
    terms = {name: np.zeros((6, 6)) for name in SOURCES}
    terms["depth"] = np.diag([4e-6, 1e-6, 9e-6, 1e-4, 1e-4, 1e-4])
    budget = combine(terms, np.zeros(6, bool), None)
    assert budget.lateral_sigma(np.array([0.0, 0.0, 1.0])) == pytest.approx(3e-3)
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2)
    assert budget.lateral_sigma(axis) == pytest.approx(np.sqrt(2.5e-6))


# --------------------------------------------------------------------------------------------
# Planted errors through the pipeline: one frame of the box, its camera pose or depth changed.


@pytest.fixture(scope="module")
def box():
    from jaxreg.synth import StereoSensor, tabletop_scene

    sensor = StereoSensor.d435()
    scene = tabletop_scene(4, object="box", distractors=0, model_points=8192)
    return scene, sensor.depth_noise(scene.frame.intrinsics)


def test_a_planted_hand_eye_error_is_covered_by_the_hand_eye_term(box):
    scene, noise = box
    # the robot believes the camera is 4 mm and 0.4 deg away from where it is
    error = np.array([0.004, -0.003, 0.002, 0.004, -0.005, 0.003])
    believed = scene.frame.base_T_camera @ SE3.exp(error.astype(np.float32))
    frame = RGBDFrame(scene.frame.depth, scene.frame.intrinsics, scene.frame.rgb, believed)
    stated = np.diag([0.003**2] * 3 + [np.radians(0.4) ** 2] * 3)
    est = estimate_pose(
        frame, scene.model_points, symmetry=scene.symmetry, depth_noise=noise,
        hand_eye_covariance=stated,
    )  # fmt: skip
    assert est.success
    delta = _error(est, scene)
    assert np.linalg.norm(delta[:3]) > 0.003  # the planted error reached the pose
    assert region_contains(delta, est.covariance, 0.95)
    assert not region_contains(delta, _without(est.budget, "calibration"), 0.95)


def test_a_planted_depth_scale_error_is_covered_by_the_calibration_term(box):
    scene, noise = box
    frame = RGBDFrame(
        scene.frame.depth * np.float32(1.02), scene.frame.intrinsics, scene.frame.rgb,
        scene.frame.base_T_camera,
    )  # fmt: skip
    est = estimate_pose(
        frame, scene.model_points, symmetry=scene.symmetry, depth_noise=noise,
        depth_scale_sigma=0.015,
    )  # fmt: skip
    assert est.success
    delta = _error(est, scene)
    assert np.linalg.norm(delta[:3]) > 0.005
    assert region_contains(delta, est.covariance, 0.95, translation_only=True)
    without = _without(est.budget, "calibration")
    assert not region_contains(delta, without, 0.95, translation_only=True)


def test_calibration_arguments_are_checked(box):
    scene, _ = box
    with pytest.raises(ValueError, match="hand_eye_covariance"):
        estimate_pose(scene.frame, scene.model_points, hand_eye_covariance=np.eye(3))
    with pytest.raises(ValueError, match="intrinsics_sigma"):
        estimate_pose(scene.frame, scene.model_points, intrinsics_sigma=(1.0, -1.0, 0.0, 0.0))


def test_a_cylinder_is_free_about_its_axis_never_nan():
    from jaxreg.synth import tabletop_scene

    scene = tabletop_scene(7, object="cylinder", distractors=0, model_points=8192)
    est = estimate_pose(scene.frame, scene.model_points, symmetry=scene.symmetry)
    assert est.success
    assert not np.any(np.isnan(est.covariance))
    assert np.isinf(est.covariance[5, 5])  # the symmetry axis is the object's z
    assert np.all(np.isfinite(est.covariance[:5, :5]))
    assert np.all(est.covariance[5, :5] == 0) and np.all(est.covariance[:5, 5] == 0)
    assert "symmetry axis" in est.budget.free_reason
    for term in est.budget.terms.values():
        assert not np.any(np.isnan(term)) and np.isinf(term[5, 5])
    assert region_contains(_error(est, scene), est.covariance, 0.99)


def test_equally_good_starts_that_disagree_widen_the_region(box):
    scene, noise = box
    # the box's half-turn symmetries undeclared: its flipped fits are equally good answers
    est = estimate_pose(scene.frame, scene.model_points, depth_noise=noise)
    assert est.success
    assert est.stages["register"]["equally_good_starts"] >= 2
    rotation_sigma = np.sqrt(np.diag(est.budget.terms["ambiguity"])[3:])
    assert rotation_sigma.max() > np.radians(20)  # the flips are in the region
    others = _without(est.budget, "ambiguity")
    assert np.sqrt(np.diag(others)[3:]).max() < np.radians(5)


def test_only_a_contiguous_run_of_good_turns_around_the_answer_frees_an_axis():
    from jaxreg.pipeline._register_stage import PROBE_ANGLES_DEG
    from jaxreg.pipeline.estimate import _good_arc

    angles = np.asarray(PROBE_ANGLES_DEG)
    assert _good_arc(angles, angles == 180) == 0  # an isolated flip: ambiguity, not freedom
    assert _good_arc(angles, np.abs(angles) <= 60) == 120
    assert _good_arc(angles, (angles >= -40) & (angles <= 150)) == 190
    assert _good_arc(angles, angles >= 120) == 0  # a second basin away from the answer
    assert _good_arc(angles, np.ones(len(angles), bool)) == 360
