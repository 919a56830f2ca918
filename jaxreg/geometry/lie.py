"""SE(3) and SO(3): jaxlie's groups, plus what jaxlie lacks.

Poses and rotations are `jaxlie.SE3` / `jaxlie.SO3`, re-exported unchanged. They carry leading
batch axes natively (`SO3(wxyz=(..., 4))`, `SE3(wxyz_xyz=(..., 7))`); every function here
accepts them and broadcasts over those axes.

Conventions (shared by all of jaxreg):

* a pose maps source/model coordinates into target/scene coordinates: `pose @ points`;
* tangent vectors follow jaxlie: SE(3) twists are `(vx, vy, vz, wx, wy, wz)` (translational part
  first), SO(3) tangents are rotation vectors `(wx, wy, wz)` in radians;
* covariances are of the *right* perturbation: `T_true = T_est @ SE3.exp(delta)`,
  `delta ~ N(0, Sigma)`.

The means (`chordal_mean`, `karcher_mean`) build on this module and live in
:mod:`jaxreg.geometry.means`.

Compute SE(3) exponentials with `se3_exp`, not `SE3.exp`: jaxlie 1.5's version is wrong in
translation by a relative `|w| / 2` for small rotations (see `se3_exp`).

Gradients are finite everywhere, including at the identity and at a half turn: every formula
that is singular there evaluates its dead branch on a safe constant ("double where"), and the
eigenvector-based projections differentiate only the (simple) top eigenvector.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3, SO3
from jaxlie.utils import get_epsilon
from jaxtyping import Array, ArrayLike, Float

__all__ = [
    "SE3",
    "SO3",
    "adjoint_transport",
    "covariance_from_open3d",
    "covariance_to_open3d",
    "geodesic_angle",
    "random_rotations",
    "rotation_angle",
    "rotation_grid",
    "rotation_grid_around",
    "se3_exp",
    "se3_from_matrix",
    "se3_to_matrix",
    "so3_from_matrix",
    "tangent_from_open3d",
    "tangent_to_open3d",
]


def _float_dtype(dtype) -> np.dtype:
    """`dtype`, or JAX's default float (float64 under `jax_enable_x64`, else float32)."""
    return jax.dtypes.canonicalize_dtype(jnp.float64 if dtype is None else dtype)


def _as_float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.floating) else x.astype(_float_dtype(None))


def _positive_w(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    """The representative of `q` / `-q` with a non-negative scalar part (a constant-sign flip,
    so derivatives pass through unchanged)."""
    return jnp.where(q[..., :1] < 0, -q, q)


# --------------------------------------------------------------------------------------------
# The exponential map of SE(3).


@jax.jit
def se3_exp(tangent: Float[ArrayLike, "... 6"]) -> SE3:
    """`exp` of twists `(vx, vy, vz, wx, wy, wz)` `(..., 6)`: use it instead of `SE3.exp`.

    The pose is `(SO3.exp(w), V(w) v)` with the SO(3) left Jacobian
    `V = I + (1 - cos t)/t^2 [w]x + (t - sin t)/t^3 [w]x^2`, `t = |w|`. jaxlie 1.5's `SE3.exp`
    replaces `V` by the rotation matrix `R = I + [w]x + ...` whenever `t^2 < 1e-5` (float32)
    or `1e-10` (float64): its translation is then off by `[w]x v / 2`, a relative error of
    `t / 2` (1.5 mm per metre of translation at `t = 3e-3` rad in float32), its derivative in
    `w` is twice the true one, and `SE3.exp(x.log())` does not round-trip (`SE3.log` is
    right). Here the small-angle branch is the Taylor series of `V` itself, and
    `1 - cos t` is evaluated as `2 sin^2(t/2)` to avoid cancellation just above the branch
    point. Gradients are finite at `w = 0`.
    """
    tangent = _as_float(tangent)
    if tangent.shape[-1:] != (6,):
        raise ValueError(f"se3_exp expects twists (..., 6), got {tangent.shape}")
    v, w = tangent[..., :3], tangent[..., 3:]
    theta_sq = jnp.sum(w**2, axis=-1, keepdims=True)
    small = theta_sq < get_epsilon(tangent.dtype)
    theta_sq_safe = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(theta_sq_safe)
    a = jnp.where(
        small,
        0.5 - theta_sq / 24.0 + theta_sq**2 / 720.0,
        2.0 * jnp.sin(0.5 * theta) ** 2 / theta_sq_safe,
    )
    b = jnp.where(
        small,
        1.0 / 6.0 - theta_sq / 120.0 + theta_sq**2 / 5040.0,
        (theta - jnp.sin(theta)) / (theta_sq_safe * theta),
    )
    w_cross_v = jnp.cross(w, v)
    translation = v + a * w_cross_v + b * jnp.cross(w, w_cross_v)
    return SE3.from_rotation_and_translation(SO3.exp(w), translation)


# --------------------------------------------------------------------------------------------
# Angles.


@jax.jit
def rotation_angle(rotation: SO3) -> Float[Array, ...]:
    """Rotation angle in radians, in `[0, pi]`, of `rotation` (batch `(...)`).

    Computed as `2 atan2(|xyz|, |w|)` of the quaternion: accurate near 0 and near pi (where
    `arccos` of the rotation matrix's trace loses half the digits), independent of the
    quaternion's norm and sign. The gradient is finite everywhere: at the identity (a cone
    point of the angle) it is zero, and at a half turn (a ridge, where `q` and `-q` meet) it
    is the one-sided derivative.
    """
    q = rotation.wxyz
    xyz_sq = jnp.sum(q[..., 1:] ** 2, axis=-1)
    zero = xyz_sq < jnp.finfo(q.dtype).tiny
    xyz_norm = jnp.sqrt(jnp.where(zero, 1.0, xyz_sq))
    return jnp.where(zero, 0.0, 2.0 * jnp.arctan2(xyz_norm, jnp.abs(q[..., 0])))


@jax.jit
def geodesic_angle(a: SO3, b: SO3) -> Float[Array, ...]:
    """Geodesic distance on SO(3): the angle in radians, in `[0, pi]`, of `a^-1 b`.

    `a` and `b` broadcast against each other (batches `(...)`). Equals the bi-invariant
    Riemannian distance `|log(a^-1 b)|` and the angle between the two orientations; stable
    near 0 and near pi, with finite gradients at both (see `rotation_angle`).
    """
    return rotation_angle(a.inverse() @ b)


# --------------------------------------------------------------------------------------------
# Projection to SO(3) through a 4x4 symmetric eigenproblem.


def _gap_tolerance(eigenvalues: Float[Array, "... 4"]) -> Float[Array, "... 1"]:
    scale = jnp.max(jnp.abs(eigenvalues), axis=-1, keepdims=True)
    return 10.0 * jnp.finfo(eigenvalues.dtype).eps * scale + jnp.finfo(eigenvalues.dtype).tiny


@jax.custom_jvp
def top_eigenpair(a: Float[Array, "... 4 4"]) -> tuple[Array, Array]:
    """Eigenvalues ``(..., 4)`` (ascending) and the unit top eigenvector ``(..., 4)`` of the
    symmetric ``a``, with a derivative that stays finite where lower eigenvalues repeat.

    The quaternion eigenproblems of rotation averaging and of Kabsch/Horn alignment share it.
    """
    eigenvalues, vectors = jnp.linalg.eigh(a)
    return eigenvalues, vectors[..., :, -1]


@top_eigenpair.defjvp
def _top_eigenpair_jvp(primals, tangents):
    # d v = sum_{j != top} v_j (v_j^T da v) / (lambda_top - lambda_j). Only gaps to the top
    # eigenvalue appear: repeated lower eigenvalues (e.g. -1, -1, -1 for an exact rotation) are
    # harmless. A (numerically) repeated top eigenvalue means the answer is not unique; its
    # derivative along that direction is set to zero instead of infinity.
    # Eigenvalue tangents are v_j^T da v_j.
    (a,), (da,) = primals, tangents
    eigenvalues, vectors = jnp.linalg.eigh(a)
    top = vectors[..., :, -1]
    gap = eigenvalues[..., -1:] - eigenvalues
    live = (gap > _gap_tolerance(eigenvalues)) & (jnp.arange(4) < 3)
    inverse_gap = jnp.where(live, 1.0 / jnp.where(live, gap, 1.0), 0.0)
    vt_da = jnp.einsum("...ji,...jk->...ik", vectors, da)
    projected = jnp.einsum("...ik,...k->...i", vt_da, top)
    d_eigenvalues = jnp.einsum("...ik,...ki->...i", vt_da, vectors)
    d_top = jnp.einsum("...ij,...j->...i", vectors, inverse_gap * projected)
    return (eigenvalues, top), (d_eigenvalues, d_top)


def procrustes_quaternion_matrix(m: Float[Array, "... 3 3"]) -> Float[Array, "... 4 4"]:
    """Symmetric `K(M)` with `q^T K q = tr(R(q)^T M)` for unit `q = (w, x, y, z)`
    (Bar-Itzhack 2000)."""
    m00, m01, m02 = m[..., 0, 0], m[..., 0, 1], m[..., 0, 2]
    m10, m11, m12 = m[..., 1, 0], m[..., 1, 1], m[..., 1, 2]
    m20, m21, m22 = m[..., 2, 0], m[..., 2, 1], m[..., 2, 2]
    rows = [
        [m00 + m11 + m22, m21 - m12, m02 - m20, m10 - m01],
        [m21 - m12, m00 - m11 - m22, m01 + m10, m02 + m20],
        [m02 - m20, m01 + m10, m11 - m00 - m22, m12 + m21],
        [m10 - m01, m02 + m20, m12 + m21, m22 - m00 - m11],
    ]
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


@jax.jit
def so3_from_matrix(matrix: Float[ArrayLike, "... 3 3"]) -> SO3:
    """The rotation nearest to `matrix` in Frobenius norm, as a unit quaternion with `w >= 0`.

    This is the special orthogonal Procrustes projection `argmax_{R in SO(3)} tr(R^T M)`
    (`U diag(1, 1, det(U V^T)) V^T` for `M = U S V^T`), computed as the top eigenvector of a
    4x4 symmetric matrix: it is exact for a rotation, robust for a slightly non-orthonormal
    block (numerical drift, a 4x4 read from a text file), never returns a reflection, and its
    gradient is finite, also at the identity where an SVD's singular values all repeat.

    `jaxlie.SO3.from_matrix` instead assumes an exact rotation: for `1.02 R` plus a small shear
    it returns a quaternion of norm 1.007 whose rotation is 0.08 degrees off the nearest one.
    """
    m = _as_float(matrix)
    if m.shape[-2:] != (3, 3):
        raise ValueError(f"so3_from_matrix expects (..., 3, 3), got {m.shape}")
    return SO3(wxyz=_positive_w(top_eigenpair(procrustes_quaternion_matrix(m))[1]))


# --------------------------------------------------------------------------------------------
# Conversions.


@jax.jit
def se3_from_matrix(matrix: Float[ArrayLike, "... 4 4"]) -> SE3:
    """`SE3` from homogeneous matrices `(..., 4, 4)` (`[R t; 0 1]`, mapping source to target).

    The rotation block is projected to the nearest rotation (`so3_from_matrix`), so slightly
    non-orthonormal input (float32 products, text files with 6 digits) gives a valid pose; the
    bottom row is ignored. Use this rather than `SE3.from_matrix`, which trusts the block.
    """
    m = _as_float(matrix)
    if m.shape[-2:] != (4, 4):
        raise ValueError(f"se3_from_matrix expects (..., 4, 4), got {m.shape}")
    return SE3.from_rotation_and_translation(so3_from_matrix(m[..., :3, :3]), m[..., :3, 3])


@jax.jit
def se3_to_matrix(pose: SE3) -> Float[Array, "... 4 4"]:
    """Homogeneous matrices `(..., 4, 4)` `[R t; 0 1]` of `pose` (batch `(...)`), in the pose's
    dtype (`SE3.as_matrix` builds JAX's default float instead)."""
    rotation = pose.rotation().as_matrix()
    top = jnp.concatenate([rotation, pose.translation()[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(
        jnp.array([0.0, 0.0, 0.0, 1.0], rotation.dtype), (*top.shape[:-2], 1, 4)
    )
    return jnp.concatenate([top, bottom], axis=-2)


_OPEN3D_ORDER = np.array([3, 4, 5, 0, 1, 2])


def tangent_to_open3d(tangent: Float[ArrayLike, "... 6"]) -> Float[Array, "... 6"]:
    """Reorders a jaxlie twist `(vx, vy, vz, wx, wy, wz)` into Open3D's `(wx, wy, wz, tx, ty, tz)`.

    Open3D's registration pipeline (the Jacobian rows `(p x n, n)` of
    `TransformationEstimationPointToPlane` and of colored ICP, and the rows and columns of
    `get_information_matrix_from_point_clouds`) orders 6-vectors rotation first:
    `xi = (alpha, beta, gamma, a, b, c)`, turned into a pose by `TransformVector6dToMatrix4d`
    as `R = Rz(gamma) Ry(beta) Rx(alpha)`, `t = (a, b, c)`. To first order around zero that is
    the exponential of the jaxlie twist `(a, b, c, alpha, beta, gamma)`, so for the small
    increments and the linearisations where Open3D uses it the two differ by this permutation
    only.

    This is a permutation and nothing else. Open3D's increments are *left* perturbations
    expressed in the target frame (ICP updates `T <- M(xi) T` with `M` the matrix above, and
    its information matrix is `J^T J` of point-to-point residuals with respect to such an
    `xi`), while jaxreg's are right perturbations (`T exp(delta)`): move between the two with
    `adjoint_transport`.
    """
    return jnp.asarray(tangent)[..., _OPEN3D_ORDER]


def tangent_from_open3d(tangent: Float[ArrayLike, "... 6"]) -> Float[Array, "... 6"]:
    """Inverse of `tangent_to_open3d`: `(wx, wy, wz, tx, ty, tz)` -> `(vx, vy, vz, wx, wy, wz)`."""
    return jnp.asarray(tangent)[..., _OPEN3D_ORDER]


def covariance_to_open3d(matrix: Float[ArrayLike, "... 6 6"]) -> Float[Array, "... 6 6"]:
    """Permutes rows and columns of a 6x6 covariance *or* information matrix from jaxlie's
    `(v, w)` order to Open3D's `(w, t)` order: `P M P^T` with `P` the permutation of
    `tangent_to_open3d`. The perturbation side is unchanged (see `tangent_to_open3d`): an
    Open3D information matrix describes a left perturbation; `adjoint_transport` (or, for an
    information matrix `I`, `Ad^T I Ad`) converts sides."""
    m = jnp.asarray(matrix)
    return m[..., _OPEN3D_ORDER, :][..., :, _OPEN3D_ORDER]


def covariance_from_open3d(matrix: Float[ArrayLike, "... 6 6"]) -> Float[Array, "... 6 6"]:
    """Inverse of `covariance_to_open3d`: Open3D's `(w, t)` order back to jaxlie's `(v, w)`."""
    m = jnp.asarray(matrix)
    return m[..., _OPEN3D_ORDER, :][..., :, _OPEN3D_ORDER]


@jax.jit
def adjoint_transport(pose: SE3, cov: Float[ArrayLike, "... 6 6"]) -> Float[Array, "... 6 6"]:
    """`Ad_T Sigma Ad_T^T`: moves a right-perturbation covariance of `pose` to the left one.

    If `T_true = T @ SE3.exp(delta)` with `delta ~ N(0, Sigma)` (jaxreg's convention, tangent
    order `(v, w)`), then exactly `T_true = SE3.exp(Ad_T delta) @ T`, so the perturbation
    expressed on the left, in the frame `T` maps into (the target frame), has covariance
    `Ad_T Sigma Ad_T^T`. `Ad_T = [[R, t^ R], [0, R]]` is `pose.adjoint()`.

    Other uses of the same identity:

    * left to right: `adjoint_transport(pose.inverse(), cov_left)`;
    * re-anchoring the body frame, `T' = T @ B` with fixed `B`: the right covariance of `T'`
      is `adjoint_transport(B.inverse(), Sigma)`.

    `pose` has batch `(...)`, `cov` `(..., 6, 6)`; the two broadcast.
    """
    ad = pose.adjoint()
    cov = jnp.asarray(cov, ad.dtype)
    return ad @ cov @ jnp.swapaxes(ad, -1, -2)


# --------------------------------------------------------------------------------------------
# Sampling.


@functools.partial(jax.jit, static_argnames=("shape", "dtype"))
def random_rotations(key: Array, shape: int | tuple[int, ...] = (), dtype=None) -> SO3:
    """Independent uniform (Haar) random rotations with batch `shape`.

    A normalised standard-normal 4-vector is uniform on the unit sphere S^3, which covers SO(3)
    twice with the Haar measure. Returned with `w >= 0`. `dtype` defaults to JAX's float.
    """
    shape = (shape,) if isinstance(shape, int) else tuple(shape)
    q = jax.random.normal(key, (*shape, 4), _float_dtype(dtype))
    return SO3(wxyz=_positive_w(q / jnp.linalg.norm(q, axis=-1, keepdims=True)))


# Super-Fibonacci constants (Alexa, "Super-Fibonacci Spirals: Fast, Low-Discrepancy Sampling
# of SO(3)", CVPR 2022): phi = sqrt(2) and psi, the real root of psi^4 = psi + 4.
_SUPER_FIBONACCI_PHI = math.sqrt(2.0)
_SUPER_FIBONACCI_PSI = 1.533751168755204288118041


def rotation_grid(n: int, dtype=None) -> SO3:
    """A deterministic near-uniform set of exactly `n` rotations (batch `(n,)`).

    Super-Fibonacci spiral (Alexa, CVPR 2022): sample `i` has `s = i + 1/2`,
    `r = sqrt(s/n)`, `R = sqrt(1 - s/n)`, `alpha = 2 pi s / sqrt(2)`, `beta = 2 pi s / psi`
    and quaternion `(r sin alpha, r cos alpha, R sin beta, R cos beta)`, returned with
    `w >= 0`. Any `n` works, the points are pairwise distinct, and the covering radius (the
    largest angle from any rotation to its nearest grid rotation, measured against 200,000
    random probes) is about

    ======  =========  ==========================  ==========================
    n       grid       random set of n (3 draws)   bound ~(6 pi / n)^1/3
    ======  =========  ==========================  ==========================
    24      84 deg     100 - 122 deg               53 deg
    100     51 deg     66 - 83 deg                 33 deg
    300     35 deg     47 - 49 deg                 23 deg
    1000    22 deg     34 - 38 deg                 15 deg
    4000    13.5 deg   22 deg                      9.6 deg
    ======  =========  ==========================  ==========================

    Use it for multi-start registration: with a convergence basin of radius `b`, a grid whose
    covering radius is below `b` puts at least one start inside the basin.
    """
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"rotation_grid needs a positive integer size, got {n!r}")
    s = np.arange(n, dtype=np.float64) + 0.5
    r, big_r = np.sqrt(s / n), np.sqrt(1.0 - s / n)
    alpha = 2.0 * np.pi * s / _SUPER_FIBONACCI_PHI
    beta = 2.0 * np.pi * s / _SUPER_FIBONACCI_PSI
    q = np.stack(
        [r * np.sin(alpha), r * np.cos(alpha), big_r * np.sin(beta), big_r * np.cos(beta)], axis=-1
    )
    q = np.where(q[:, :1] < 0, -q, q)
    return SO3(wxyz=jnp.asarray(q, _float_dtype(dtype)))


_PLASTIC = 1.324717957244746025960908854  # R2 low-discrepancy sequence (Roberts 2018)


@functools.partial(jax.jit, static_argnames=("n",))
def rotation_grid_around(center: SO3, n: int, max_angle: Float[ArrayLike, ""]) -> SO3:
    """`n` deterministic rotations within `max_angle` radians (at most pi) of `center`.

    For multi-start registration around a prior: the result has batch `(*center_batch, n)`
    with `result[..., i] = center @ SO3.exp(v_i)` (a perturbation in `center`'s body frame, the
    right-perturbation convention), so `geodesic_angle(center, result[..., i]) = |v_i|`.
    Sample 0 is `center` itself. The `v_i` fill the ball `|v| <= max_angle` evenly in
    exponential coordinates: radius `max_angle (i / n)^(1/3)` (uniform in volume) and
    direction from the two-dimensional R2 low-discrepancy sequence. For small `max_angle`
    this is uniform in the Haar measure too; at `max_angle = pi/2` the Haar density at the rim
    is 0.81 times that at the centre, so the rim is slightly oversampled.
    """
    if not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"rotation_grid_around needs a positive integer size, got {n!r}")
    i = np.arange(n, dtype=np.float64)
    u = np.mod(0.5 + i[:, None] * np.array([1.0 / _PLASTIC, 1.0 / _PLASTIC**2]), 1.0)
    z = 1.0 - 2.0 * u[:, 0]
    azimuth = 2.0 * np.pi * u[:, 1]
    rho = np.sqrt(np.maximum(0.0, 1.0 - z**2))
    directions = np.stack([rho * np.cos(azimuth), rho * np.sin(azimuth), z], axis=-1)
    unit_ball = directions * np.cbrt(i / n)[:, None]
    dtype = center.wxyz.dtype
    offsets = SO3.exp(jnp.asarray(unit_ball, dtype) * jnp.asarray(max_angle, dtype))
    return SO3(wxyz=center.wxyz[..., None, :]) @ offsets

