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

The pairs are visited in round-robin order (Brent and Luk's parallel ordering): a sweep is
``n - 1`` rounds (``n`` for odd ``n``), each rotating ``n // 2`` disjoint pairs at once, and
one loop trip is one round. Its pairs sit at the same fixed positions every trip: the trip
ends by relabelling the indices (a fixed permutation of rows and columns) so that the next
round's pairs occupy those positions. So a trip is a few whole-matrix operations with
constant indices, compiled once. Written out instead as one trip per sweep of separate
per-entry arrays, the chain of dependent rotations was recomputed in each of the sweep's
fused outputs: a vmapped 6x6 call compiled to 8.9k optimized HLO instructions (4x4: 1.7k),
this one to 0.3k, which is what loading a stored executable costs.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

__all__ = ["jacobi_eigh"]


def _round_robin(n: int) -> tuple[int, list[tuple[int, int]], list[int]]:
    """The positions, pairs and relabelling of a round of the circle method over ``m``
    positions (``m = n`` for even ``n``; odd ``n`` adds an idle position 0).

    Returns ``m``, the pairs ``(k, m - 1 - k)`` rotated in every round (those with the idle
    position left out), and ``perm``: after a round, position ``i`` takes the content of
    position ``perm[i]`` (0 stays, the others move one step round a cycle). Over ``m - 1``
    rounds every two indices meet exactly once, and the labels come back to where they were.
    """
    m = n + n % 2
    pairs = [(k, m - 1 - k) for k in range(n % 2, m // 2)]
    perm = [0] + [i % (m - 1) + 1 for i in range(1, m)]
    return m, pairs, perm


def _rotation(apq: Array, app: Array, aqq: Array) -> tuple[Array, Array, Array]:
    """``t = tan``, ``c = cos`` and ``s = sin`` of the Jacobi rotation zeroing ``a[p, q]``
    (Rutishauser's formulas; no rotation where ``a[p, q] == 0``)."""
    live = apq != 0
    theta = (aqq - app) / (2 * jnp.where(live, apq, 1.0))
    t = jnp.sign(theta) / (jnp.abs(theta) + jnp.sqrt(theta * theta + 1))
    t = jnp.where(live, jnp.where(theta == 0, 1.0, t), 0.0)
    c = 1 / jnp.sqrt(t * t + 1)
    return t, c, t * c


def jacobi_eigh(
    a: Float[Array, "... n n"], sweeps: int = 6
) -> tuple[Float[Array, "... n"], Float[Array, "... n n"]]:
    """Eigenvalues (ascending) and unit eigenvectors (columns) of symmetric ``a``, like
    ``jnp.linalg.eigh``, by ``sweeps`` cyclic Jacobi sweeps (static; each visits every
    off-diagonal pair once, in round-robin order). Meant for tiny ``n`` (4 for Horn's
    quaternion matrix): the cost is ``sweeps * n (n - 1) / 2`` rotations of ``O(n)`` each.
    Only the upper triangle of ``a`` is read. Not differentiated here: ICP differentiates its
    solution implicitly, not through its iterations."""
    n = a.shape[-1]
    if n == 1:
        return a[..., 0], jnp.ones_like(a)
    m, pairs, perm = _round_robin(n)
    idle = m - n  # an odd n is padded with a zero row and column in front, never rotated
    p, q = np.array(pairs, dtype=int).reshape(-1, 2).T
    # Per position: its pair (index into p, q), the sign of s in J[partner, position] and
    # of t in the pair's new diagonal, and its partner (itself when idle).
    pair_of, sign, partner = np.zeros(m, int), np.zeros(m), np.arange(m)
    pair_of[p], pair_of[q] = np.arange(len(p)), np.arange(len(p))
    sign[p], sign[q], partner[p], partner[q] = -1.0, 1.0, q, p
    in_pair = np.zeros((m, m), bool)
    in_pair[p, q] = in_pair[q, p] = True

    a = jnp.where(np.triu(np.ones((n, n), bool)), a, jnp.swapaxes(a, -1, -2))
    a = jnp.pad(a, [(0, 0)] * (a.ndim - 2) + [(idle, 0), (idle, 0)])
    v = jnp.broadcast_to(jnp.eye(m, dtype=a.dtype), a.shape)
    sign = jnp.asarray(sign, a.dtype)

    def round_(_, carry):
        """``a <- J^T a J`` and ``v <- v J`` for this round's rotations ``J``, relabelled."""
        a, v = carry
        apq = a[..., p, q]
        t, c, s = _rotation(apq, a[..., p, p], a[..., q, q])
        c = jnp.where(sign != 0, c[..., pair_of], 1.0)
        s = sign * s[..., pair_of]
        tpq = sign * (t * apq)[..., pair_of]
        rows = c[..., :, None] * a + s[..., :, None] * a[..., partner, :]
        a = rows * c[..., None, :] + rows[..., :, partner] * s[..., None, :]
        a = jnp.where(in_pair, 0.0, a)  # each pair's a[p, q], exactly
        diagonal = jnp.diagonal(carry[0], axis1=-2, axis2=-1) + tpq  # a[p, p] -/+ t a[p, q]
        a = jnp.where(np.eye(m, dtype=bool), diagonal[..., None, :], a)
        v = v * c[..., None, :] + v[..., :, partner] * s[..., None, :]
        return a[..., perm, :][..., :, perm], v[..., :, perm]

    a, v = jax.lax.fori_loop(0, sweeps * (m - 1), round_, (a, v))
    lam = jnp.diagonal(a, axis1=-2, axis2=-1)[..., idle:]
    order = jnp.argsort(lam, axis=-1)
    lam = jnp.take_along_axis(lam, order, axis=-1)
    v = jnp.take_along_axis(v[..., idle:, idle:], order[..., None, :], axis=-1)
    return lam, v
