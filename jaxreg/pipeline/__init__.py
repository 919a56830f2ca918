"""Pixels to pose: segment (table plane, Euclidean clusters, prompts; or the caller's own
mask) -> lift (depth pixels to base-frame points, filters, downsampling) -> register
(multi-start coarse search, refinement, the evidence that can refuse, covariance), behind
``estimate_pose`` (``estimate_poses``: many frames, one per core at a time); each stage's
evidence is a typed record (``PoseEstimate.stages``); :func:`track` follows an object from
frame to frame without segmentation.

May import every package above it: core, geometry, uncertainty, search, registration, camera.
"""

from jaxreg.pipeline.batch import estimate_poses as estimate_poses
from jaxreg.pipeline.estimate import (
    STAGES as STAGES,
    PoseEstimate as PoseEstimate,
    estimate_pose as estimate_pose,
)
from jaxreg.pipeline.track import track as track
