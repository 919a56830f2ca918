"""Small dense linear algebra for PnP's batched hot paths: tiny matrix products, and the
Cholesky solve and inverse of symmetric positive definite matrices (the 6x6 normal equations),
unrolled into scalar arithmetic.

XLA's CPU backend runs a batched LAPACK call on thousands of 6x6 matrices one small matrix at a
time; unrolled, the same work is a few dozen elementwise operations over the whole batch, which
XLA fuses. Every function takes leading batch axes `(...)`. A matrix that is not numerically
positive definite (a pivot `<= 0`, or not finite) is reported by the `ok` flag rather than
raised; the other outputs are then finite placeholders to be discarded.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

__all__ = [
    "cho_solve",
    "cholesky",
    "matmul",
    "packed",
    "spd_inverse",
    "spd_inverse_rows",
    "spd_solve",
]


def matmul(
    a: Float[Array, "*batch m k"], b: Float[Array, "*batch k n"]
) -> Float[Array, "*batch m n"]:
    """`a @ b` for tiny matrices, as a broadcast product and a sum: elementwise work XLA fuses,
    where a vmapped `dot` of 8x6 and 6x6 operands runs ~7x slower on its CPU backend."""
    return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)


def _unpack(A: Array) -> list[list[Array]]:
    n = A.shape[-1]
    return [[A[..., i, j] for j in range(n)] for i in range(n)]


def packed(upper) -> list[list[Array]]:
    """The full matrix (rows of scalars) of the upper triangle `upper`, given row by row
    (`n (n + 1) / 2` scalars)."""
    n = int(round((np.sqrt(8 * len(upper) + 1) - 1) / 2))
    rows: list[list[Array]] = [[upper[0]] * n for _ in range(n)]
    k = 0
    for i in range(n):
        for j in range(i, n):
            rows[i][j] = rows[j][i] = upper[k]
            k += 1
    return rows


def cholesky(a: list[list[Array]]) -> tuple[list[list[Array]], list[Array], Array]:
    """Lower factor `L` (rows of scalars, `A = L L^T`) of a matrix given as rows of scalars,
    the reciprocals of its diagonal and whether every pivot was positive."""
    n = len(a)
    zero = jnp.zeros_like(a[0][0])
    L: list[list[Array]] = [[zero] * n for _ in range(n)]
    inv_diag = []
    ok = jnp.ones(zero.shape, bool)
    for j in range(n):
        pivot = a[j][j] - sum((L[j][k] * L[j][k] for k in range(j)), zero)
        good = pivot > 0  # False for NaN too
        ok = ok & good
        root = jnp.sqrt(jnp.where(good, pivot, 1.0))
        L[j][j] = root
        inv = 1.0 / root
        inv_diag.append(inv)
        for i in range(j + 1, n):
            dot = sum((L[i][k] * L[j][k] for k in range(j)), zero)
            L[i][j] = (a[i][j] - dot) * inv
    return L, inv_diag, ok


def cho_solve(L, inv_diag, b: list[Array]) -> list[Array]:
    """`x` with `L L^T x = b`, all as scalars."""
    n = len(b)
    zero = jnp.zeros_like(inv_diag[0])
    y: list[Array] = []
    for i in range(n):
        y.append((b[i] - sum((L[i][k] * y[k] for k in range(i)), zero)) * inv_diag[i])
    x: list[Array] = [zero] * n
    for i in reversed(range(n)):
        x[i] = (y[i] - sum((L[k][i] * x[k] for k in range(i + 1, n)), zero)) * inv_diag[i]
    return x


def spd_solve(
    A: Float[Array, "*batch n n"], b: Float[Array, "*batch n"]
) -> tuple[Float[Array, "*batch n"], Bool[Array, "*batch"]]:
    """`x = A^-1 b` by Cholesky, and whether `A` was positive definite."""
    L, inv_diag, ok = cholesky(_unpack(A))
    x = cho_solve(L, inv_diag, [b[..., i] for i in range(A.shape[-1])])
    return jnp.stack(x, axis=-1), ok


def spd_inverse_rows(a: list[list[Array]]) -> tuple[list[list[Array]], Array]:
    """`A^-1` by Cholesky (`L^-T L^-1`, exactly symmetric) of a matrix given as rows of
    scalars, as rows of scalars, and whether `A` was positive definite."""
    n = len(a)
    L, inv_diag, ok = cholesky(a)
    zero = jnp.zeros_like(inv_diag[0])
    # M = L^-1, lower triangular, by forward substitution on the identity's columns.
    M: list[list[Array]] = [[zero] * n for _ in range(n)]
    for j in range(n):
        M[j][j] = inv_diag[j]
        for i in range(j + 1, n):
            dot = sum((L[i][k] * M[k][j] for k in range(j, i)), zero)
            M[i][j] = -dot * inv_diag[i]
    rows: list[list[Array]] = [[zero] * n for _ in range(n)]
    for i in range(n):
        for j in range(i, n):
            rows[i][j] = rows[j][i] = sum((M[k][i] * M[k][j] for k in range(j, n)), zero)
    return rows, ok


def spd_inverse(
    A: Float[Array, "*batch n n"],
) -> tuple[Float[Array, "*batch n n"], Bool[Array, "*batch"]]:
    """`A^-1` by Cholesky (`L^-T L^-1`, exactly symmetric), and whether `A` was positive
    definite."""
    rows, ok = spd_inverse_rows(_unpack(A))
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2), ok
