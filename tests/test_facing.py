"""ICP from a viewpoint: a source point seen by a sensor is paired only with target points
whose outward normal faces that sensor, so the back faces of a thin wall take no pairs (and
the pipeline registers a thin-walled model's outer face without the pull toward the camera);
``query_nearest``'s mask, which it is built on."""

import jax
import numpy as np
import pytest
from scipy.stats import chi2

import jaxreg as jr
from jaxreg.search.neighbors import build_grid, knn, query_nearest
from jaxreg.synth import StereoSensor, surface_samples, tabletop_scene

WALL = 0.003  # metres between a plate's two faces


def _thin_corner(rng, per_face=1500):
    """Three perpendicular plates ``WALL`` thick meeting at the origin (a hollow box's corner
    seen from outside): each plate's outer face on a coordinate plane (normal toward -axis)
    and its inner face ``WALL`` inside it (normal toward +axis). Returns points ``(6 F, 3)``,
    outward normals, and which rows are outer faces."""
    points, normals, outer = [], [], []
    for axis in range(3):
        for depth, sign in ((0.0, -1.0), (WALL, 1.0)):
            p = rng.uniform(0.0, 0.08, (per_face, 3))
            p[:, axis] = depth
            n = np.zeros((per_face, 3))
            n[:, axis] = sign
            points.append(p), normals.append(n), outer.append(np.full(per_face, sign < 0))
    return (
        np.concatenate(points).astype(np.float32),
        np.concatenate(normals).astype(np.float32),
        np.concatenate(outer),
    )


@pytest.fixture(scope="module")
def corner():
    rng = np.random.default_rng(3)
    target, normals, outer = _thin_corner(rng)
    eye = np.array([-1.0, -1.0, -1.0], np.float32)  # the sensor sees the outer faces
    seen = target[outer][::3]
    ray = seen - eye
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    source = (seen + rng.normal(0.0, 0.003, (len(seen), 1)) * ray).astype(np.float32)
    return source, target, normals, eye, outer


# The registration of the corner's source from its sensor (point-to-plane, 1 cm pairs).
OPTIONS = dict(method="point_to_plane", max_correspondence_distance=0.01, max_iterations=40)


@pytest.fixture(scope="module")
def facing(corner):
    """The corner's source registered from its sensor's viewpoint, pairs found on the grid."""
    source, target, normals, eye, _ = corner
    return jr.icp(source, target, target_normals=normals, viewpoint=eye, **OPTIONS)


def _shift_toward_eye(result, eye):
    """How far (metres) the registration moved the source away from the sensor along the
    corner's diagonal: the data placed deeper into the wall."""
    direction = -eye / np.linalg.norm(eye)
    return float(np.asarray(result.pose.translation()) @ direction)


def test_a_viewpoint_removes_the_pull_of_a_thin_walls_back_face(corner, facing):
    source, target, normals, eye, _ = corner
    plain = jr.icp(source, target, target_normals=normals, **OPTIONS)
    # the noise carries a share of the points nearer the inner face: matched to it, they
    # drag the data into the wall
    assert _shift_toward_eye(plain, eye) > 5e-4
    assert abs(_shift_toward_eye(facing, eye)) < 2e-4
    assert bool(facing.converged)
    matched = np.asarray(facing.correspondences)
    _, _, _, _, outer = corner
    assert np.all(outer[matched[matched < len(target)]])  # only outer faces were paired


def test_rows_outside_viewpoint_rows_may_match_any_face(corner):
    _, target, normals, eye, outer = corner
    away = (~outer) & (np.sort(target, axis=1)[:, 1] > 0.01)  # 1 cm from the other plates
    inner = target[away][:50] + np.float32(1e-4) * normals[away][:50]  # on back faces
    options = dict(
        method="point_to_plane", target_normals=normals, max_correspondence_distance=0.002,
        max_iterations=1, viewpoint=eye,
    )  # fmt: skip
    seen = jr.icp(inner, target, **options)
    told = jr.icp(inner, target, viewpoint_rows=np.zeros(50, bool), **options)
    assert np.all(np.asarray(seen.correspondences) == len(target))  # a back face: no pair
    index = np.asarray(told.correspondences)
    assert np.all(index < len(target)) and not np.any(outer[index])


def test_brute_force_and_the_grid_pair_the_same_faces(corner, facing):
    """Traced in the target, ICP pairs by blocked brute force: the same faces as the grid."""
    source, target, normals, eye, _ = corner
    by_grid = facing
    traced = jax.jit(lambda t, n: jr.icp(source, t, target_normals=n, viewpoint=eye, **OPTIONS))
    by_brute = traced(target, normals)
    same = np.asarray(by_grid.correspondences) == np.asarray(by_brute.correspondences)
    assert same.mean() > 0.99  # float32 ties may go either way
    np.testing.assert_allclose(
        np.asarray(by_grid.pose.wxyz_xyz), np.asarray(by_brute.pose.wxyz_xyz), atol=1e-5
    )


def test_query_nearest_with_a_mask_answers_only_allowed_rows():
    rng = np.random.default_rng(0)
    target = rng.uniform(-0.05, 0.05, (2000, 3)).astype(np.float32)
    queries = rng.uniform(-0.05, 0.05, (500, 3)).astype(np.float32)
    allowed = rng.random(2000) < 0.5
    grid = build_grid(target, 0.02)
    index, sq, valid = (np.asarray(a) for a in query_nearest(grid, queries, 0.02, mask=allowed))
    assert np.all(allowed[index[valid]])
    found = knn(queries, target, 1, max_distance=0.02, mask=allowed)
    brute, brute_sq = np.asarray(found[0]), np.asarray(found[1])
    plain = np.asarray(query_nearest(grid, queries, 0.02)[0])
    exact = allowed[plain]  # the nearest point overall is allowed: the answer is exact
    assert exact.sum() > 100
    np.testing.assert_allclose(sq[exact], brute_sq[exact, 0], rtol=1e-4)
    free = np.asarray(
        query_nearest(grid, queries, 0.02, mask=allowed, mask_queries=np.zeros(500, bool))[0]
    )
    np.testing.assert_array_equal(free, plain)
    assert brute.shape == (500, 1)


def test_the_pipeline_registers_a_mugs_outer_face_not_its_wall():
    """A mug (a 4 mm wall) given with its mesh's outward normals: the answer is not pulled
    toward the camera (without the viewpoint this frame's answer came back 4 mm nearer the
    camera, outside its bars), and its 95% region holds the truth."""
    scene = tabletop_scene(9602, object="mug")
    points, normals = surface_samples(scene.model, 20000)
    estimate = jr.estimate_pose(
        scene.frame, points, model_normals=normals, symmetry=scene.symmetry,
        depth_noise=StereoSensor.d435().depth_noise(scene.frame.intrinsics),
    )  # fmt: skip
    assert estimate.success, estimate.reason
    truth = np.asarray(scene.truth.as_matrix(), np.float64)
    error = np.asarray(estimate.pose.translation()) - truth[:3, 3]
    toward = np.asarray(scene.frame.base_T_camera.translation()) - truth[:3, 3]
    toward[2] = 0.0  # the table holds the height
    assert abs(error @ toward / np.linalg.norm(toward)) < 1e-3
    delta = np.asarray((estimate.pose.inverse() @ scene.truth).log(), np.float64)
    covariance = np.asarray(estimate.covariance, np.float64)
    fixed = np.isfinite(np.diag(covariance))
    block = covariance[np.ix_(fixed, fixed)]
    distance = delta[fixed] @ np.linalg.solve(block, delta[fixed])
    assert distance < chi2.ppf(0.95, fixed.sum())


@pytest.mark.parametrize(
    "bad, message",
    [
        (dict(method="point_to_point", viewpoint=np.zeros(3)), "point_to_plane"),
        (dict(viewpoint=np.zeros(2)), r"shape \(3,\)"),
        (dict(viewpoint=np.zeros(3), viewpoint_rows=np.ones(3, bool)), "viewpoint_rows"),
        (dict(viewpoint_rows=np.ones(len(range(40)), bool)), "needs a viewpoint"),
    ],
)
def test_bad_viewpoints_raise(bad, message):
    rng = np.random.default_rng(2)
    source = rng.normal(size=(40, 3)).astype(np.float32)
    options = dict(method="point_to_plane", target_normals=np.tile([0, 0, 1.0], (40, 1)))
    with pytest.raises(ValueError, match=message):
        jr.icp(source, source, **{**options, **bad})
