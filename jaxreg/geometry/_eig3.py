"""Closed-form eigendecomposition of symmetric 3x3 matrices, elementwise over a batch.

XLA's batched ``eigh`` of 3x3 matrices is ~10x slower on CPU than this arithmetic, and it
calls LAPACK on a thread pool. Used for point-neighbourhood covariances
(:mod:`jaxreg.search.normals`) and the PCA of PnP's object points (:mod:`jaxreg.camera._pnp_init`).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

__all__ = ["eigh3"]


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
