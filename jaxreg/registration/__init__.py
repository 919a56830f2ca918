"""Registration solvers: ICP (point-to-point, point-to-plane, trimming, robust IRLS kernels,
multi-start; its options one :class:`~jaxreg.registration.icp.ICPOptions`), the ICP pose
covariance, RANSAC global registration on feature matches, and robust (GNC) alignment of given
correspondences. :mod:`jaxreg.registration.solver` holds ICP's steps (prepare, run, unpad) for
code that batches registrations its own way.

Every solver returns a result with a per-lane ``status``. May import :mod:`jaxreg.core`,
:mod:`jaxreg.geometry`, :mod:`jaxreg.uncertainty` and :mod:`jaxreg.search`.
"""

from jaxreg.core._lazy import exports

# The public names, each module imported on first use; jaxreg.registration.<module> resolves
# too (ICP's steps are reached through theirs: jaxreg.registration.solver.run), and
# jaxreg.registration.icp is the module (the function is jaxreg.icp).
__getattr__, __dir__ = exports(
    __name__,
    {
        "jaxreg.registration.icp": (
            "ICPOptions", "ICPStatus", "RegistrationResult", "best_index", "icp_covariance",
            "init_spread", "multistart_icp", "pca_inits", "perturbed_inits", "rotation_inits",
            "select_best",
        ),
        "jaxreg.registration.projective": ("ProjectiveAssociation", "organized_normals"),
        "jaxreg.registration.ransac": (
            "RansacResult", "RansacStatus", "ransac_iterations", "ransac_registration",
        ),
        "jaxreg.registration.robust": ("RobustAlignment", "RobustStatus", "robust_kabsch"),
    },
)  # fmt: skip
