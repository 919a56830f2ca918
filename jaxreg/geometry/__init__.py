"""Geometry core: SE(3)/SO(3) utilities on jaxlie's types (geodesic angles, means, sampling,
adjoint transport, ``se3_exp``), weighted Kabsch/Umeyama and ``align``, robust kernels,
small eigensolvers (:mod:`jaxreg.geometry.eigen`), the pose metrics
(pose error, ADD/ADD-S, ``Symmetry``, canonicalisation) and the BOP benchmark's (VSD, MSSD,
MSPD, Average Recall).

Conventions: a pose maps source/model coordinates into target/scene coordinates; tangents are
jaxlie's ``(vx, vy, vz, wx, wy, wz)``. May import :mod:`jaxreg.core` only.
"""

from jaxreg.core._lazy import submodules

__getattr__ = submodules(__name__)  # jaxreg.geometry.<module> without importing it first
