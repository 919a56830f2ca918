"""jaxreg: differentiable, batched 6-DOF pose estimation and point-cloud registration in JAX."""

from jaxlie import SE3 as SE3, SO3 as SO3

from jaxreg import align as align, kernels as kernels
from jaxreg.align import Alignment as Alignment, kabsch as kabsch, umeyama as umeyama
