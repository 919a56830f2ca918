"""Tag corners in the tag frame, and OpenCV's ArUco detection returning them in that order."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SO3

from jaxreg.camera import project
from jaxreg.camera.tags import detect_tags, tag_object_points

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
TAG = 0.045
FACING = np.diag([1.0, -1.0, -1.0])  # tag z (out of its face) toward the camera, y up in image


def test_tag_object_points_are_a_square_on_z0_in_detector_order():
    corners = np.asarray(tag_object_points(TAG))
    assert corners.shape == (4, 3) and np.all(corners[:, 2] == 0.0)
    edges = np.roll(corners, -1, axis=0) - corners
    np.testing.assert_allclose(np.linalg.norm(edges, axis=1), TAG, rtol=1e-6)
    # top-left, top-right, bottom-right, bottom-left with y up: clockwise seen from +z
    assert np.cross(edges[0], edges[1])[2] < 0
    np.testing.assert_allclose(corners[0, :2], [-TAG / 2, TAG / 2], rtol=1e-6)


def test_detect_tags_returns_corners_in_object_order(x64):
    """A rendered ArUco tag is found, with corners at their projections (IPPE_SQUARE order)."""
    cv2 = pytest.importorskip("cv2", reason="OpenCV (the peers extra) is not installed")
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    side = 120
    marker = cv2.aruco.generateImageMarker(dictionary, 7, side)
    R = np.asarray(SO3.exp(jnp.array([0.4, 0.2, 0.3])).as_matrix()) @ FACING
    t = np.array([0.01, -0.02, 0.5])
    # marker pixel (a, b) -> tag plane (x, y): pixel edges at -0.5 and side - 0.5
    S = np.array(
        [
            [TAG / side, 0, -TAG / 2 + TAG / (2 * side)],
            [0, -TAG / side, TAG / 2 - TAG / (2 * side)],
            [0, 0, 1],
        ]
    )
    H = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ S
    # Render at 4x and average 4x4 blocks (low-res pixel i is high-res 4 i + 1.5): no aliasing.
    up = np.array([[4.0, 0.0, 1.5], [0.0, 4.0, 1.5], [0.0, 0.0, 1.0]])
    fine = cv2.warpPerspective(marker, up @ H, (2560, 1920), borderValue=255)
    image = cv2.resize(fine, (640, 480), interpolation=cv2.INTER_AREA)
    corners, ids = detect_tags(image, "DICT_4X4_50")
    assert ids.tolist() == [7]
    expected = jax.device_get(project(np.asarray(tag_object_points(TAG)) @ R.T + t, K))
    # OpenCV's sub-pixel refinement pulls the outer corners of a ~55 px tag ~0.25 px inward.
    np.testing.assert_allclose(corners[0], expected, atol=0.35)
    with pytest.raises(ValueError, match="unknown cv2.aruco dictionary"):
        detect_tags(image, "DICT_NOT_A_DICTIONARY")
    corners, ids = detect_tags(np.full((48, 64), 255, np.uint8))
    assert corners.shape == (0, 4, 2) and ids.shape == (0,)
