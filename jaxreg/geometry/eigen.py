"""Eigendecompositions of small symmetric matrices in plain XLA arithmetic (no LAPACK call).

* :func:`eigh3`: closed form for 3x3 matrices, elementwise over a batch. XLA's batched ``eigh``
  of 3x3 matrices is ~10x slower on CPU than this arithmetic, and it calls LAPACK on a thread
  pool. Used for point-neighbourhood covariances (:mod:`jaxreg.search.normals`) and the PCA of
  PnP's object points (:mod:`jaxreg.camera._pnp_init`).
* :func:`jacobi_eigh`: cyclic Jacobi sweeps for tiny ``n`` (ICP's 4x4 and 6x6 problems).

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

__all__ = ["eigh3", "jacobi_eigh"]

# --------------------------------------------------------------------------------------------
# 3x3: closed form.


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _unit(v, fallback):
    """``v`` normalised, or ``fallback`` where ``v`` is zero."""
    n2 = _dot(v, v)
    ok = n2 > 0
    inv = 1 / jnp.sqrt(jnp.where(ok, n2, 1))
    return tuple(jnp.where(ok, vi * inv, f) for vi, f in zip(v, fallback, strict=True))


def _null_vector(rows, fallback):
    """Unit vector orthogonal to the rows of a rank-2 symmetric 3x3 matrix: the longest of
    the three row cross products, normalised (``fallback`` where all vanish)."""
    r0, r1, r2 = rows
    c = [_cross(r0, r1), _cross(r0, r2), _cross(r1, r2)]
    d = [_dot(ci, ci) for ci in c]
    best = tuple(jnp.where(d[0] >= d[1], a, b) for a, b in zip(c[0], c[1], strict=True))
    best = tuple(
        jnp.where(d[2] > jnp.maximum(d[0], d[1]), a, b) for a, b in zip(c[2], best, strict=True)
    )
    return _unit(best, fallback)


def eigh3(c: Float[Array, "... 6"]) -> tuple[Array, Array]:
    """Eigenvalues ``(..., 3)`` and unit eigenvectors ``(..., 3, 3)`` (columns, matching) of
    symmetric 3x3 matrices given by their entries ``(a00, a01, a02, a11, a12, a22)``.

    Closed form, elementwise over the batch (XLA's batched ``eigh`` of 3x3 matrices is
    ~10x slower on CPU). Eberly's robust scheme: the matrix is scaled by its largest entry;
    the eigenvalues come from the trigonometric solution of the characteristic cubic; the
    eigenvector of the eigenvalue farther from the middle one is the longest cross product
    of two rows of ``A - lambda I`` (rank 2 even when the other two eigenvalues repeat);
    the middle one solves a 2x2 problem in the plane orthogonal to it, and the third
    completes the frame. The eigenvalues are then recomputed as Rayleigh quotients: the
    cubic's roots lose half the digits where two of them repeat (collinear neighbours),
    the quotients do not. A zero matrix gives zeros and the identity frame; eigenvalues are
    ascending up to rounding where they repeat.
    """
    dtype = c.dtype
    raw = [c[..., i] for i in range(6)]
    scale = jnp.max(jnp.abs(c), axis=-1)
    live = scale > jnp.finfo(dtype).tiny
    inv_scale = 1 / jnp.where(live, scale, 1)
    a00, a01, a02, a11, a12, a22 = (jnp.where(live, x * inv_scale, 0) for x in raw)
    q = (a00 + a11 + a22) / 3
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6
    iso = p2 <= 0  # a multiple of the identity
    p = jnp.sqrt(jnp.where(iso, 1, p2))
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
    det = det + a02 * (a01 * a12 - b11 * a02)
    half_det = jnp.clip(det / (2 * p * p * p), -1, 1)
    angle = jnp.arccos(jnp.where(iso, 0, half_det)) / 3
    beta2 = 2 * jnp.cos(angle)
    beta0 = 2 * jnp.cos(angle + 2 * np.pi / 3)
    roots = [q + p * b for b in (beta0, -(beta0 + beta2), beta2)]
    zero, one = jnp.zeros_like(q), jnp.ones_like(q)
    low_first = half_det < 0  # the smallest root is the isolated one
    lam = jnp.where(low_first, roots[0], roots[2])
    first = _null_vector(
        ((a00 - lam, a01, a02), (a01, a11 - lam, a12), (a02, a12, a22 - lam)),
        (one, zero, zero),
    )
    w = first
    big0 = jnp.abs(w[0]) > jnp.abs(w[1])
    u = _unit(
        (jnp.where(big0, -w[2], 0), jnp.where(big0, 0, w[2]), jnp.where(big0, w[0], -w[1])),
        (zero, zero, one),
    )
    v = _cross(w, u)

    def times_a(x):
        return (
            a00 * x[0] + a01 * x[1] + a02 * x[2],
            a01 * x[0] + a11 * x[1] + a12 * x[2],
            a02 * x[0] + a12 * x[1] + a22 * x[2],
        )

    au, av = times_a(u), times_a(v)
    m00, m01, m11 = _dot(u, au) - roots[1], _dot(u, av), _dot(v, av) - roots[1]
    use00 = jnp.abs(m00) >= jnp.abs(m11)
    x, y = jnp.where(use00, m01, m11), jnp.where(use00, m00, m01)
    mid = _unit(tuple(x * ui - y * vi for ui, vi in zip(u, v, strict=True)), u)
    # Re-orthogonalise: where the 2x2 block is ~0 (repeated roots) mid is rounding noise.
    along = _dot(mid, first)
    mid = _unit(tuple(m - along * f for m, f in zip(mid, first, strict=True)), u)
    last = _unit(_cross(first, mid), v)
    v0 = tuple(jnp.where(low_first, f, t) for f, t in zip(first, last, strict=True))
    v2 = tuple(jnp.where(low_first, t, f) for f, t in zip(first, last, strict=True))
    evals = jnp.stack([_dot(e, times_a(e)) for e in (v0, mid, v2)], -1)
    vecs = jnp.stack([jnp.stack(e, -1) for e in (v0, mid, v2)], -1)
    return evals * jnp.where(live, scale, 0)[..., None], vecs


# --------------------------------------------------------------------------------------------
# n x n: cyclic Jacobi sweeps.


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
