"""Cameras: intrinsics, distortion, projection and its Jacobians, ``RGBDFrame``; PnP (general,
planar IPPE with its two-fold ambiguity, Levenberg-Marquardt refinement, covariance) and
fiducial tags.

A camera pose ``camera_T_object`` maps object coordinates into the camera frame (x right,
y down, z forward). May import :mod:`jaxreg.core` and :mod:`jaxreg.geometry`.
"""

from jaxreg.camera.model import (
    Intrinsics as Intrinsics,
    RGBDFrame as RGBDFrame,
    apply_intrinsics as apply_intrinsics,
    distort as distort,
    pose_jacobian as pose_jacobian,
    project as project,
    projection_jacobian as projection_jacobian,
    reprojection_error as reprojection_error,
    undistort_points as undistort_points,
)
from jaxreg.core._lazy import exports

# PnP's and the tags' names, each module imported on first use; jaxreg.camera.<module> too.
__getattr__, __dir__ = exports(
    __name__,
    {
        "jaxreg.camera.pnp": (
            "PlanarPnPResult", "PnPResult", "PnPStatus", "solve_pnp", "solve_pnp_planar",
        ),
        "jaxreg.camera.tags": ("detect_tags", "tag_object_points"),
    },
)  # fmt: skip
