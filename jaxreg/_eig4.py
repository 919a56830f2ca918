"""Eigen-decomposition of small symmetric matrices by cyclic Jacobi sweeps, in plain XLA ops.

ICP's point-to-point step solves Horn's 4x4 quaternion eigenproblem, and its point-to-plane
step a 6x6 normal-equation system, once per start and iteration. ``jnp.linalg.eigh`` lowers
to a LAPACK custom call on CPU which (jaxlib 0.10) splits a large batch over XLA's intra-op
thread pool and waits for the pieces on a thread of that same pool: with several host
devices sharing a small pool (``--xla_force_host_platform_device_count=2`` on 2 cores) every
pool thread ends up waiting and the program deadlocks (a basin sweep of 1,280 starts on 2
forced host devices hung in ``lapack_ssyevd_ffi`` / ``ParallelBatchMap``). Jacobi sweeps are
a fixed number of elementwise updates: no custom call, no thread pool, fused with their
neighbours, and as accurate as ``eigh`` (quadratic convergence: 4x4 and 6x6 matrices reach
float32 and float64 rounding within 6 sweeps).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["jacobi_eigh"]


def _rotate(carry, p: int, q: int):
    """One Jacobi rotation zeroing ``a[p, q]``: ``a <- J^T a J``, ``v <- v J``."""
    a, v = carry
    apq = a[..., p, q]
    app, aqq = a[..., p, p], a[..., q, q]
    live = apq != 0
    theta = (aqq - app) / (2 * jnp.where(live, apq, 1.0))
    t = jnp.sign(theta) / (jnp.abs(theta) + jnp.sqrt(theta * theta + 1))
    t = jnp.where(live, jnp.where(theta == 0, 1.0, t), 0.0)
    c = 1 / jnp.sqrt(t * t + 1)
    s = t * c
    c_, s_ = c[..., None], s[..., None]
    # Columns p and q, then rows p and q (a stays symmetric).
    col_p, col_q = a[..., :, p], a[..., :, q]
    a = a.at[..., :, p].set(c_ * col_p - s_ * col_q).at[..., :, q].set(s_ * col_p + c_ * col_q)
    row_p, row_q = a[..., p, :], a[..., q, :]
    a = a.at[..., p, :].set(c_ * row_p - s_ * row_q).at[..., q, :].set(s_ * row_p + c_ * row_q)
    vp, vq = v[..., :, p], v[..., :, q]
    v = v.at[..., :, p].set(c_ * vp - s_ * vq).at[..., :, q].set(s_ * vp + c_ * vq)
    return a, v


def jacobi_eigh(
    a: Float[Array, "... n n"], sweeps: int = 6
) -> tuple[Float[Array, "... n"], Float[Array, "... n n"]]:
    """Eigenvalues (ascending) and unit eigenvectors (columns) of symmetric ``a``, like
    ``jnp.linalg.eigh``, by ``sweeps`` cyclic Jacobi sweeps (static; each visits every
    off-diagonal pair once). Meant for tiny ``n`` (4 for Horn's quaternion matrix): the cost
    is ``sweeps * n (n - 1) / 2`` rotations of ``O(n)`` each. Not differentiated here: ICP
    differentiates its solution implicitly, not through its iterations."""
    n = a.shape[-1]
    v = jnp.broadcast_to(jnp.eye(n, dtype=a.dtype), a.shape)

    def sweep(_, carry):
        for p, q in itertools.combinations(range(n), 2):
            carry = _rotate(carry, p, q)
        return carry

    a, v = jax.lax.fori_loop(0, sweeps, sweep, (a, v))
    lam = jnp.diagonal(a, axis1=-2, axis2=-1)
    order = jnp.argsort(lam, axis=-1)
    lam = jnp.take_along_axis(lam, order, axis=-1)
    v = jnp.take_along_axis(v, order[..., None, :], axis=-1)
    return lam, v
