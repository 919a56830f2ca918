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


def _rotate(a: dict, v: list, n: int, p: int, q: int):
    """One Jacobi rotation zeroing ``a[p, q]`` (``a <- J^T a J``, ``v <- v J``), entry by
    entry: ``a`` maps ``(i, j)``, ``i <= j``, to the batch of that entry; ``v`` is a list of
    rows of batches. Only rows and columns ``p`` and ``q`` change."""
    apq, app, aqq = a[p, q], a[p, p], a[q, q]
    live = apq != 0
    theta = (aqq - app) / (2 * jnp.where(live, apq, 1.0))
    t = jnp.sign(theta) / (jnp.abs(theta) + jnp.sqrt(theta * theta + 1))
    t = jnp.where(live, jnp.where(theta == 0, 1.0, t), 0.0)
    c = 1 / jnp.sqrt(t * t + 1)
    s = t * c
    a = dict(a)
    a[p, p] = app - t * apq
    a[q, q] = aqq + t * apq
    a[p, q] = jnp.zeros_like(apq)
    for r in range(n):
        if r in (p, q):
            continue
        rp, rq = (min(r, p), max(r, p)), (min(r, q), max(r, q))
        arp, arq = a[rp], a[rq]
        a[rp], a[rq] = c * arp - s * arq, s * arp + c * arq
    v = [list(row) for row in v]
    for row in v:
        vp, vq = row[p], row[q]
        row[p], row[q] = c * vp - s * vq, s * vp + c * vq
    return a, v


def jacobi_eigh(
    a: Float[Array, "... n n"], sweeps: int = 6
) -> tuple[Float[Array, "... n"], Float[Array, "... n n"]]:
    """Eigenvalues (ascending) and unit eigenvectors (columns) of symmetric ``a``, like
    ``jnp.linalg.eigh``, by ``sweeps`` cyclic Jacobi sweeps (static; each visits every
    off-diagonal pair once). Meant for tiny ``n`` (4 for Horn's quaternion matrix): the cost
    is ``sweeps * n (n - 1) / 2`` rotations of ``O(n)`` each. Only the upper triangle of
    ``a`` is read. Not differentiated here: ICP differentiates its solution implicitly, not
    through its iterations.

    The matrix is held as ``n (n + 1) / 2`` separate batches of its entries, and ``v`` as
    ``n^2``, so that a rotation is a few elementwise operations on whole batches (no
    scatter into a ``(..., n, n)`` array), which XLA fuses into one loop and compiles
    quickly."""
    n = a.shape[-1]
    upper = [(i, j) for i in range(n) for j in range(i, n)]
    zero, one = jnp.zeros_like(a[..., 0, 0]), jnp.ones_like(a[..., 0, 0])
    start = (
        tuple(a[..., i, j] for i, j in upper),
        tuple(one if i == j else zero for i in range(n) for j in range(n)),
    )

    def sweep(_, carry):
        entries = dict(zip(upper, carry[0], strict=True))
        v = [list(carry[1][i * n : (i + 1) * n]) for i in range(n)]
        for p, q in itertools.combinations(range(n), 2):
            entries, v = _rotate(entries, v, n, p, q)
        return tuple(entries[ij] for ij in upper), tuple(x for row in v for x in row)

    flat_a, flat_v = jax.lax.fori_loop(0, sweeps, sweep, start)
    entries = dict(zip(upper, flat_a, strict=True))
    lam = jnp.stack([entries[i, i] for i in range(n)], -1)
    v = jnp.stack([jnp.stack(flat_v[i * n : (i + 1) * n], -1) for i in range(n)], -2)
    order = jnp.argsort(lam, axis=-1)
    lam = jnp.take_along_axis(lam, order, axis=-1)
    v = jnp.take_along_axis(v, order[..., None, :], axis=-1)
    return lam, v
