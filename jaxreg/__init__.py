"""jaxreg: differentiable, batched 6-DOF pose estimation and point-cloud registration in JAX.

The public names below are re-exported from one module each; see those modules for the
conventions (poses map source/model into target/scene coordinates, tangents are jaxlie's
``(vx, vy, vz, wx, wy, wz)``, covariances are of the right perturbation).
"""

from jaxreg import (
    align as align,
    io as io,
    kernels as kernels,
    lie as lie,
    neighbors as neighbors,
    normals as normals,
)
from jaxreg.align import Alignment as Alignment, kabsch as kabsch, umeyama as umeyama
from jaxreg.icp import (
    ICPStatus as ICPStatus,
    RegistrationResult as RegistrationResult,
    icp as icp,
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
)
from jaxreg.neighbors import voxel_downsample as voxel_downsample
from jaxreg.normals import estimate_normals as estimate_normals
