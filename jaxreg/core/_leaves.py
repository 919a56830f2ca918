"""Concrete host values as arrays without compiling a program: as JAX array leaves
(:func:`as_leaf`), or kept on the host where an argument is only checked and prepared
(:func:`as_array`).

``jnp.asarray`` of host data runs a small XLA program per shape and dtype (conversion,
canonicalisation), which every new process compiles or loads again; for a command line run
these add up. Converting in numpy and copying with ``jax.device_put`` compiles nothing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

__all__ = ["as_array", "as_leaf"]


def as_leaf(value, dtype=None) -> Array:
    """``value`` as a JAX array leaf (of ``dtype`` if given, else JAX's canonical dtype of its
    own): a traced value through ``jnp.asarray``; a concrete one converted in numpy and copied
    to the device."""
    if isinstance(value, jax.core.Tracer):
        return jnp.asarray(value, dtype=dtype)
    array = np.asarray(value)
    dtype = array.dtype if dtype is None else dtype
    return jax.device_put(array.astype(jax.dtypes.canonicalize_dtype(dtype)))


def as_array(value, dtype=None):
    """``value`` as an array of ``dtype`` (its own if ``None``), converting nothing to the
    device: a numpy array for host input (Python numbers, numpy arrays), so that checking or
    preparing it compiles no device program; JAX arrays and tracers stay JAX arrays."""
    if isinstance(value, jax.Array | jax.core.Tracer):
        return jnp.asarray(value, dtype)
    return np.asarray(value, dtype)
