"""Geometry core: SE(3)/SO(3) utilities on jaxlie's types (geodesic angles, means, sampling,
adjoint transport, ``se3_exp``), weighted Kabsch/Umeyama and ``align``, robust kernels,
small eigensolvers (:mod:`jaxreg.geometry.eigen`), the pose metrics
(pose error, ADD/ADD-S, ``Symmetry``, canonicalisation) and the BOP benchmark's (VSD, MSSD,
MSPD, Average Recall).

Conventions: a pose maps source/model coordinates into target/scene coordinates; tangents are
jaxlie's ``(vx, vy, vz, wx, wy, wz)``. May import :mod:`jaxreg.core` only.
"""

from jaxreg.core._lazy import exports

# The public names, each module imported on first use; jaxreg.geometry.<module> resolves too.
__getattr__, __dir__ = exports(
    __name__,
    {
        "jaxreg.geometry.alignment": ("Alignment", "AlignmentStatus", "align", "kabsch", "umeyama"),
        "jaxreg.geometry.bop_metrics": (
            "BopRecall", "average_recall", "bop_symmetry_transforms", "correct", "mspd", "mssd",
            "vsd",
        ),
        "jaxreg.geometry.eigen": ("eigh3", "jacobi_eigh"),
        "jaxreg.geometry.kernels": (
            "L2", "AbstractRobustKernel", "Cauchy", "GemanMcClure", "Huber", "Tukey", "Welsch",
            "trim_mask",
        ),
        "jaxreg.geometry.lie": (
            "SE3", "SO3", "adjoint_transport", "covariance_from_open3d", "covariance_to_open3d",
            "geodesic_angle", "random_rotations", "rotation_angle", "rotation_grid",
            "rotation_grid_around", "se3_exp", "se3_from_matrix", "se3_to_matrix",
            "so3_from_matrix", "tangent_from_open3d", "tangent_to_open3d",
        ),
        "jaxreg.geometry.means": ("chordal_mean", "karcher_mean"),
        "jaxreg.geometry.metrics": (
            "Symmetry", "add", "add_s", "canonicalise", "diameter", "pose_error",
            "rotation_error",
        ),
    },
)  # fmt: skip
