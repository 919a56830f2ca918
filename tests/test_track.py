"""jaxreg.track: the pose in the next frame from the previous one, without segmentation; it
follows a moved object and refuses (lost) when the object is not where the previous pose says."""

import dataclasses

import numpy as np
import pytest
from jaxlie import SE3, SO3

import jaxreg as jr
from jaxreg.geometry.metrics import add_s


@pytest.fixture(scope="module")
def scene():
    return jr.synth.tabletop_scene(5, object="box", distractors=1)


def _moved(pose: SE3, shift, degrees) -> SE3:
    """``pose`` shifted by ``shift`` (metres, base frame) and turned ``degrees`` about the
    base z axis through the object's origin."""
    turn = SO3.from_z_radians(np.radians(degrees))
    return SE3.from_rotation_and_translation(
        turn @ pose.rotation(), pose.translation() + np.asarray(shift, np.float32)
    )


def _within_tenth(scene, pose) -> bool:
    """ADD-S below 10% of the model's diameter (issue 36's tracking criterion)."""
    points = scene.model_points
    diameter = np.max(np.linalg.norm(points[:, None] - points[None, ::8], axis=-1))
    return float(add_s(points, pose, scene.truth)) < 0.1 * diameter


def test_follows_an_object_from_a_nearby_previous_pose(scene):
    previous = _moved(scene.truth, (0.02, -0.01, 0.0), 6.0)  # 2.2 cm and 6 degrees off
    est = jr.track(scene.frame, scene.model_points, previous, symmetry=scene.symmetry)
    assert est.success, est.reason
    assert _within_tenth(scene, est.pose)
    assert not _within_tenth(scene, _moved(scene.truth, (0.05, 0.0, 0.0), 0.0))
    assert set(est.stages) == {"segment", "lift", "register"}
    assert est.stages["register"].candidates == []  # no coarse search
    sigmas = np.sqrt(np.diag(est.covariance)[:3])
    assert np.all(np.isfinite(sigmas)) and sigmas.max() < 0.02
    # the 4x4 matrix and the previous estimate are the same start
    again = jr.track(scene.frame, scene.model_points, np.asarray(previous.as_matrix()))
    assert again.success
    chained = jr.track(scene.frame, scene.model_points, est, symmetry=scene.symmetry)
    assert chained.success
    assert _within_tenth(scene, chained.pose)


def test_refuses_as_lost_when_the_object_is_not_where_it_was(scene):
    far = _moved(scene.truth, (0.35, 0.3, 0.0), 0.0)  # a previous pose on empty table
    est = jr.track(scene.frame, scene.model_points, far)
    assert not est.success and est.pose is None
    assert est.reason.startswith("lost: ") and "re-detect with estimate_pose" in est.reason
    # the object gone from the frame (its pixels without depth, the colour image kept: the
    # programs compiled for a frame with one serve it)
    depth = np.where(scene.mask, np.nan, np.asarray(scene.frame.depth))
    gone = jr.RGBDFrame(depth, scene.frame.intrinsics, scene.frame.rgb, scene.frame.base_T_camera)
    lost = jr.track(gone, scene.model_points, scene.truth)
    assert not lost.success and lost.reason.startswith("lost: ")


def test_bad_previous_poses_are_refused_clearly(scene):
    with pytest.raises(ValueError, match="previous must be"):
        jr.track(scene.frame, scene.model_points, np.eye(3))
    with pytest.raises(ValueError, match="rotation"):
        jr.track(scene.frame, scene.model_points, np.diag([2.0, 1.0, 1.0, 1.0]))
    blank = jr.camera.RGBDFrame(
        np.full_like(np.asarray(scene.frame.depth), np.nan), scene.frame.intrinsics,
        scene.frame.rgb, scene.frame.base_T_camera,
    )  # fmt: skip
    failed = jr.estimate_pose(blank, scene.model_points)
    assert not failed.success
    with pytest.raises(ValueError, match="holds no pose"):
        jr.track(scene.frame, scene.model_points, failed)
    with pytest.raises(ValueError, match="max_motion"):
        jr.track(scene.frame, scene.model_points, scene.truth, max_motion=0.0)


@pytest.fixture(scope="module")
def pushed():
    """A box pushed across the table over six frames (1-5 cm and 2-10 degrees a frame), a board
    in front of it in frame 3, gone from the view in frame 5."""
    return jr.synth.tracking_sequence(11, object="box", frames=6, occluded=(3,), leaves_at=5)


def test_the_sequence_moves_the_target_by_the_steps_asked(pushed):
    steps = pushed.steps
    assert steps.shape == (5, 2)
    assert np.all((steps[:, 0] >= 0.01) & (steps[:, 0] <= 0.05))
    assert np.all((steps[:, 1] >= 2.0) & (steps[:, 1] <= 10.0))
    for k, (before, after) in enumerate(zip(pushed.scenes, pushed.scenes[1:], strict=False)):
        moved = np.linalg.norm(np.asarray(after.truth.translation() - before.truth.translation()))
        assert moved == pytest.approx(steps[k, 0], abs=1e-5)
    assert pushed.occluded.tolist() == [False, False, False, True, False, False]
    assert pushed.in_view.tolist() == [True] * 5 + [False]
    seen = [int(scene.mask.sum()) for scene in pushed.scenes]
    assert seen[3] < 0.8 * min(seen[2], seen[4]) and seen[5] == 0


def test_follows_a_pushed_box_through_occlusion_and_loses_it_when_it_leaves(pushed):
    scenes = pushed.scenes
    model, symmetry = scenes[0].model_points, scenes[0].symmetry
    estimate = jr.estimate_pose(scenes[0].frame, model, symmetry=symmetry)
    assert estimate.success and _within_tenth(scenes[0], estimate.pose), estimate.reason
    for scene in scenes[1:5]:  # the board in frame 3 hides 40% of the box's width
        estimate = jr.track(scene.frame, model, estimate, symmetry=symmetry)
        assert estimate.success, estimate.reason
        assert _within_tenth(scene, estimate.pose)
    lost = jr.track(scenes[5].frame, model, estimate, symmetry=symmetry)
    assert not lost.success and lost.reason.startswith("lost: ")


@pytest.mark.parametrize(
    "request_, message",
    [
        ({"frames": 1}, "at least 2 frames"),
        ({"step_translation": (0.05, 0.01)}, "step_translation"),
        ({"step_rotation_deg": (5.0, 2.0)}, "step_rotation_deg"),
        ({"occluded": (9,)}, "occluded frames"),
        ({"occluder_fraction": 1.5}, "occluder_fraction"),
    ],
)
def test_bad_sequence_requests_raise(request_, message):
    with pytest.raises(ValueError, match=message):
        jr.synth.tracking_sequence(0, **request_)


def test_a_previous_estimate_lends_its_view_terms_while_the_view_holds(scene):
    """From a previous track step's ``PoseEstimate`` the costly view terms (the probes'
    alternatives, the segmentation term) are carried, and the bars are no narrower than
    measured ones; the first step after ``estimate_pose`` measures its own (the estimate
    registered a table cluster, not the followed pixels); they are measured again once the
    camera's direction in the object frame turned past ``CARRY_TURN_DEG``, the segment's point
    count changed past ``CARRY_POINTS``, or for another model."""
    from jaxreg.pipeline.track import CARRY_POINTS, CARRY_TURN_DEG

    estimated = jr.estimate_pose(scene.frame, scene.model_points, symmetry=scene.symmetry)
    assert estimated.success and estimated.measured_view is not None
    assert not estimated.measured_view.followed
    first = jr.track(scene.frame, scene.model_points, estimated, symmetry=scene.symmetry)
    assert first.success, first.reason
    assert first.stages["register"].view_carried_deg is None
    assert first.measured_view.followed
    carried = jr.track(scene.frame, scene.model_points, first, symmetry=scene.symmetry)
    assert carried.success, carried.reason
    turn = carried.stages["register"].view_carried_deg
    assert turn is not None and turn < 1.0
    assert carried.measured_view is first.measured_view
    unmeasured = dataclasses.replace(first, measured_view=None)  # the same table, no view
    fresh = jr.track(scene.frame, scene.model_points, unmeasured, symmetry=scene.symmetry)
    assert fresh.stages["register"].view_carried_deg is None
    assert fresh.measured_view is not None and fresh.measured_view is not first.measured_view
    for name in ("segmentation", "ambiguity"):
        np.testing.assert_allclose(
            carried.budget.terms[name], first.budget.terms[name], rtol=1e-9, atol=1e-15
        )
    # on the same frame the carried bars are no narrower than those measured there
    ratio = np.sqrt(np.diag(carried.covariance) / np.diag(fresh.covariance))
    assert np.all(ratio > 0.8), ratio
    view = first.measured_view
    # the view measured from a camera direction turned further than the carry allows
    centre = scene.model_points.mean(0)
    ray = np.asarray(view.camera_T_object.inverse().translation()) - centre
    axis = np.cross(ray, np.eye(3)[np.argmin(np.abs(ray))])  # across the line of sight
    axis *= np.radians(CARRY_TURN_DEG + 3.0) / np.linalg.norm(axis)
    turn_about = (
        SE3.from_translation(centre) @ SE3.from_rotation(SO3.exp(axis))
        @ SE3.from_translation(-centre)
    )  # fmt: skip
    turned = dataclasses.replace(view, camera_T_object=view.camera_T_object @ turn_about)
    again = jr.track(
        scene.frame, scene.model_points, dataclasses.replace(first, measured_view=turned),
        symmetry=scene.symmetry,
    )
    assert again.success and again.stages["register"].view_carried_deg is None
    # another model (every second point of this one) measures its own view
    other = jr.track(scene.frame, scene.model_points[::2], first, symmetry=scene.symmetry)
    assert other.stages["register"].view_carried_deg is None
    fewer = dataclasses.replace(view, points=int(len(carried.points) / (CARRY_POINTS - 0.05)))
    again = jr.track(
        scene.frame, scene.model_points, dataclasses.replace(first, measured_view=fewer),
        symmetry=scene.symmetry,
    )
    assert again.success and again.stages["register"].view_carried_deg is None
