"""jaxreg: differentiable, batched 6-DOF pose estimation and point-cloud registration in JAX.

The public names below are re-exported from one module each; see those modules for the
conventions (poses map source/model into target/scene coordinates, tangents are jaxlie's
``(vx, vy, vz, wx, wy, wz)``, covariances are of the right perturbation).

``import jaxreg`` loads none of them: each name (and each subpackage, ``jaxreg.io``,
``jaxreg.pipeline``, ...) is imported on first use, so a script that calls ``jaxreg.icp`` loads
the registration code and what it needs, not the pipeline, the camera models or scipy. Nothing
here changes JAX's configuration; :func:`enable_compilation_cache` is for the caller to call.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

# Each module and the public names it defines, re-exported here.
_EXPORTS = {
    "jaxreg.camera.model": (
        "Intrinsics", "RGBDFrame", "apply_intrinsics", "distort", "pose_jacobian", "project",
        "projection_jacobian", "reprojection_error", "undistort_points",
    ),
    "jaxreg.camera.pnp": (
        "PlanarPnPResult", "PnPResult", "PnPStatus", "solve_pnp", "solve_pnp_planar",
    ),
    "jaxreg.camera.tags": ("detect_tags", "tag_object_points"),
    "jaxreg.core.compilation": ("default_cache_folder", "enable_compilation_cache"),
    "jaxreg.geometry.alignment": ("Alignment", "AlignmentStatus", "align", "kabsch", "umeyama"),
    "jaxreg.geometry.eigen": ("eigh3", "jacobi_eigh"),
    "jaxreg.geometry.bop_metrics": (
        "BopRecall", "average_recall", "bop_symmetry_transforms", "correct", "mspd", "mssd", "vsd",
    ),
    "jaxreg.geometry.kernels": (
        "L2", "AbstractRobustKernel", "Cauchy", "GemanMcClure", "Huber", "Tukey", "Welsch",
        "trim_mask",
    ),
    "jaxreg.geometry.lie": (
        "SE3", "SO3", "adjoint_transport", "covariance_from_open3d", "covariance_to_open3d",
        "geodesic_angle", "random_rotations", "rotation_angle", "rotation_grid",
        "rotation_grid_around", "se3_exp", "se3_from_matrix", "se3_to_matrix", "so3_from_matrix",
        "tangent_from_open3d", "tangent_to_open3d",
    ),
    "jaxreg.geometry.means": ("chordal_mean", "karcher_mean"),
    "jaxreg.geometry.metrics": (
        "Symmetry", "add", "add_s", "canonicalise", "pose_error", "rotation_error",
    ),
    "jaxreg.pipeline.batch": ("estimate_poses",),
    "jaxreg.pipeline.estimate": ("PoseEstimate", "estimate_pose", "visibility"),
    "jaxreg.pipeline.records": (
        "Alternatives", "Candidate", "CoarseSearch", "EquivalentPose", "LiftedSegment",
        "LiftRecord", "MeasuredView", "RegisterRecord", "Registration", "Segmented",
        "SegmentRecord",
    ),
    "jaxreg.pipeline.segment": (
        "Clusters", "Segmentation", "SegmentStatus", "TablePlane", "choose_cluster",
        "cluster_mask", "euclidean_clusters", "fit_plane", "segment_frame",
    ),
    "jaxreg.pipeline.settings": (
        "LiftSettings", "PipelineSettings", "RegisterSettings", "SegmentSettings",
    ),
    "jaxreg.pipeline.track": ("track",),
    "jaxreg.registration.icp": (
        "ICPOptions", "ICPStatus", "RegistrationResult", "best_index", "icp", "icp_covariance",
        "init_spread", "multistart_icp", "pca_inits", "perturbed_inits", "rotation_inits",
        "select_best",
    ),
    "jaxreg.registration.projective": ("ProjectiveAssociation", "organized_normals"),
    "jaxreg.registration.ransac": (
        "RansacResult", "RansacStatus", "ransac_iterations", "ransac_registration",
    ),
    "jaxreg.registration.robust": ("RobustAlignment", "RobustStatus", "robust_kabsch"),
    "jaxreg.search.features": ("FPFH", "FeatureMatches", "fpfh", "match_features"),
    "jaxreg.search.neighbors": (
        "NeighborGrid", "build_grid", "knn", "pad_grid", "query_nearest", "radius_search",
        "validate_grid", "voxel_downsample",
    ),
    "jaxreg.search.normals": (
        "NormalEstimate", "NormalStatus", "estimate_normals", "estimate_normals_with_curvature",
    ),
    "jaxreg.uncertainty": (
        "AbstractPointNoise", "DepthNoise", "ErrorBudget", "GraspPrediction", "GroupStatistics",
        "IsotropicNoise", "PointCovariance", "PoseStatistics", "error_budget", "grasp_axis",
        "grasp_margin", "grasp_prediction", "grasp_success_probability", "pose_statistics",
    ),
    "jaxreg.uncertainty.budget": (
        "PoseBudget", "lateral_sigma", "mahalanobis", "region_contains",
    ),
}  # fmt: skip
_SUBPACKAGES = (
    "camera", "cli", "core", "geometry", "io", "pipeline", "registration", "search", "studies",
    "synth", "uncertainty",
)  # fmt: skip
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}

__all__ = sorted(_MODULE_OF)


def __getattr__(name: str):
    if name in _MODULE_OF:
        value = getattr(importlib.import_module(_MODULE_OF[name]), name)
    elif name in _SUBPACKAGES:
        value = importlib.import_module(f"jaxreg.{name}")
    else:
        raise AttributeError(f"module 'jaxreg' has no attribute {name!r}")
    globals()[name] = value  # later lookups find it without this call
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_MODULE_OF, *_SUBPACKAGES})


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
    from jaxreg.core.compilation import (
        default_cache_folder as default_cache_folder,
        enable_compilation_cache as enable_compilation_cache,
    )
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
        bop_symmetry_transforms as bop_symmetry_transforms,
        correct as correct,
        mspd as mspd,
        mssd as mssd,
        vsd as vsd,
    )
    from jaxreg.geometry.eigen import eigh3 as eigh3, jacobi_eigh as jacobi_eigh
    from jaxreg.geometry.kernels import (
        L2 as L2,
        AbstractRobustKernel as AbstractRobustKernel,
        Cauchy as Cauchy,
        GemanMcClure as GemanMcClure,
        Huber as Huber,
        Tukey as Tukey,
        Welsch as Welsch,
        trim_mask as trim_mask,
    )
    from jaxreg.geometry.lie import (
        SE3 as SE3,
        SO3 as SO3,
        adjoint_transport as adjoint_transport,
        covariance_from_open3d as covariance_from_open3d,
        covariance_to_open3d as covariance_to_open3d,
        geodesic_angle as geodesic_angle,
        random_rotations as random_rotations,
        rotation_angle as rotation_angle,
        rotation_grid as rotation_grid,
        rotation_grid_around as rotation_grid_around,
        se3_exp as se3_exp,
        se3_from_matrix as se3_from_matrix,
        se3_to_matrix as se3_to_matrix,
        so3_from_matrix as so3_from_matrix,
        tangent_from_open3d as tangent_from_open3d,
        tangent_to_open3d as tangent_to_open3d,
    )
    from jaxreg.geometry.means import chordal_mean as chordal_mean, karcher_mean as karcher_mean
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
    from jaxreg.registration.icp import (
        ICPOptions as ICPOptions,
        ICPStatus as ICPStatus,
        RegistrationResult as RegistrationResult,
        best_index as best_index,
        icp as icp,
        icp_covariance as icp_covariance,
        init_spread as init_spread,
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
        knn as knn,
        pad_grid as pad_grid,
        query_nearest as query_nearest,
        radius_search as radius_search,
        validate_grid as validate_grid,
        voxel_downsample as voxel_downsample,
    )
    from jaxreg.search.normals import (
        NormalEstimate as NormalEstimate,
        NormalStatus as NormalStatus,
        estimate_normals as estimate_normals,
        estimate_normals_with_curvature as estimate_normals_with_curvature,
    )
    from jaxreg.uncertainty import (
        AbstractPointNoise as AbstractPointNoise,
        DepthNoise as DepthNoise,
        ErrorBudget as ErrorBudget,
        GraspPrediction as GraspPrediction,
        GroupStatistics as GroupStatistics,
        IsotropicNoise as IsotropicNoise,
        PointCovariance as PointCovariance,
        PoseStatistics as PoseStatistics,
        error_budget as error_budget,
        grasp_axis as grasp_axis,
        grasp_margin as grasp_margin,
        grasp_prediction as grasp_prediction,
        grasp_success_probability as grasp_success_probability,
        pose_statistics as pose_statistics,
    )
    from jaxreg.uncertainty.budget import (
        PoseBudget as PoseBudget,
        lateral_sigma as lateral_sigma,
        mahalanobis as mahalanobis,
        region_contains as region_contains,
    )
