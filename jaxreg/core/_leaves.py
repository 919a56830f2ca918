"""Concrete host values as JAX array leaves without compiling a program.

``jnp.asarray`` of host data runs a small XLA program per shape and dtype (conversion,
canonicalisation), which every new process compiles or loads again; for a command line run
these add up. Converting in numpy and copying with ``jax.device_put`` compiles nothing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

__all__ = ["as_leaf"]


def as_leaf(value, dtype=None) -> Array:
    """``value`` as a JAX array leaf (of ``dtype`` if given, else JAX's canonical dtype of its
    own): a traced value through ``jnp.asarray``; a concrete one converted in numpy and copied
    to the device."""
    if isinstance(value, jax.core.Tracer):
        return jnp.asarray(value, dtype=dtype)
    array = np.asarray(value)
    dtype = array.dtype if dtype is None else dtype
    return jax.device_put(array.astype(jax.dtypes.canonicalize_dtype(dtype)))
