"""Pixels to pose: segment (table plane, Euclidean clusters, prompts; or the caller's own
mask) -> lift (depth pixels to base-frame points, filters, downsampling) -> register
(multi-start coarse search, refinement, the evidence that can refuse, covariance), behind
``estimate_pose`` (``estimate_poses``: many frames, one per core at a time); each stage's
evidence is a typed record (``PoseEstimate.stages``); :func:`track` follows an object from
frame to frame without segmentation.

May import every package above it: core, geometry, uncertainty, search, registration, camera.
"""

from jaxreg.core._lazy import exports
from jaxreg.pipeline.batch import estimate_poses as estimate_poses
from jaxreg.pipeline.estimate import (
    STAGES as STAGES,
    PoseEstimate as PoseEstimate,
    estimate_pose as estimate_pose,
    visibility as visibility,
)
from jaxreg.pipeline.records import (
    Alternatives as Alternatives,
    Candidate as Candidate,
    CoarseSearch as CoarseSearch,
    EquivalentPose as EquivalentPose,
    LiftedSegment as LiftedSegment,
    LiftRecord as LiftRecord,
    MeasuredView as MeasuredView,
    RegisterRecord as RegisterRecord,
    Registration as Registration,
    Segmented as Segmented,
    SegmentRecord as SegmentRecord,
)
from jaxreg.pipeline.segment import (
    Clusters as Clusters,
    Segmentation as Segmentation,
    SegmentStatus as SegmentStatus,
    TablePlane as TablePlane,
    choose_cluster as choose_cluster,
    cluster_mask as cluster_mask,
    euclidean_clusters as euclidean_clusters,
    fit_plane as fit_plane,
    segment_frame as segment_frame,
)
from jaxreg.pipeline.settings import (
    LiftSettings as LiftSettings,
    PipelineSettings as PipelineSettings,
    RegisterSettings as RegisterSettings,
    SegmentSettings as SegmentSettings,
)
from jaxreg.pipeline.track import track as track

# jaxreg.pipeline.<module> without importing it first; dir() lists the public names
__getattr__, __dir__ = exports(__name__, {})
