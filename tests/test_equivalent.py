"""When depth cannot decide: turns of the model that fit the view as well as the answer are
reported (estimate.equivalent_poses) and widen the covariance; a declared symmetry's copies are
the answer itself and are not reported."""

import numpy as np
import pytest

import jaxreg as jr
from jaxreg.geometry.lie import geodesic_angle
from jaxreg.geometry.metrics import add_s


@pytest.fixture(scope="module")
def box():
    return jr.synth.tabletop_scene(4, object="box", distractors=0)


def test_a_boxs_half_turns_are_reported_without_a_declared_symmetry(box):
    est = jr.estimate_pose(box.frame, box.model_points)
    assert est.success, est.reason
    assert float(add_s(box.model_points, est.pose, box.truth)) < 0.005
    turns = est.equivalent_poses
    assert len(turns) >= 1
    for turn in turns:
        angle = np.degrees(float(geodesic_angle(turn.pose.rotation(), est.pose.rotation())))
        assert angle > 90  # a distinct answer, not the answer again
        # the same box in depth: the turn is one of the box's symmetries
        assert float(add_s(box.model_points, turn.pose, box.truth)) < 0.006
        assert 0 < turn.weight <= 1 and turn.score > 0.5
        assert set(turn.as_dict()) >= {"pose", "axis", "angle_deg", "weight"}
    # the covariance holds them: a rotation sigma of the order of the turn about some axis
    rotation_sigma = np.sqrt(np.diag(est.covariance)[3:])
    assert np.nanmax(rotation_sigma) > np.radians(45)


def test_a_declared_symmetry_leaves_no_equivalent_pose(box):
    est = jr.estimate_pose(box.frame, box.model_points, symmetry=box.symmetry)
    assert est.success, est.reason
    assert est.equivalent_poses == ()
    assert np.sqrt(np.diag(est.covariance)[3:]).max() < np.radians(5)
