"""Projective data association (``jr.ProjectiveAssociation``): ICP against an organized cloud,
each source point matched in a window around its pixel, against the grid's nearest
neighbours on the same clouds."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3

import jaxreg as jr
from jaxreg.geometry.lie import se3_exp

WIDTH, HEIGHT = 96, 72


def _surface():
    """An organized cloud in its camera's frame: a wavy sheet ~0.6 m away (all six degrees
    of freedom constrained), NaN in a hole; its intrinsics."""
    intrinsics = jr.Intrinsics(110.0, 110.0, (WIDTH - 1) / 2, (HEIGHT - 1) / 2, WIDTH, HEIGHT)
    rays = np.asarray(intrinsics.pixel_rays(), np.float64)
    x, y = rays[..., 0], rays[..., 1]
    depth = 0.6 + 0.04 * np.sin(9 * x + 1) * np.cos(7 * y) + 0.05 * x + 0.03 * y
    points = rays * depth[..., None]
    points[30:36, 40:50] = np.nan  # a hole: no depth there
    return intrinsics, points.astype(np.float32)


def _offset():
    return se3_exp(jnp.array([0.004, -0.003, 0.002, 0.02, -0.015, 0.01], jnp.float32))


@pytest.fixture(scope="module")
def scene():
    intrinsics, points = _surface()
    normals = np.asarray(jr.organized_normals(points))
    # the source: every second pixel's point of the central part, moved off the truth
    source = points[8:-8:2, 8:-8:2].reshape(-1, 3)
    source = source[np.all(np.isfinite(source), 1)]
    truth = _offset()  # target ~ truth @ source_moved
    moved = np.asarray(truth.inverse() @ jnp.asarray(source))
    return intrinsics, points, normals, moved, truth


def _error(pose: SE3, truth: SE3) -> tuple[float, float]:
    delta = np.asarray((truth.inverse() @ pose).log())
    return float(np.linalg.norm(delta[:3])), float(np.degrees(np.linalg.norm(delta[3:])))


def test_point_to_plane_finds_the_truth_as_the_grid_does(scene):
    intrinsics, points, normals, source, truth = scene
    association = jr.ProjectiveAssociation(intrinsics)
    options = jr.ICPOptions(
        method="point_to_plane", max_correspondence_distance=0.02, max_iterations=30
    )
    projective = jr.icp(
        source, points, options=options, target_normals=normals, association=association
    )
    flat, flat_normals = points.reshape(-1, 3), normals.reshape(-1, 3)
    grid = jr.icp(source, flat, options=options, target_normals=flat_normals)
    assert projective.status == jr.ICPStatus.success, projective.status
    for result in (projective, grid):
        translation, angle = _error(result.pose, truth)
        assert translation < 1e-4 and angle < 0.01, (translation, angle)
    # at the answer the window holds each point's nearest target point: the same pairs
    same = np.asarray(projective.correspondences) == np.asarray(grid.correspondences)
    assert same.mean() > 0.95, same.mean()
    assert abs(float(projective.inlier_fraction) - float(grid.inlier_fraction)) < 0.01


def test_rows_or_image_give_one_answer(scene):
    intrinsics, points, normals, source, _ = scene
    kwargs = dict(method="point_to_plane", association=jr.ProjectiveAssociation(intrinsics))
    image = jr.icp(source, points, target_normals=normals, **kwargs)
    rows = jr.icp(source, points.reshape(-1, 3), target_normals=normals.reshape(-1, 3), **kwargs)
    np.testing.assert_array_equal(image.pose.wxyz_xyz, rows.pose.wxyz_xyz)


def test_a_camera_away_from_the_target_frame(scene):
    """Target in a base frame: ``target_T_camera`` carries the projection."""
    intrinsics, points, normals, source, truth = scene
    base_T_camera = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(0.3, -0.2, 1.0), jnp.array([0.2, -0.1, 0.5])
    )
    rotation = np.asarray(base_T_camera.rotation().as_matrix())
    in_base = points @ rotation.T + np.asarray(base_T_camera.translation())
    normals_base = normals @ rotation.T
    association = jr.ProjectiveAssociation(intrinsics, base_T_camera)
    start = base_T_camera  # source (camera frame) into the base frame
    result = jr.icp(
        source, in_base, start, method="point_to_plane", target_normals=normals_base,
        association=association, max_iterations=30,
    )  # fmt: skip
    translation, angle = _error(base_T_camera.inverse() @ result.pose, truth)
    assert translation < 1e-4 and angle < 0.01, (translation, angle)


def test_a_source_outside_the_image_has_no_pairs(scene):
    intrinsics, points, normals, source, _ = scene
    far = SE3.from_translation(jnp.array([5.0, 0.0, 0.0]))  # every point left of the image
    result = jr.icp(
        source, points, far, method="point_to_plane", target_normals=normals,
        association=jr.ProjectiveAssociation(intrinsics),
    )  # fmt: skip
    assert result.status == jr.ICPStatus.too_few_correspondences
    assert int(result.num_inliers) == 0
    behind = SE3.from_translation(jnp.array([0.0, 0.0, -2.0]))  # behind the camera
    result = jr.icp(
        source, points, behind, method="point_to_plane", target_normals=normals,
        association=jr.ProjectiveAssociation(intrinsics),
    )  # fmt: skip
    assert result.status == jr.ICPStatus.too_few_correspondences


def test_the_gradient_follows_the_target(scene):
    """Shifting the organized target by ``d`` shifts the answer's translation by ``d``: the
    implicit derivative through the projective pairs is the identity there."""
    intrinsics, points, normals, source, truth = scene
    association = jr.ProjectiveAssociation(intrinsics)

    def translation(shift):
        result = jr.icp(
            source, jnp.asarray(points) + shift, truth, method="point_to_plane",
            target_normals=normals, association=association, max_iterations=10,
        )  # fmt: skip
        return result.pose.translation()

    jacobian = jax.jacfwd(translation)(jnp.zeros(3))
    np.testing.assert_allclose(np.asarray(jacobian), np.eye(3), atol=2e-3)


def test_point_to_point_and_a_wider_window(scene):
    intrinsics, points, _, source, truth = scene
    small = SE3(jnp.asarray(truth.wxyz_xyz)) @ se3_exp(jnp.array([0.001, 0, 0, 0, 0, 0.002]))
    result = jr.icp(
        source, points, small, association=jr.ProjectiveAssociation(intrinsics, window=2),
        max_iterations=60, max_correspondence_distance=0.01,
    )  # fmt: skip
    translation, angle = _error(result.pose, truth)
    assert translation < 5e-4 and angle < 0.05, (translation, angle)


def test_bad_requests(scene):
    intrinsics, points, normals, source, _ = scene
    association = jr.ProjectiveAssociation(intrinsics)
    with pytest.raises(ValueError, match="one row per pixel"):
        jr.icp(source, points[:-1], association=association)
    with pytest.raises(ValueError, match="one row per pixel"):
        jr.icp(
            source, points, method="point_to_plane", target_normals=normals[:, :-1],
            association=association,
        )  # fmt: skip
    flat = points.reshape(-1, 3)
    grid = jr.build_grid(np.nan_to_num(flat, nan=1e3), 0.02)
    with pytest.raises(ValueError, match="give one"):
        jr.icp(source, flat, association=association, neighbors=grid)
    with pytest.raises(TypeError, match="ProjectiveAssociation"):
        jr.icp(source, flat, association="projective")
    with pytest.raises(TypeError, match="Intrinsics"):
        jr.ProjectiveAssociation(np.eye(3))
    with pytest.raises(ValueError, match="window"):
        jr.ProjectiveAssociation(intrinsics, window=-1)


def test_organized_normals():
    intrinsics, points = _surface()
    flat = np.asarray(intrinsics.pixel_rays()) * 0.5  # the plane z = 0.5
    normals = np.asarray(jr.organized_normals(flat))
    np.testing.assert_allclose(normals, np.broadcast_to([0, 0, -1.0], normals.shape), atol=1e-5)
    normals = np.asarray(jr.organized_normals(points))
    unit = np.linalg.norm(normals, axis=-1)
    inside = np.isfinite(points).all(-1)
    assert np.all(np.abs(unit[inside] - 1) < 1e-4)  # one-sided differences at the hole's rim
    assert np.all(unit[~inside] == 0)
    assert np.all(np.einsum("hwi,hwi->hw", normals, -np.nan_to_num(points))[inside] > 0)
    with pytest.raises(ValueError, match="H, W, 3"):
        jr.organized_normals(points.reshape(-1, 3))
