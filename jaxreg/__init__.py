"""jaxreg: differentiable, batched 6-DOF pose estimation and point-cloud registration in JAX.

The public names below are re-exported from one module each; see those modules for the
conventions (poses map source/model into target/scene coordinates, tangents are jaxlie's
``(vx, vy, vz, wx, wy, wz)``, covariances are of the right perturbation).
"""

from jaxreg import (
    alignment as alignment,
    camera as camera,
    io as io,
    kernels as kernels,
    lie as lie,
    neighbors as neighbors,
    normals as normals,
    pnp as pnp,
    tags as tags,
    uncertainty as uncertainty,
)
from jaxreg.alignment import (
    Alignment as Alignment,
    AlignmentStatus as AlignmentStatus,
    align as align,
    kabsch as kabsch,
    umeyama as umeyama,
)
from jaxreg.camera import project as project, reprojection_error as reprojection_error
from jaxreg.icp import (
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
from jaxreg.kernels import (
    L2 as L2,
    Cauchy as Cauchy,
    GemanMcClure as GemanMcClure,
    Huber as Huber,
    Tukey as Tukey,
    Welsch as Welsch,
)
from jaxreg.lie import (
    SE3 as SE3,
    SO3 as SO3,
    adjoint_transport as adjoint_transport,
    chordal_mean as chordal_mean,
    geodesic_angle as geodesic_angle,
    karcher_mean as karcher_mean,
    random_rotations as random_rotations,
    rotation_grid as rotation_grid,
    rotation_grid_around as rotation_grid_around,
    se3_exp as se3_exp,
)
from jaxreg.neighbors import (
    NeighborGrid as NeighborGrid,
    build_grid as build_grid,
    validate_grid as validate_grid,
    voxel_downsample as voxel_downsample,
)
from jaxreg.normals import estimate_normals as estimate_normals
from jaxreg.pnp import (
    PlanarPnPResult as PlanarPnPResult,
    PnPResult as PnPResult,
    PnPStatus as PnPStatus,
    solve_pnp as solve_pnp,
    solve_pnp_planar as solve_pnp_planar,
)
from jaxreg.tags import detect_tags as detect_tags, tag_object_points as tag_object_points
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
