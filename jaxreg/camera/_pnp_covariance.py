"""First-order covariance of a PnP pose from its pixel Jacobian, batched for `jaxreg.camera.pnp`.

`sigma_px^2 (J^T W J)^-1` with `J` the `(2N, 6)` pixel Jacobian of the right perturbation
`T_true = T_est @ SE3.exp(delta)` (jaxlie tangent order `(vx, vy, vz, wx, wy, wz)`, so the
covariance is in the object frame) at the returned pose, for independent isotropic pixel noise
of `sigma_px` per coordinate. Directions the data do not determine (an eigenvalue of the
column-normalised information below `100 eps` of the largest) get `inf` variance in every
row and column of the tangent coordinates they involve. A closed form (Cholesky) decides the
well-determined and the empty problems; an eigendecomposition runs only when a lane of the
batch is near-singular.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxlie import SE3
from jaxtyping import Array

from jaxreg.camera._pnp_linalg import matmul, packed, spd_inverse_rows
from jaxreg.camera._pnp_refine import _cross, _distortion_jacobian, weighted_jacobian

__all__ = ["covariance", "covariances"]


def _normalised_information(pose: SE3, X, K, dist, w):
    """`J^T W J` at `pose` (zero where not finite), its column norms `col` (1 where zero) and
    `C = J^T W J / outer(col, col)`, whose diagonal is 1 (0 where the column is zero)."""
    J = weighted_jacobian(pose, X, K, dist, jnp.sqrt(w))
    info = matmul(J.T, J)
    info = jnp.where(jnp.all(jnp.isfinite(info)), info, 0.0)
    col = jnp.sqrt(jnp.diagonal(info))
    col = jnp.where(col > 0, col, 1.0)
    return info, col, info / jnp.outer(col, col)


def _with_undetermined(cov, free, pose: SE3, tol):
    """`inf` in the rows and columns of the `free` tangent coordinates, the per-axis sigmas
    described in `jaxreg.camera.pnp.PnPResult`, and whether any coordinate is free."""
    free_pair = free[:, None] | free[None, :]
    R = pose.rotation().as_matrix()
    t_var = jnp.einsum("ij,jk,ik->i", R, jnp.where(free_pair, 0.0, cov)[:3, :3], R)
    t_free = jnp.any(free[None, :3] & (jnp.abs(R) > jnp.sqrt(tol)), axis=1)
    t_sigma = jnp.where(t_free, jnp.inf, jnp.sqrt(jnp.maximum(t_var, 0.0)))
    cov = jnp.where(free_pair, jnp.inf, cov)
    r_sigma = jnp.rad2deg(jnp.sqrt(jnp.maximum(jnp.diagonal(cov[3:, 3:]), 0.0)))
    return cov, t_sigma, r_sigma, jnp.any(free)


def covariance(pose: SE3, X, K, dist, w, sigma_px):
    """`sigma_px^2 (J^T W J)^-1` at `pose` with `inf` on undetermined directions (see the
    module docstring), the per-axis sigmas described in `jaxreg.camera.pnp.PnPResult`, and whether
    any direction is undetermined. One eigendecomposition per problem: the reference for
    `_covariance_closed_form`, used where that one cannot decide."""
    tol = 100 * jnp.finfo(X.dtype).eps
    _, col, C = _normalised_information(pose, X, K, dist, w)
    evals, evecs = jnp.linalg.eigh(C)
    determined = evals > tol * evals[-1]
    inv = jnp.where(determined, 1.0 / jnp.where(determined, evals, 1.0), 0.0)
    cov = sigma_px**2 * ((evecs * inv) @ evecs.T) / jnp.outer(col, col)
    # Tangent coordinates with a share in an undetermined direction (evecs[i, k]: coordinate i).
    free = jnp.any(~determined & (jnp.abs(evecs) > jnp.sqrt(tol)), axis=1)
    return _with_undetermined(cov, free, pose, tol)


def _information(R, t, X, K, dist, sw) -> list[Array]:
    """The 21 upper-triangle entries (row by row) of `J^T W J` at the pose `(R, t)`, on scalars:
    J's rows are `[a R, X x (a R)]` for the rows `a` of the pixels' Jacobian with respect to
    the camera-frame point (`jaxreg.camera.model.pose_jacobian`), weighted by `sw`."""
    Xs = (X[:, 0], X[:, 1], X[:, 2])
    Rs = tuple(tuple(R[i, j] for j in range(3)) for i in range(3))
    Xc = [sum(Rs[i][k] * Xs[k] for k in range(3)) + t[i] for i in range(3)]
    x, y = Xc[0] / Xc[2], Xc[1] / Xc[2]
    d = None if dist is None else tuple(dist[i] for i in range(5))
    (d00, d01), (d10, d11) = _distortion_jacobian(x, y, d)
    inv_z = sw / Xc[2]
    rows = []
    for k0, k1 in ((K[0, 0], K[0, 1]), (K[1, 0], K[1, 1])):
        q0, q1 = k0 * d00 + k1 * d10, k0 * d01 + k1 * d11
        P = (q0 * inv_z, q1 * inv_z, -(q0 * x + q1 * y) * inv_z)
        B = tuple(P[0] * Rs[0][j] + P[1] * Rs[1][j] + P[2] * Rs[2][j] for j in range(3))
        rows.append((*B, *_cross(Xs, B)))
    J0, J1 = rows
    return [jnp.sum(J0[i] * J0[j] + J1[i] * J1[j]) for i in range(6) for j in range(i, 6)]


def _covariance_closed_form(pose: SE3, X, K, dist, w, sigma_px):
    """`covariance`'s outputs without an eigendecomposition, and whether they are its.

    Two cases are decided here. Every direction is determined when `1 / trace(C^-1)`, a lower
    bound on C's smallest eigenvalue, exceeds twice `tol` times the largest absolute row sum of
    C, an upper bound on its largest eigenvalue (the factor 2 covers the rounding of `C^-1`,
    whose relative error there is ~`eps / tol`): then the covariance is the plain inverse, by
    Cholesky. No direction is determined when the information is zero (no weight, or a
    non-finite Jacobian). Between them lie near-singular problems, left to `covariance`: the
    returned flag is False there.

    Written on scalars (`_information`, a Cholesky inverse of rows of scalars), as the
    refinement's step is (`jaxreg.camera._pnp_refine`), so that a vmapped batch runs as
    fused elementwise loops rather than batched dots and slices of `(B, 6, 6)` arrays."""
    dtype = X.dtype
    tol = 100 * jnp.finfo(dtype).eps
    R = pose.rotation().as_matrix()
    info = packed(_information(R, pose.translation(), X, K, dist, jnp.sqrt(w)))
    finite = functools.reduce(jnp.logical_and, [jnp.isfinite(a) for row in info for a in row])
    info = [[jnp.where(finite, a, 0.0) for a in row] for row in info]
    col = [jnp.sqrt(info[i][i]) for i in range(6)]
    col = [jnp.where(c > 0, c, 1.0) for c in col]
    C = [[info[i][j] / (col[i] * col[j]) for j in range(6)] for i in range(6)]
    C_inv, positive = spd_inverse_rows(C)
    trace = sum(C_inv[i][i] for i in range(6))
    largest = functools.reduce(jnp.maximum, [sum(jnp.abs(a) for a in row) for row in C])
    determined = positive & jnp.isfinite(trace) & (trace * 2 * tol * largest < 1.0)
    zero = functools.reduce(jnp.logical_and, [info[i][j] == 0 for i in range(6) for j in range(6)])
    cov = [
        [jnp.where(zero, 0.0, sigma_px**2 * C_inv[i][j] / (col[i] * col[j])) for j in range(6)]
        for i in range(6)
    ]
    # `_with_undetermined` with every coordinate free or none: the translation's variance
    # along the camera axes is `diag(R cov_tt R^T)`.
    t_var = [
        sum(R[i, j] * R[i, k] * cov[j][k] for j in range(3) for k in range(3)) for i in range(3)
    ]
    t_free = [zero & jnp.any(jnp.abs(R[i]) > jnp.sqrt(tol)) for i in range(3)]
    t_sigma = jnp.stack(
        [
            jnp.where(f, jnp.inf, jnp.sqrt(jnp.maximum(v, 0.0)))
            for f, v in zip(t_free, t_var, strict=True)
        ]
    )
    cov = jnp.where(zero, jnp.inf, jnp.stack([jnp.stack(row) for row in cov]))
    r_sigma = jnp.rad2deg(jnp.sqrt(jnp.maximum(jnp.diagonal(cov[3:, 3:]), 0.0)))
    return (cov, t_sigma, r_sigma, zero), determined | zero


def covariances(pose: SE3, X, K, dist, w, sigma_px, axes):
    """`covariance` of a flat batch of problems `(B,)` (X `(B, N, 3)`, w `(B, N)`, K and dist
    batched or shared as `axes` says) at poses of batch `(B,)` or `(B, C)` (C candidates each).

    Closed form where it decides (`_covariance_closed_form`), the eigendecomposition elsewhere;
    that runs only when some lane needs it, and then for the whole batch."""

    def batched(fn):
        f = lambda T, X, K, dist, w: fn(T, X, K, dist, w, sigma_px)  # noqa: E731
        if pose.wxyz_xyz.ndim == 3:
            f = jax.vmap(f, in_axes=(0, None, None, None, None))
        return jax.vmap(f, in_axes=(0, 0, axes[0], axes[1], 0))

    fast, decided = batched(_covariance_closed_form)(pose, X, K, dist, w)

    def fallback():
        exact = batched(covariance)(pose, X, K, dist, w)
        return jax.tree.map(
            lambda a, b: jnp.where(
                decided.reshape(decided.shape + (1,) * (a.ndim - decided.ndim)), a, b
            ),
            fast,
            exact,
        )

    return jax.lax.cond(jnp.all(decided), lambda: fast, fallback)
