"""Repeatability study: three tiers on synthetic scenes with a planted hand-eye error, and the
hand-eye correction found by differentiating through lifting and registration.

One study (seed 0, 640x360, 6 + 6 + 3 x 4 frames, exact masks) serves most tests; the viewpoint
tier is its longest, so the tiers' statistics and the correction's share one compilation, and
the control (no planted error), the other seeds and the orbit study reuse every compiled shape.
The study through the real pipeline (``registration="pipeline"``) compiles
``jaxreg.estimate_pose`` and is slow.
"""

import jax
import numpy as np
import pytest
from jaxlie import SE3

import jaxreg as jr
from jaxreg.geometry.lie import se3_exp
from jaxreg.registration.icp import ICPStatus
from jaxreg.studies._hand_eye import estimate_hand_eye_correction, stack_frames
from jaxreg.studies._repeatability import repeatability
from jaxreg.synth import tabletop_scene

# The planted hand-eye error: 4.9 mm and 1.0 degree (right perturbation of base_T_camera).
BIAS = np.r_[[0.004, -0.002, 0.002], np.radians(1.0) * np.array([0.6, -0.8, 0.0])]
SIZES = dict(frozen=6, replacements=6, draws_per_view=4, registration="mask")
# Recovery tolerance: errors on seeds 0-7 reach 1.97 mm and 0.28 degrees, each the same as
# the same seed gives with nothing planted (the registration's own view bias, absorbed).
TOLERANCE = (2.5e-3, 0.35)  # metres, degrees


@pytest.fixture(scope="module")
def study():
    return repeatability(0, hand_eye_bias=BIAS, **SIZES)


@pytest.fixture(scope="module")
def correction(study):
    return study.correct_hand_eye()


def check_recovered(correction, planted):
    """The correction undoes the planted error within TOLERANCE and 4 standard errors per
    axis, the views agree, and no viewpoint bias beyond the resolution is left."""
    assert correction.status_message() == "the views agree: the correction converged"
    error = np.asarray(correction.tangent) + planted
    assert np.linalg.norm(error[:3]) < TOLERANCE[0]
    assert np.degrees(np.linalg.norm(error[3:])) < TOLERANCE[1]
    se = np.sqrt(np.diag(np.asarray(correction.covariance)))
    assert np.all(np.abs(error) < 4 * se)
    assert float(correction.disagreement_after) < 0.15 * float(correction.disagreement_before)
    assert bool(correction.before.groups.bias_detected)
    assert not bool(correction.bias_left)


def test_every_frame_registers(study):
    codes = np.asarray(study.status._value)
    assert len(codes) == 6 + 6 + 12
    usable = [ICPStatus.success._value, ICPStatus.max_iterations._value]
    assert np.isin(codes, usable).all()
    assert np.mean(codes == ICPStatus.success._value) > 0.8


def test_a_hand_eye_bias_is_a_repeatable_offset_only_moving_the_camera_reveals(study):
    """Tiers 1 and 2 are tight (sub-millimetre) yet every estimate sits where the planted
    error predicts, millimetres from the truth; tier 3's viewpoints form tight, mutually offset
    clusters that the per-viewpoint test flags."""
    tier = np.asarray(study.tier)
    camera = SE3(study.true_base_T_camera.wxyz_xyz[0])  # viewpoint 0: the camera of tiers 1, 2
    moved = camera @ se3_exp(BIAS.astype(np.float32)) @ camera.inverse() @ study.nominal
    predicted = np.asarray(moved.translation() - study.nominal.translation())
    assert np.linalg.norm(predicted) > 5e-3
    for t, stats in enumerate([study.frozen, study.replacement]):
        assert np.all(np.asarray(stats.translation_sigma) < 1e-3)
        assert float(stats.rotation_spread_deg) < 1.0
        assert int(stats.count) == 6
        np.testing.assert_allclose(study.translation_bias[t], predicted, atol=0.5e-3)
    groups = study.viewpoint.groups
    assert bool(groups.bias_detected)
    assert np.max(np.asarray(groups.offset_ratio)[:3]) > 10
    np.testing.assert_array_equal(groups.count, [4, 4, 4])
    # Within a viewpoint the spread stays tier-1 sized; across viewpoints it is millimetres.
    assert np.all(np.asarray(groups.translation_sigma) < 1e-3)
    assert np.max(np.asarray(study.viewpoint.translation_sigma)) > 3e-3
    assert np.array_equal(np.unique(np.asarray(study.view)[tier == 2]), [0, 1, 2])


def test_budget_and_grasp_success_put_the_bias_first(study):
    """Along the closing axis (base x) the viewpoint tier dominates the RSS budget, and the
    predicted grasp success drops where the bias shows."""
    lateral = np.asarray(study.lateral_error)
    tier = np.asarray(study.tier)
    assert float(study.margin) == pytest.approx(0.0075)
    # The same spread from the statistics (poses referred to the nominal) and from the errors.
    np.testing.assert_allclose(
        study.lateral_sigma[2], study.viewpoint.translation_sigma[0], rtol=1e-3
    )
    np.testing.assert_allclose(study.lateral_bias[0], lateral[tier == 0].mean(), rtol=1e-6)
    assert float(study.budget.shares["viewpoint"]) > 0.9
    assert float(study.budget.total) > 5 * float(study.lateral_sigma[0])
    p = np.asarray(study.grasp_success)
    assert p[2] < p[0] and p[0] > 0.99
    assert float(study.budget_grasp_success) < p[0]


def test_correction_recovers_the_planted_hand_eye_error(study, correction):
    """Gauss-Newton through lift + ICP brings the views together; the correction undoes the
    planted 4.9 mm / 1 degree error to within 2.5 mm and 0.35 degrees (and 4 standard errors
    per axis), and no viewpoint offset beyond 0.5 mm / 0.5 degrees is left."""
    assert int(correction.rank) == 6 and bool(correction.converged)
    check_recovered(correction, BIAS)
    np.testing.assert_allclose(correction.pose.log(), correction.tangent, atol=1e-6)


def test_what_is_left_after_the_correction_is_the_registrations_own_view_bias(correction):
    """With no hand-eye error the viewpoints still differ by tenths of a millimetre and
    degree (the sensor's noise meets the box's edges differently from each view): the
    resolution of ``bias_left`` sits above that floor, and what the correction leaves is the
    same size."""
    control = repeatability(0, hand_eye_bias=np.zeros(6), **SIZES).viewpoint.groups
    floor_t = np.abs(np.asarray(control.translation_offset)).max()
    floor_r = np.abs(np.asarray(control.rotation_offset_deg)).max()
    assert 0.02e-3 < floor_t < 0.5e-3 and floor_r < 0.5
    left = correction.after.groups
    assert np.abs(np.asarray(left.translation_offset)).max() < 2 * max(floor_t, 0.1e-3)
    assert np.abs(np.asarray(left.rotation_offset_deg)).max() < 0.5


@pytest.mark.parametrize("seed", [1, 3])
def test_the_correction_holds_on_other_scenes(seed):
    """Seeds 1 and 3 are those where the bias test still fired after the correction when the
    residual view-dependent registration bias was judged against within-view noise alone."""
    check_recovered(repeatability(seed, hand_eye_bias=BIAS, **SIZES).correct_hand_eye(), BIAS)


def test_a_list_of_frames_gives_the_same_correction(study, correction):
    third = np.asarray(study.tier) == 2
    frames = [jax.tree.map(lambda x, i=i: x[i] if np.ndim(x) else x, study.frames)
              for i in range(int(third.sum()))]  # fmt: skip
    again = estimate_hand_eye_correction(
        frames, study.masks, study.model_points, study.model_normals,
        SE3(study.poses.wxyz_xyz[third]), max_steps=1,
    )  # fmt: skip
    np.testing.assert_allclose(again.disagreement_before, correction.disagreement_before, rtol=1e-5)


def test_a_step_search_that_never_improves_is_no_improvement_not_agreement(study, monkeypatch):
    """A Jacobian that does not describe the registrations (here: its sign flipped) makes every
    Gauss-Newton step, halved 4 times, increase the disagreement: the correction stays at
    zero, and the status says so instead of "the views agree"."""
    from jaxreg.studies import _hand_eye

    linearise = _hand_eye._linearise

    def flipped(*args):
        jac, *rest = linearise(*args)
        return (-jac, *rest)

    monkeypatch.setattr(_hand_eye, "_linearise", flipped)
    result = study.correct_hand_eye()
    assert float(result.disagreement_after) == float(result.disagreement_before)
    assert result.status_message().startswith("no step reduced the views' disagreement")
    assert not bool(result.converged) and int(result.iterations) == 0
    np.testing.assert_array_equal(result.tangent, np.zeros(6))


def test_a_frame_the_pipeline_fails_has_a_nan_pose_not_the_truth(monkeypatch):
    """Where the estimator gives no pose, the study reports NaN and the reason, never the
    truth: a stand-in for estimate_pose (its result's fields) fails the second frame."""
    from types import SimpleNamespace

    from jaxreg.pipeline import estimate

    calls = []

    def stand_in(frame, model_points, *, model_normals=None, symmetry=None):
        calls.append(len(calls))
        found = len(calls) != 2
        return SimpleNamespace(
            success=found,
            pose=SE3.identity() if found else None,
            mask=np.isfinite(np.asarray(frame.depth)),
            reason="found" if found else "the model is not there: a stand-in's failure",
        )

    monkeypatch.setattr(estimate, "estimate_pose", stand_in)
    study = repeatability(
        0, frozen=3, replacements=2, draws_per_view=2, image_size=(160, 90), model_samples=256
    )
    found = np.asarray(study.found)
    assert found.tolist() == [i != 1 for i in range(len(calls))]
    poses = np.asarray(study.poses.wxyz_xyz)
    assert np.all(np.isnan(poses[1])) and np.all(np.isfinite(poses[found]))
    assert study.reasons[1] == "the model is not there: a stand-in's failure"
    assert np.isnan(np.asarray(study.lateral_error)[1])


def test_an_orbit_leaves_the_screw_about_its_axis_unobservable():
    """Cameras at one elevation and distance differ by turns about the vertical through the
    object: the correction's turn about that line and slide along it change no view, so the
    observable projector annihilates them and the rest is still recovered."""
    orbit = ((45.0, 50.0, 0.6), (135.0, 50.0, 0.6), (225.0, 50.0, 0.6))
    study = repeatability(0, hand_eye_bias=BIAS, viewpoints=orbit, **SIZES)
    result = study.correct_hand_eye()
    assert int(result.rank) == 4
    assert result.status_message().startswith("converged, but the views fix only some")
    centre = np.asarray(study.nominal.translation(), float)
    up = np.array([0.0, 0.0, 1.0])
    turn, slide = np.r_[np.cross(centre, up), up], np.r_[up, 0.0, 0.0, 0.0]  # base-frame twists
    camera = SE3(study.true_base_T_camera.wxyz_xyz[0])
    projector = np.asarray(result.observable)
    for twist in (turn, slide):
        null = np.asarray(camera.inverse().adjoint()) @ twist  # the same twist, camera frame
        assert np.linalg.norm(projector @ null) < 0.02 * np.linalg.norm(null)
    error = projector @ (np.asarray(result.tangent) + BIAS)
    assert np.linalg.norm(error[:3]) < 3e-3 and np.degrees(np.linalg.norm(error[3:])) < 0.35
    assert not bool(result.bias_left)


def test_bad_requests_raise(study):
    with pytest.raises(ValueError, match="at least 2"):
        repeatability(0, frozen=1)
    with pytest.raises(ValueError, match="hand_eye_bias"):
        repeatability(0, hand_eye_bias=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="registration"):
        repeatability(0, registration="exact")
    inits = study.view_poses
    with pytest.raises(ValueError, match="masks"):
        estimate_hand_eye_correction(
            study.frames, study.masks[:, :10], study.model_points, study.model_normals, inits
        )
    with pytest.raises(ValueError, match="fewer than 3"):
        estimate_hand_eye_correction(
            study.frames, np.zeros(study.masks.shape, bool), study.model_points,
            study.model_normals, inits,
        )  # fmt: skip
    small = jr.Intrinsics(200.0, 200.0, 79.5, 59.5, 160, 120)
    wider = jr.Intrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
    frames = [tabletop_scene(0, noise=False, intrinsics=k).frame for k in (small, wider)]
    with pytest.raises(ValueError, match="intrinsics"):
        stack_frames(frames)
    with pytest.raises(ValueError, match="inits"):
        estimate_hand_eye_correction(
            study.frames, study.masks, study.model_points, study.model_normals, study.nominal
        )


@pytest.mark.slow
def test_through_the_pipeline_the_tiers_and_the_correction_hold():
    """The default study: every pose from jaxreg.estimate_pose (it compiles for minutes).
    Tiers 1 and 2 stay sub-millimetre, the viewpoints reveal the planted error, and the
    correction, registering the pixels the pipeline's poses explain, recovers it."""
    study = repeatability(0, hand_eye_bias=BIAS, frozen=6, replacements=6, draws_per_view=4)
    assert study.registration == "pipeline" and study.status is None
    assert np.asarray(study.found).all()
    for stats in (study.frozen, study.replacement):
        assert np.all(np.asarray(stats.translation_sigma) < 1e-3)
    assert bool(study.viewpoint.groups.bias_detected)
    check_recovered(study.correct_hand_eye(), BIAS)
