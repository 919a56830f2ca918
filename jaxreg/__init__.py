"""jaxreg: differentiable, batched 6-DOF pose estimation and point-cloud registration in JAX.

The public names below are re-exported from one module each; see those modules for the
conventions (poses map source/model into target/scene coordinates, tangents are jaxlie's
``(vx, vy, vz, wx, wy, wz)``, covariances are of the right perturbation).
"""

from jaxreg import (
    camera as camera,
    core as core,
    geometry as geometry,
    io as io,
    pipeline as pipeline,
    registration as registration,
    search as search,
    uncertainty as uncertainty,
)
from jaxreg.camera.model import (
    Intrinsics as Intrinsics,
    RGBDFrame as RGBDFrame,
    project as project,
    reprojection_error as reprojection_error,
)
from jaxreg.camera.pnp import (
    PlanarPnPResult as PlanarPnPResult,
    PnPResult as PnPResult,
    PnPStatus as PnPStatus,
    solve_pnp as solve_pnp,
    solve_pnp_planar as solve_pnp_planar,
)
from jaxreg.camera.tags import detect_tags as detect_tags, tag_object_points as tag_object_points
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
    geodesic_angle as geodesic_angle,
    random_rotations as random_rotations,
    rotation_grid as rotation_grid,
    rotation_grid_around as rotation_grid_around,
    se3_exp as se3_exp,
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
from jaxreg.pipeline.estimate import PoseEstimate as PoseEstimate, estimate_pose as estimate_pose
from jaxreg.registration.icp import (
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
from jaxreg.search.features import fpfh as fpfh, match_features as match_features
from jaxreg.search.neighbors import (
    NeighborGrid as NeighborGrid,
    build_grid as build_grid,
    pad_grid as pad_grid,
    validate_grid as validate_grid,
    voxel_downsample as voxel_downsample,
)
from jaxreg.search.normals import estimate_normals as estimate_normals
from jaxreg.uncertainty import (
    DepthNoise as DepthNoise,
    IsotropicNoise as IsotropicNoise,
    PointCovariance as PointCovariance,
    PoseStatistics as PoseStatistics,
    error_budget as error_budget,
    grasp_margin as grasp_margin,
    grasp_success_probability as grasp_success_probability,
    pose_statistics as pose_statistics,
)


def __getattr__(name: str):
    # jaxreg.synth and jaxreg.studies need the ray caster (trimesh + Embree), and jaxreg.cli
    # needs both: imported on first use, not with jaxreg.
    if name in ("synth", "studies", "cli"):
        import importlib

        return importlib.import_module(f"jaxreg.{name}")
    raise AttributeError(f"module 'jaxreg' has no attribute {name!r}")
