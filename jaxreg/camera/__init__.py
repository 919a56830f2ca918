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
from jaxreg.core._lazy import submodules

__getattr__ = submodules(__name__)  # jaxreg.camera.<module> without importing it first
