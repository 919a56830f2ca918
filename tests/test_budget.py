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
    register = est.stages["register"]
    assert register.equally_good_starts + register.equally_good_probes >= 2
    rotation_sigma = np.sqrt(np.diag(est.budget.terms["ambiguity"])[3:])
    assert rotation_sigma.max() > np.radians(20)  # the flips are in the region
    others = _without(est.budget, "ambiguity")
    assert np.sqrt(np.diag(others)[3:]).max() < np.radians(5)


def test_only_a_contiguous_run_of_good_turns_around_the_answer_frees_an_axis():
    from jaxreg.pipeline._answer import PROBE_ANGLES_DEG, _good_arc

    angles = np.asarray(PROBE_ANGLES_DEG)
    assert _good_arc(angles, angles == 180) == 0  # an isolated flip: ambiguity, not freedom
    assert _good_arc(angles, np.abs(angles) <= 60) == 120
    assert _good_arc(angles, (angles >= -40) & (angles <= 150)) == 190
    assert _good_arc(angles, angles >= 120) == 0  # a second basin away from the answer
    assert _good_arc(angles, np.ones(len(angles), bool)) == 360


# --------------------------------------------------------------------------------------------
# The terms' pieces.


def _box_points(rng, n=1500):
    """Points on three faces of a 6 x 4 x 10 cm box (object frame) and their normals."""
    half = np.array([0.03, 0.02, 0.05])
    points, normals = [], []
    for axis in range(3):
        p = rng.uniform(-half, half, (n // 3, 3))
        p[:, axis] = half[axis]
        points.append(p)
        normals.append(np.tile(np.eye(3)[axis], (n // 3, 1)))
    return np.concatenate(points), np.concatenate(normals)


def test_the_depth_term_is_icp_covariance_of_the_same_pairs():
    import jaxreg as jr
    from jaxreg.pipeline import _error_sources as _budget
    from jaxreg.uncertainty import DepthNoise

    rng = np.random.default_rng(0)
    model, normals = _box_points(rng)
    object_T_base = SE3.exp(np.array([0.01, -0.02, 0.3, 0.2, -0.1, 0.3]))
    segment = np.asarray(object_T_base.inverse() @ model)  # base frame, exact
    camera = SE3.exp(np.array([0.0, 0.0, -0.3, 0.0, 0.0, 0.0]))
    noise = DepthNoise((0.0, 0.0, 2.5e-3), camera)
    pairs, pair_normals, _, kept = _budget._pairs(
        segment, np.asarray(object_T_base.wxyz_xyz), model, normals, 0.006, 1.0, None, len(segment)
    )
    jac = _budget._jacobian(pairs, pair_normals, np.asarray(object_T_base.wxyz_xyz))
    inverse = np.linalg.inv(jac.T @ jac)
    host = _budget._depth_base(jac, pairs, noise, inverse, np.ones(len(kept), bool))
    reference = np.asarray(
        jr.icp_covariance(
            segment.astype(np.float32), model.astype(np.float32), object_T_base,
            method="point_to_plane", target_normals=normals.astype(np.float32),
            max_correspondence_distance=0.006, source_noise=noise,
        )  # fmt: skip
    )
    np.testing.assert_allclose(np.sqrt(np.diag(host)), np.sqrt(np.diag(reference)), rtol=0.1)


def test_the_fit_term_sees_residuals_shared_by_neighbouring_points():
    from jaxreg.pipeline import _error_sources as _budget

    rng = np.random.default_rng(1)
    model, normals = _box_points(rng, 3000)
    pose = np.asarray(SE3.identity().wxyz_xyz)
    jac = _budget._jacobian(model, normals, pose)
    inverse = np.linalg.inv(jac.T @ jac)
    blocks = _budget._blocks(model, 0.012)
    sigma = 0.001
    depth = inverse * sigma**2  # independent residuals of this sigma: H^-1 sigma^2
    independent = rng.normal(0.0, sigma, len(model))
    shared = rng.normal(0.0, sigma, blocks.max() + 1)[blocks]  # one offset per 12 mm patch
    alone = _budget._fit_term(jac, independent, blocks, inverse, depth)
    patches = _budget._fit_term(jac, shared, blocks, inverse, depth)
    assert np.trace(alone) < 0.5 * np.trace(depth)  # nothing beyond the depth noise
    assert np.trace(patches) > 3 * np.trace(depth)  # far fewer independent errors than points


def test_perturbed_segments_erode_grow_and_drop_pieces(box):
    from jaxreg.pipeline._error_sources import perturbed_segments

    scene, _ = box
    frame, mask = scene.frame, scene.mask
    cloud = np.asarray(frame.points(mask)).reshape(-1, 3)
    points = cloud[np.all(np.isfinite(cloud), axis=1)]
    size = len(points) + 500
    segments = perturbed_segments(
        frame, mask, points, None, 0.0, size, np.random.default_rng(0), count=8
    )
    counts = np.sum(np.all(np.isfinite(segments), axis=2), axis=1)
    assert np.all(counts[:2] < len(points))  # eroded
    assert np.all(counts[2:4] > len(points))  # grown by the ring around the mask
    np.testing.assert_allclose(counts[4:], len(points) - int(0.15 * len(points)), atol=1)


# --------------------------------------------------------------------------------------------
# Coverage: frames of every object that nothing tunes on.


@pytest.mark.slow
def test_the_region_covers_the_truth_on_most_unseen_frames_of_every_object():
    from jaxreg.studies import calibration_study

    study = calibration_study(seeds=range(5000, 5002))  # two frames of each object
    found = study.found()
    assert len(found) == len(study.frames) == 8
    assert not any(np.any(np.isnan(f.covariance)) for f in found)
    # on these 8 frames the truth lies inside every 95% region (85-99% over the many frames of
    # benchmarks/: one frame outside here is a change to look at, not noise to allow)
    assert study.coverage(0.95) == 1.0
    assert study.coverage(0.95, translation=True) == 1.0
    for name in ("box", "mug", "cylinder", "container"):
        assert study.coverage(0.99, name) == 1.0, name  # both of its frames
    # bars that are not uselessly wide: the equally good starts and turns, weighed by their
    # evidence, widen them beyond the sensor noise alone
    assert study.sharpness() <= 5

    def inside(without: str | None = None) -> int:
        count = 0
        for f in found:
            cov = f.covariance
            if without is not None:
                term = np.where(np.isfinite(f.terms[without]), f.terms[without], 0.0)
                cov = np.where(np.isfinite(cov), cov - term, cov)
            count += region_contains(f.delta, cov, 0.95)
        return count

    # the ambiguity term, which no other test plants an error for, carries real error on these
    # frames; the mismatch term never narrows the region
    assert inside("mismatch") <= inside() and inside("ambiguity") < inside()
    text = study.table()
    assert text.count("\n") == 2 + 4 + 1 - 1 and "| all | 8/8 |" in text


def test_a_term_that_cannot_be_computed_is_unknown_never_zero():
    """A non-finite term, or one its caller could not compute, is named in the budget's
    `unknown` and makes every axis of the total infinite: the bars bound nothing rather than
    leaving the term out (narrower) as a zero would."""
    from jaxreg.uncertainty.budget import SOURCES, combine

    terms = {name: np.eye(6) * 1e-6 for name in SOURCES}
    known = combine(terms, np.zeros(6, bool), None)
    assert known.unknown == {} and np.all(np.isfinite(known.total))
    terms["fit"] = np.full((6, 6), np.nan)
    broken = combine(terms, np.zeros(6, bool), None)
    assert set(broken.unknown) == {"fit"}
    assert np.all(np.isinf(np.diag(broken.total)))
    terms["fit"] = np.eye(6) * 1e-6
    failed = combine(terms, np.zeros(6, bool), None, unknown={"segmentation": "no fit"})
    assert failed.unknown == {"segmentation": "no fit"}
    assert np.all(np.isinf(np.diag(failed.total)))
    # inf on a free axis is the free axis, not an unknown term
    free = np.array([False] * 5 + [True])
    terms["ambiguity"] = np.diag([1e-6] * 5 + [np.inf])
    assert combine(terms, free, "symmetry").unknown == {}
