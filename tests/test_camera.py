"""The camera model: projection and distortion against OpenCV, undistortion as its inverse,
and the projection and pose Jacobians against central differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3

from jaxreg.camera import (
    pose_jacobian,
    project,
    projection_jacobian,
    reprojection_error,
    undistort_points,
)

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.28, 0.09, 1.2e-3, -8e-4, -0.02])


@pytest.mark.parametrize("ncoef", [4, 5])
def test_project_matches_opencv_with_distortion(x64, ncoef):
    cv2 = pytest.importorskip("cv2", reason="OpenCV (the peers extra) is not installed")
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.3, 0.3, (50, 2)), rng.uniform(0.4, 1.5, 50)])
    ours = np.asarray(project(points, K, DIST[:ncoef]))
    ref, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, DIST[:ncoef])
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-8)
    # OpenCV has no skew; ours adds K[0, 1] * y'' to u.
    K_skew = K.copy()
    K_skew[0, 1] = 0.7
    skewed = np.asarray(project(points, K_skew, DIST[:ncoef]))
    distorted_y = (ours[:, 1] - K[1, 2]) / K[1, 1]
    np.testing.assert_allclose(skewed[:, 0] - ours[:, 0], 0.7 * distorted_y, atol=1e-9)


def test_undistort_inverts_projection(x64):
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.4, 0.4, (2, 3, 20, 2))  # leading batch axes
    points = np.concatenate([xy, np.ones((2, 3, 20, 1))], axis=-1)
    np.testing.assert_allclose(undistort_points(project(points, K, DIST), K, DIST), xy, atol=1e-10)
    np.testing.assert_allclose(undistort_points(project(points, K), K), xy, atol=1e-12)


def test_bad_dist_coeffs_raise():
    with pytest.raises(ValueError, match="4 or 5 entries"):
        project(np.ones((3, 3)), K, np.zeros(3))


@jax.jit
def _jacobians_and_differences(cam, pose, obj, h):
    """Analytic Jacobians and central differences of `project` and of the pixels under a right
    perturbation of the pose, all in one compiled call."""
    J = projection_jacobian(cam, K, DIST)
    steps = jnp.eye(3, dtype=cam.dtype) * h
    shift = steps.reshape(3, *(1,) * (cam.ndim - 1), 3)
    fd = (project(cam + shift, K, DIST) - project(cam - shift, K, DIST)) / (2 * h)
    Jp = pose_jacobian(pose, obj, K, DIST)

    def pixels(tangent):
        T = pose @ SE3.exp(tangent)  # first order is all a central difference sees
        R, t = T.rotation().as_matrix(), T.translation()
        return project(jnp.einsum("...ij,...nj->...ni", R, obj) + t[..., None, :], K, DIST)

    tangents = jnp.eye(6, dtype=cam.dtype) * h
    batch = pose.get_batch_axes()
    fdp = jax.vmap(
        lambda e: (
            (pixels(jnp.broadcast_to(e, (*batch, 6))) - pixels(jnp.broadcast_to(-e, (*batch, 6))))
            / (2 * h)
        )
    )(tangents)
    return J, jnp.moveaxis(fd, 0, -1), Jp, jnp.moveaxis(fdp, 0, -1), pixels(jnp.zeros(6))


def test_jacobians_and_reprojection_error(x64):
    batch = (3, 2)
    rng = np.random.default_rng(2)
    n = 5
    cam = np.concatenate(
        [rng.uniform(-0.2, 0.2, (*batch, n, 2)), rng.uniform(0.5, 1.0, (*batch, n, 1))], -1
    )
    pose = SE3.from_rotation_and_translation(
        SO3.exp(jnp.asarray(rng.normal(scale=0.3, size=(*batch, 3)))),
        jnp.asarray(np.broadcast_to([0.01, -0.02, 0.6], (*batch, 3))),
    )
    obj = rng.uniform(-0.05, 0.05, (*batch, n, 3))
    J, fd, Jp, fdp, pixels = _jacobians_and_differences(cam, pose, obj, 1e-6)
    assert J.shape == (*batch, n, 2, 3) and Jp.shape == (*batch, n, 2, 6)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(Jp, fdp, rtol=1e-6, atol=1e-4)
    observed = np.asarray(pixels) + np.array([3.0, 4.0])
    np.testing.assert_allclose(reprojection_error(pose, obj, observed, K, DIST), 5.0, rtol=1e-12)
