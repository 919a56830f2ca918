"""estimate_poses: the pipeline over several frames in one call, frames concurrently."""

import numpy as np
import pytest

from jaxreg.geometry.metrics import add_s
from jaxreg.pipeline import estimate_pose, estimate_poses
from jaxreg.synth._meshes import surface_points


@pytest.fixture(scope="module")
def scenes():
    from jaxreg.synth import tabletop_scene

    return [tabletop_scene(seed, object="box", distractors=0) for seed in (4, 5, 6)]


def test_each_frame_gets_the_answer_it_gets_alone(scenes):
    model = surface_points(scenes[0].model)
    symmetry = scenes[0].symmetry
    many = estimate_poses([s.frame for s in scenes], model, symmetry=symmetry)
    assert len(many) == 3
    for scene, est in zip(scenes, many, strict=True):
        alone = estimate_pose(scene.frame, model, symmetry=symmetry)
        assert est.success == alone.success and est.failed_stage == alone.failed_stage
        np.testing.assert_array_equal(est.pose.wxyz_xyz, alone.pose.wxyz_xyz)
        np.testing.assert_array_equal(est.covariance, alone.covariance)
        assert float(add_s(scene.model_points, est.pose, scene.truth)) < 0.005


def test_masks_are_one_per_frame_and_a_bad_frame_is_named(scenes):
    model = surface_points(scenes[0].model)
    frames = [s.frame for s in scenes[:2]]
    with pytest.raises(ValueError, match="one per frame: 1 masks, 2 frames"):
        estimate_poses(frames, model, masks=[scenes[0].mask])
    with pytest.raises(ValueError, match="masks="):
        estimate_poses(frames, model, mask=scenes[0].mask)
    empty = np.zeros_like(scenes[1].mask)
    with pytest.raises(ValueError, match="frame 1: the mask is empty"):
        estimate_poses(frames, model, masks=[scenes[0].mask, empty])
    assert estimate_poses([], model) == []
