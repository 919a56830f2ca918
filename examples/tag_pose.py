"""Pose of an ArUco tag from a synthetic camera image, with both planar candidates and error bars.

Renders a 45 mm DICT_4X4_50 tag at a known pose (0.55 m, tilted 25 degrees) into a blurred,
noisy 640x480 image, detects its corners with OpenCV's ArUco detector, and solves planar PnP:
both IPPE candidates refined by Levenberg-Marquardt, their reprojection errors, the ambiguity
ratio, the pose error against the truth and the first-order error bars for an assumed corner
noise. Needs OpenCV (the optional `peers` extra). Run: python examples/tag_pose.py
"""

import sys

import jax.numpy as jnp
import numpy as np
from jaxlie import SE3, SO3

from jaxreg import PnPStatus, detect_tags, solve_pnp_planar, tag_object_points

try:
    import cv2
except ImportError:
    sys.exit(
        "examples/tag_pose.py needs OpenCV: pip install 'jaxreg[peers]' (opencv-python-headless)"
    )

TAG_SIZE = 0.045  # metres, outer edge of the black border
TAG_ID = 7
CORNER_SIGMA_PX = 0.2  # assumed detector corner noise, per pixel coordinate
K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
WIDTH, HEIGHT = 640, 480


def render_tag(camera_T_tag: SE3, rng: np.random.Generator) -> np.ndarray:
    """A grey image with the tag (on a white card) seen at `camera_T_tag`, blurred and noisy."""
    side = 240  # marker texture size in pixels; the card adds a white margin of side / 4
    marker = cv2.aruco.generateImageMarker(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), TAG_ID, side
    )
    margin = side // 4
    card = cv2.copyMakeBorder(
        marker, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=255
    )
    # Card pixel (a, b) -> tag plane (x right, y up): the marker's outer edge, pixel edges at
    # margin - 0.5 and margin + side - 0.5, maps to -+TAG_SIZE / 2.
    scale = TAG_SIZE / side
    card_to_plane = np.array(
        [
            [scale, 0.0, -scale * (margin - 0.5) - TAG_SIZE / 2],
            [0.0, -scale, scale * (margin - 0.5) + TAG_SIZE / 2],
            [0.0, 0.0, 1.0],
        ]
    )
    M = np.asarray(camera_T_tag.as_matrix())
    plane_to_pixels = K @ np.column_stack([M[:3, 0], M[:3, 1], M[:3, 3]])
    # Render at 4x and average 4x4 blocks (pixel i of the image is 4 i + 1.5 at 4x).
    up = np.array([[4.0, 0.0, 1.5], [0.0, 4.0, 1.5], [0.0, 0.0, 1.0]])
    fine = cv2.warpPerspective(
        card, up @ plane_to_pixels @ card_to_plane, (4 * WIDTH, 4 * HEIGHT), borderValue=110
    )
    image = cv2.resize(fine, (WIDTH, HEIGHT), interpolation=cv2.INTER_AREA).astype(np.float64)
    image = cv2.GaussianBlur(image, (0, 0), 0.7) + rng.normal(0.0, 2.0, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)


def describe(pose: SE3) -> str:
    t_mm = np.asarray(pose.translation()) * 1e3
    rpy = np.rad2deg(np.asarray(pose.rotation().as_rpy_radians()))
    t = ", ".join(f"{v:7.2f}" for v in t_mm)
    r = ", ".join(f"{v:7.2f}" for v in rpy)
    return f"t = ({t}) mm, rpy = ({r}) deg"


def main():
    rng = np.random.default_rng(3)
    # Facing the camera (tag z toward it, y up in the image), tilted 25 degrees, turned 20.
    facing = SO3.from_matrix(jnp.diag(jnp.array([1.0, -1.0, -1.0])))
    rotation = SO3.from_x_radians(np.deg2rad(25.0)) @ facing @ SO3.from_z_radians(np.deg2rad(20.0))
    truth = SE3.from_rotation_and_translation(rotation, jnp.array([0.03, -0.02, 0.55]))

    image = render_tag(truth, rng)
    corners, ids = detect_tags(image, "DICT_4X4_50")
    if TAG_ID not in ids:
        sys.exit("tag not detected")
    pixels = corners[list(ids).index(TAG_ID)]
    print(f"detected tag {TAG_ID}; corners (px):\n{np.array2string(pixels, precision=2)}")

    result = solve_pnp_planar(tag_object_points(TAG_SIZE), pixels, K, sigma_px=CORNER_SIGMA_PX)
    print("\ncandidates (camera_T_tag), best first:")
    for i, candidate in enumerate((result.best, result.second)):
        rmse = float(candidate.reprojection_rmse_px)
        status = PnPStatus[candidate.status]
        print(f"  {i}: {describe(candidate.pose)}, rmse = {rmse:.3f} px, status: {status}")
    print(
        f"ambiguity ratio (rmse[1] / rmse[0]) = {float(result.ambiguity_ratio):.2f}, "
        f"candidates {float(result.separation_deg):.1f} deg apart"
    )

    best = result.best
    print(f"\ntruth: {describe(truth)}")
    error = best.pose.inverse() @ truth  # right perturbation: truth = estimate @ error
    t_err = (np.asarray(best.pose.translation()) - np.asarray(truth.translation())) * 1e3
    r_err = np.rad2deg(np.asarray(error.rotation().log()))
    t_sig = np.asarray(best.translation_sigma) * 1e3
    r_sig = np.asarray(best.rotation_sigma_deg)
    print(f"pose error vs truth and 1-sigma error bars for {CORNER_SIGMA_PX} px corner noise:")
    for axis, e, s in zip("xyz", t_err, t_sig, strict=True):
        print(f"  camera {axis}: {e:+7.3f} mm   (sigma {s:.3f} mm)")
    for axis, e, s in zip("xyz", r_err, r_sig, strict=True):
        print(f"  about tag {axis}: {e:+7.3f} deg  (sigma {s:.3f} deg)")
    print(
        f"depth sigma is {t_sig[2] / max(t_sig[:2]):.0f}x the in-plane sigma: a tag pins its "
        "position across the image far better than along the line of sight.\n"
        "The depth error also carries the detector's bias: OpenCV's sub-pixel refinement puts "
        "the outer corners of a ~50 px tag ~0.25 px inside the true ones, so the tag looks ~1% "
        "smaller, i.e. ~1% farther away."
    )


if __name__ == "__main__":
    main()
