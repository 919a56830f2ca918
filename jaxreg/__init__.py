"""jaxreg: differentiable, batched 6-DOF pose estimation and point-cloud registration in JAX."""

from jaxlie import SE3 as SE3, SO3 as SO3
