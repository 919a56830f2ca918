"""Registration solvers: ICP (point-to-point, point-to-plane, trimming, robust IRLS kernels,
multi-start; its options one :class:`~jaxreg.registration.icp.ICPOptions`), the ICP pose
covariance, RANSAC global registration on feature matches, and robust (GNC) alignment of given
correspondences. :mod:`jaxreg.registration.solver` holds ICP's steps (prepare, run, unpad) for
code that batches registrations its own way.

Every solver returns a result with a per-lane ``status``. May import :mod:`jaxreg.core`,
:mod:`jaxreg.geometry`, :mod:`jaxreg.uncertainty` and :mod:`jaxreg.search`.
"""

from jaxreg.core._lazy import submodules

__getattr__ = submodules(__name__)  # jaxreg.registration.<module> without importing it first
