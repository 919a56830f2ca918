"""jaxreg: differentiable, batched 6-DOF pose estimation and point-cloud registration in JAX.

The top level holds what a user calls: the solvers and their results, ``estimate_pose``,
``estimate_poses`` and ``track`` with ``PoseEstimate``, the metrics, the noise models and the
error budget. The rest is reached through its package: the pipeline's stage records and
segmentation steps through ``jaxreg.pipeline``, files through ``jaxreg.io``, synthetic scenes
through ``jaxreg.synth``, studies through ``jaxreg.studies``, and the building blocks of
geometry, search, registration, cameras and uncertainty through theirs
(``jaxreg.geometry.random_rotations``, ``jaxreg.camera.project``). Each name is re-exported
from one module; see it for the conventions (poses map source/model into target/scene
coordinates, tangents are jaxlie's ``(vx, vy, vz, wx, wy, wz)``, covariances are of the right
perturbation).

``import jaxreg`` loads none of them: each name (and each subpackage, ``jaxreg.io``,
``jaxreg.pipeline``, ...) is imported on first use, so a script that calls ``jaxreg.icp`` loads
the registration code and what it needs, not the pipeline, the camera models or scipy. Nothing
here changes JAX's configuration; :func:`enable_compilation_cache` is for the caller to call.
"""

from typing import TYPE_CHECKING

from jaxreg.core._lazy import exports as _exports

# Each module and the public names it defines, re-exported here.
_EXPORTS = {
    "jaxreg.camera.model": ("Intrinsics", "RGBDFrame"),
    "jaxreg.camera.pnp": (
        "PlanarPnPResult", "PnPResult", "PnPStatus", "solve_pnp", "solve_pnp_planar",
    ),
    "jaxreg.camera.tags": ("detect_tags", "tag_object_points"),
    "jaxreg.core.compilation": ("enable_compilation_cache",),
    "jaxreg.geometry.alignment": ("Alignment", "AlignmentStatus", "align", "kabsch", "umeyama"),
    "jaxreg.geometry.bop_metrics": ("BopRecall", "average_recall", "mspd", "mssd", "vsd"),
    "jaxreg.geometry.kernels": ("L2", "Cauchy", "GemanMcClure", "Huber", "Tukey", "Welsch"),
    "jaxreg.geometry.lie": ("SE3", "SO3", "adjoint_transport", "se3_exp"),
    "jaxreg.geometry.metrics": (
        "Symmetry", "add", "add_s", "canonicalise", "pose_error", "rotation_error",
    ),
    "jaxreg.pipeline.batch": ("estimate_poses",),
    "jaxreg.pipeline.estimate": ("PoseEstimate", "estimate_pose"),
    "jaxreg.pipeline.records": ("EquivalentPose",),
    "jaxreg.pipeline.settings": (
        "LiftSettings", "PipelineSettings", "RegisterSettings", "SegmentSettings",
    ),
    "jaxreg.pipeline.track": ("track",),
    "jaxreg.registration.icp": (
        "ICPOptions", "ICPStatus", "RegistrationResult", "icp", "icp_covariance", "multistart_icp",
        "pca_inits", "perturbed_inits", "rotation_inits", "select_best",
    ),
    "jaxreg.registration.projective": ("ProjectiveAssociation", "organized_normals"),
    "jaxreg.registration.ransac": (
        "RansacResult", "RansacStatus", "ransac_iterations", "ransac_registration",
    ),
    "jaxreg.registration.robust": ("RobustAlignment", "RobustStatus", "robust_kabsch"),
    "jaxreg.search.features": ("FPFH", "FeatureMatches", "fpfh", "match_features"),
    "jaxreg.search.neighbors": ("NeighborGrid", "build_grid", "voxel_downsample"),
    "jaxreg.search.normals": ("estimate_normals",),
    "jaxreg.uncertainty": (
        "DepthNoise", "ErrorBudget", "GraspPrediction", "IsotropicNoise", "PointCovariance",
        "PoseStatistics", "error_budget", "grasp_margin", "grasp_prediction",
        "grasp_success_probability", "pose_statistics",
    ),
    "jaxreg.uncertainty.budget": ("PoseBudget",),
}  # fmt: skip
_SUBPACKAGES = (
    "camera", "cli", "core", "geometry", "io", "pipeline", "registration", "search", "studies",
    "synth", "uncertainty",
)  # fmt: skip

__all__ = sorted(name for names in _EXPORTS.values() for name in names)
__getattr__, __dir__ = _exports(__name__, _EXPORTS)


if TYPE_CHECKING:  # what type checkers and editors see; the same names as _EXPORTS
    from jaxreg import (
        camera as camera,
        cli as cli,
        core as core,
        geometry as geometry,
        io as io,
        pipeline as pipeline,
        registration as registration,
        search as search,
        studies as studies,
        synth as synth,
        uncertainty as uncertainty,
    )
    from jaxreg.camera.model import Intrinsics as Intrinsics, RGBDFrame as RGBDFrame
    from jaxreg.camera.pnp import (
        PlanarPnPResult as PlanarPnPResult,
        PnPResult as PnPResult,
        PnPStatus as PnPStatus,
        solve_pnp as solve_pnp,
        solve_pnp_planar as solve_pnp_planar,
    )
    from jaxreg.camera.tags import (
        detect_tags as detect_tags,
        tag_object_points as tag_object_points,
    )
    from jaxreg.core.compilation import enable_compilation_cache as enable_compilation_cache
    from jaxreg.geometry.alignment import (
        Alignment as Alignment,
        AlignmentStatus as AlignmentStatus,
        align as align,
        kabsch as kabsch,
        umeyama as umeyama,
    )
    from jaxreg.geometry.bop_metrics import (
        BopRecall as BopRecall,
        average_recall as average_recall,
        mspd as mspd,
        mssd as mssd,
        vsd as vsd,
    )
    from jaxreg.geometry.kernels import (
        L2 as L2,
        Cauchy as Cauchy,
        GemanMcClure as GemanMcClure,
        Huber as Huber,
        Tukey as Tukey,
        Welsch as Welsch,
    )
    from jaxreg.geometry.lie import (
        SE3 as SE3,
        SO3 as SO3,
        adjoint_transport as adjoint_transport,
        se3_exp as se3_exp,
    )
    from jaxreg.geometry.metrics import (
        Symmetry as Symmetry,
        add as add,
        add_s as add_s,
        canonicalise as canonicalise,
        pose_error as pose_error,
        rotation_error as rotation_error,
    )
    from jaxreg.pipeline.batch import estimate_poses as estimate_poses
    from jaxreg.pipeline.estimate import (
        PoseEstimate as PoseEstimate,
        estimate_pose as estimate_pose,
    )
    from jaxreg.pipeline.records import EquivalentPose as EquivalentPose
    from jaxreg.pipeline.settings import (
        LiftSettings as LiftSettings,
        PipelineSettings as PipelineSettings,
        RegisterSettings as RegisterSettings,
        SegmentSettings as SegmentSettings,
    )
    from jaxreg.pipeline.track import track as track
    from jaxreg.registration.icp import (
        ICPOptions as ICPOptions,
        ICPStatus as ICPStatus,
        RegistrationResult as RegistrationResult,
        icp as icp,
        icp_covariance as icp_covariance,
        multistart_icp as multistart_icp,
        pca_inits as pca_inits,
        perturbed_inits as perturbed_inits,
        rotation_inits as rotation_inits,
        select_best as select_best,
    )
    from jaxreg.registration.projective import (
        ProjectiveAssociation as ProjectiveAssociation,
        organized_normals as organized_normals,
    )
    from jaxreg.registration.ransac import (
        RansacResult as RansacResult,
        RansacStatus as RansacStatus,
        ransac_iterations as ransac_iterations,
        ransac_registration as ransac_registration,
    )
    from jaxreg.registration.robust import (
        RobustAlignment as RobustAlignment,
        RobustStatus as RobustStatus,
        robust_kabsch as robust_kabsch,
    )
    from jaxreg.search.features import (
        FPFH as FPFH,
        FeatureMatches as FeatureMatches,
        fpfh as fpfh,
        match_features as match_features,
    )
    from jaxreg.search.neighbors import (
        NeighborGrid as NeighborGrid,
        build_grid as build_grid,
        voxel_downsample as voxel_downsample,
    )
    from jaxreg.search.normals import estimate_normals as estimate_normals
    from jaxreg.uncertainty import (
        DepthNoise as DepthNoise,
        ErrorBudget as ErrorBudget,
        GraspPrediction as GraspPrediction,
        IsotropicNoise as IsotropicNoise,
        PointCovariance as PointCovariance,
        PoseStatistics as PoseStatistics,
        error_budget as error_budget,
        grasp_margin as grasp_margin,
        grasp_prediction as grasp_prediction,
        grasp_success_probability as grasp_success_probability,
        pose_statistics as pose_statistics,
    )
    from jaxreg.uncertainty.budget import PoseBudget as PoseBudget
