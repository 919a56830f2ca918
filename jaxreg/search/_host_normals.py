"""Normals of a concrete cloud from its neighbourhood moments, by compiled host loops (numba).

The host twin of :func:`jaxreg.search.normals._from_moments`: the same eigen solver
(:func:`jaxreg.geometry.eigen.eigh3`'s closed form, written per point in float64), the same
orientation, curvature and status rules, so that a concrete cloud is answered without a JAX
program (whose fixed cost, padding and transfers outweigh ~0.1 us of arithmetic per point).
Status codes are :class:`jaxreg.search.normals.NormalStatus`'s, passed in as integers.

Compiled on the first call on a machine and cached on disk (``__pycache__``); large clouds run
on one thread per core (:func:`jaxreg.core._threads.in_pieces`), each point's answer
independent of the split.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from jaxreg.core._threads import in_pieces, num_pieces

__all__ = ["host_normals"]

_CACHE = dict(cache=True, nogil=True)
_GRAIN = 1024  # points per piece of a threaded pass (~0.2 ms of work)
_TINY = np.finfo(np.float64).tiny


@numba.njit(inline="always")
def _unit(x, y, z, fx, fy, fz):
    """``(x, y, z)`` normalised, or the fallback where it is zero."""
    n2 = x * x + y * y + z * z
    if n2 > 0:
        inv = 1.0 / math.sqrt(n2)
        return x * inv, y * inv, z * inv
    return fx, fy, fz


@numba.njit(inline="always")
def _longest_cross(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """The longest of the rows' three cross products, normalised (``(1, 0, 0)`` where all
    vanish): the null vector of a rank-2 symmetric matrix."""
    a0, a1, a2 = r01 * r12 - r02 * r11, r02 * r10 - r00 * r12, r00 * r11 - r01 * r10
    b0, b1, b2 = r01 * r22 - r02 * r21, r02 * r20 - r00 * r22, r00 * r21 - r01 * r20
    c0, c1, c2 = r11 * r22 - r12 * r21, r12 * r20 - r10 * r22, r10 * r21 - r11 * r20
    da, db = a0 * a0 + a1 * a1 + a2 * a2, b0 * b0 + b1 * b1 + b2 * b2
    dc = c0 * c0 + c1 * c1 + c2 * c2
    x, y, z = (a0, a1, a2) if da >= db else (b0, b1, b2)
    if dc > max(da, db):
        x, y, z = c0, c1, c2
    return _unit(x, y, z, 1.0, 0.0, 0.0)


@numba.njit(inline="always")
def _times(a, x0, x1, x2):
    """``A x`` for the symmetric ``A`` with entries ``a = (a00, a01, a02, a11, a12, a22)``."""
    return (
        a[0] * x0 + a[1] * x1 + a[2] * x2,
        a[1] * x0 + a[3] * x1 + a[4] * x2,
        a[2] * x0 + a[4] * x1 + a[5] * x2,
    )


@numba.njit(inline="always")
def _rayleigh(a, x0, x1, x2):
    """``x . A x`` (see :func:`_times`)."""
    y0, y1, y2 = _times(a, x0, x1, x2)
    return x0 * y0 + x1 * y1 + x2 * y2


@numba.njit(inline="always")
def _eigh3_smallest(c):
    """Eigenvalues ``(l0, l1, l2)`` and the unit eigenvector of ``l0`` of the symmetric matrix
    with entries ``c = (a00, a01, a02, a11, a12, a22)``: :func:`jaxreg.geometry.eigen.eigh3`'s
    scheme step by step (scaled matrix, trigonometric roots, the isolated root's vector as the
    longest row cross product, the middle one from the 2x2 problem orthogonal to it, Rayleigh
    quotients for the eigenvalues)."""
    scale = 0.0
    for i in range(6):
        scale = max(scale, abs(c[i]))
    live = scale > _TINY
    inv_scale = 1.0 / scale if live else 1.0
    a00, a01, a02 = c[0] * inv_scale, c[1] * inv_scale, c[2] * inv_scale
    a11, a12, a22 = c[3] * inv_scale, c[4] * inv_scale, c[5] * inv_scale
    if not live:
        a00 = a01 = a02 = a11 = a12 = a22 = 0.0
    q = (a00 + a11 + a22) / 3
    b00, b11, b22 = a00 - q, a11 - q, a22 - q
    p2 = (b00 * b00 + b11 * b11 + b22 * b22 + 2 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6
    iso = p2 <= 0
    p = 1.0 if iso else math.sqrt(p2)
    det = b00 * (b11 * b22 - a12 * a12) - a01 * (a01 * b22 - a12 * a02)
    det = det + a02 * (a01 * a12 - b11 * a02)
    half_det = min(max(det / (2 * p * p * p), -1.0), 1.0)
    angle = math.acos(0.0 if iso else half_det) / 3
    beta2 = 2 * math.cos(angle)
    beta0 = 2 * math.cos(angle + 2 * math.pi / 3)
    root0, root1, root2 = q + p * beta0, q + p * -(beta0 + beta2), q + p * beta2
    low_first = half_det < 0  # the smallest root is the isolated one
    lam = root0 if low_first else root2
    f0, f1, f2 = _longest_cross(a00 - lam, a01, a02, a01, a11 - lam, a12, a02, a12, a22 - lam)
    if abs(f0) > abs(f1):
        u0, u1, u2 = _unit(-f2, 0.0, f0, 0.0, 0.0, 1.0)
    else:
        u0, u1, u2 = _unit(0.0, f2, -f1, 0.0, 0.0, 1.0)
    v0, v1, v2 = f1 * u2 - f2 * u1, f2 * u0 - f0 * u2, f0 * u1 - f1 * u0
    a = (a00, a01, a02, a11, a12, a22)
    au0, au1, au2 = _times(a, u0, u1, u2)
    av0, av1, av2 = _times(a, v0, v1, v2)
    m00 = u0 * au0 + u1 * au1 + u2 * au2 - root1
    m01 = u0 * av0 + u1 * av1 + u2 * av2
    m11 = v0 * av0 + v1 * av1 + v2 * av2 - root1
    if abs(m00) >= abs(m11):
        x, y = m01, m00
    else:
        x, y = m11, m01
    d0, d1, d2 = _unit(x * u0 - y * v0, x * u1 - y * v1, x * u2 - y * v2, u0, u1, u2)
    # Re-orthogonalise: where the 2x2 block is ~0 (repeated roots) mid is rounding noise.
    along = d0 * f0 + d1 * f1 + d2 * f2
    d0, d1, d2 = _unit(d0 - along * f0, d1 - along * f1, d2 - along * f2, u0, u1, u2)
    l0, l1, l2 = _unit(f1 * d2 - f2 * d1, f2 * d0 - f0 * d2, f0 * d1 - f1 * d0, v0, v1, v2)
    e0, e1, e2 = (f0, f1, f2) if low_first else (l0, l1, l2)
    g0, g1, g2 = (l0, l1, l2) if low_first else (f0, f1, f2)
    out = scale if live else 0.0
    lam0, lam1, lam2 = _rayleigh(a, e0, e1, e2), _rayleigh(a, d0, d1, d2), _rayleigh(a, g0, g1, g2)
    return lam0 * out, lam1 * out, lam2 * out, e0, e1, e2


@numba.njit(**_CACHE)
def _normals_pass(points, ok, cov, count, viewpoint, flat_tol, codes, first, stop, out):
    """Rows ``first:stop``: ``out (n, 5)`` holds the normal, the curvature and the status code
    (``codes``: invalid point, too few neighbours, degenerate, success)."""
    for i in range(first, stop):
        lam0, lam1, lam2, n0, n1, n2 = _eigh3_smallest(cov[i])
        lam0, lam1, lam2 = max(lam0, 0.0), max(lam1, 0.0), max(lam2, 0.0)
        enough = count[i] >= 3
        # Collinear or coincident neighbours: the middle eigenvalue vanishes next to the largest.
        flat = lam1 <= flat_tol * lam2
        if not ok[i]:
            code = codes[0]
        elif not enough:
            code = codes[1]
        elif flat:
            code = codes[2]
        else:
            code = codes[3]
        if ok[i] and enough and not flat:
            facing = n0 * (viewpoint[0] - points[i, 0]) + n1 * (viewpoint[1] - points[i, 1])
            facing += n2 * (viewpoint[2] - points[i, 2])
            sign = 1.0 if facing >= 0 else -1.0
            out[i, 0], out[i, 1], out[i, 2] = sign * n0, sign * n1, sign * n2
            out[i, 3] = lam0 / (lam0 + lam1 + lam2)
        else:
            out[i, 0] = out[i, 1] = out[i, 2] = out[i, 3] = 0.0
        out[i, 4] = code


def host_normals(points, ok, cov, count, viewpoint, flat_tol: float, codes) -> np.ndarray:
    """``(n, 5)`` float64: unit normals facing ``viewpoint`` (columns 0-2), curvature (3) and
    status code (4) of each point of ``points (n, 3)`` from its neighbourhood covariance
    ``cov (n, 6)`` (entries ``xx, xy, xz, yy, yz, zz``) and neighbour ``count (n,)``; ``ok
    (n,)`` marks valid points, ``flat_tol`` is the degenerate test's ``l1 <= flat_tol * l2``
    and ``codes`` the status codes (invalid point, too few neighbours, degenerate, success)."""
    n = len(points)
    out = np.empty((n, 5))
    pieces = num_pieces(n, _GRAIN)
    bounds = (np.arange(pieces + 1) * n) // pieces
    # One compiled signature whatever the cloud's dtype (the eigenproblems are float64).
    points, viewpoint = (np.asarray(a, np.float64) for a in (points, viewpoint))
    args = (points, ok, cov, count, viewpoint, flat_tol, codes)
    in_pieces(
        lambda a, b: _normals_pass(*args, a, b, out),
        zip(bounds[:-1], bounds[1:], strict=True),
    )
    return out
