"""Square fiducial tags (ArUco, AprilTag): their corners in the tag frame, and detection.

A tag is the simplest planar PnP problem: four corners of known size on the tag's z = 0 plane.
`tag_object_points` gives those corners in the order detectors report them, `detect_tags`
finds them in an image with OpenCV's ArUco module (an optional peer: the rest of jaxreg never
needs it), and `jaxreg.solve_pnp_planar` turns each tag's corners into both candidate poses:

    corners, ids = jr.detect_tags(image, "DICT_4X4_50")          # (T, 4, 2), (T,)
    result = jr.solve_pnp_planar(jr.tag_object_points(0.045), corners, K)
    result.pose                                                   # camera_T_tag, batch (T,)
"""

from __future__ import annotations

from typing import Any

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

__all__ = ["detect_tags", "tag_object_points"]


def tag_object_points(tag_size: float) -> Float[Array, "4 3"]:
    """Corners `(4, 3)` of a square tag of side `tag_size` in its own frame (z = 0, z out of
    the front face, x right, y up), in the order ArUco detectors and
    `cv2.SOLVEPNP_IPPE_SQUARE` use: top-left, top-right, bottom-right, bottom-left as seen in
    the image."""
    h = 0.5 * tag_size
    return jnp.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def detect_tags(
    image: np.ndarray,
    dictionary: str | int | Any = "DICT_4X4_50",
    *,
    subpixel: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Detect ArUco/AprilTag markers with OpenCV (>= 4.7, optional `peers` extra).

    - `image`: `(H, W)` grayscale or `(H, W, 3)` BGR `uint8`.
    - `dictionary`: a `cv2.aruco` predefined dictionary name (e.g. "DICT_4X4_50",
      "DICT_APRILTAG_36h11"), its integer id, or a `cv2.aruco.Dictionary`.
    - `subpixel`: refine corners to sub-pixel accuracy (`CORNER_REFINE_SUBPIX`).

    Returns `corners` `(T, 4, 2)` float64 pixels in `tag_object_points` order and `ids` `(T,)`
    int (T = 0 when nothing is found). Host-only (numpy); not jittable. OpenCV's sub-pixel
    refinement places the outer corners of a ~50 px tag ~0.25 px inside the true ones (a ~1%
    scale bias, hence ~1% in depth); it is the detector's, not the solver's. Raises
    `ImportError` naming the extra when OpenCV is missing, `ValueError` for an unknown
    dictionary name.
    """
    try:
        import cv2
    except ImportError as err:
        raise ImportError(
            "detect_tags needs OpenCV: pip install 'jaxreg[peers]' (opencv-python-headless)"
        ) from err
    aruco = cv2.aruco
    if isinstance(dictionary, str):
        if not hasattr(aruco, dictionary):
            raise ValueError(f"unknown cv2.aruco dictionary {dictionary!r}")
        dictionary = getattr(aruco, dictionary)
    if isinstance(dictionary, (int, np.integer)):
        dictionary = aruco.getPredefinedDictionary(int(dictionary))
    params = aruco.DetectorParameters()
    if subpixel:
        params.cornerRefinementMethod = aruco.CORNER_REFINE_SUBPIX
    detector = aruco.ArucoDetector(dictionary, params)
    corners, ids, _ = detector.detectMarkers(np.asarray(image))
    if ids is None or len(corners) == 0:
        return np.zeros((0, 4, 2)), np.zeros((0,), dtype=int)
    return (
        np.stack([np.asarray(c, np.float64).reshape(4, 2) for c in corners]),
        np.asarray(ids, dtype=int).reshape(-1),
    )
