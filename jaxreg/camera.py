"""The camera model: pinhole projection with Brown-Conrady distortion, and its inverse.

Every pixel-space computation in jaxreg (PnP, tags, and the RGB-D frames still to come) goes
through these functions, so the conventions live in one place:

* `camera_T_object` (a `jaxlie.SE3`) maps object coordinates into the camera frame:
  `X_cam = R @ X_obj + t`. The camera looks down +z, x right, y down (OpenCV).
* Pixels: `[u, v, 1] = K @ [x'', y'', 1]` where `(x'', y'')` are the (optionally distorted)
  normalised coordinates `(x/z, y/z)`; pixel centres sit at integer coordinates (OpenCV).
  `K[2]` must be `(0, 0, 1)`; skew `K[0, 1]` is honoured (OpenCV's model has none).
* Distortion: Brown-Conrady in OpenCV order `(k1, k2, p1, p2[, k3])`, radial factor
  `1 + k1 r^2 + k2 r^4 + k3 r^6` plus tangential `p1, p2`, exactly as `cv2.projectPoints`.
* Tangent vectors are jaxlie's `(vx, vy, vz, wx, wy, wz)`, perturbing the pose on the right:
  `camera_T_object @ SE3.exp(delta)`, i.e. expressed in the object frame.

All functions take leading batch axes `(...)` that broadcast between arguments, and are
differentiable; `undistort_points` is a fixed number of fixed-point steps.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Float

from jaxreg.lie import se3_exp

__all__ = [
    "apply_intrinsics",
    "canonical_dist_coeffs",
    "distort",
    "pose_jacobian",
    "project",
    "projection_jacobian",
    "reprojection_error",
    "undistort_points",
]


def canonical_dist_coeffs(
    dist_coeffs: Float[ArrayLike, "*batch D"] | None,
) -> Float[Array, "*batch 5"] | None:
    """`None`, or the coefficients as a `(..., 5)` array `(k1, k2, p1, p2, k3)`.

    Four coefficients get `k3 = 0`; any other length raises `ValueError` (at trace time).
    """
    if dist_coeffs is None:
        return None
    dist_coeffs = jnp.asarray(dist_coeffs)
    if dist_coeffs.shape[-1:] == (4,):
        dist_coeffs = jnp.concatenate([dist_coeffs, jnp.zeros_like(dist_coeffs[..., :1])], axis=-1)
    if dist_coeffs.shape[-1:] != (5,):
        raise ValueError(
            "dist_coeffs must have 4 or 5 entries (k1, k2, p1, p2[, k3]), "
            f"got shape {dist_coeffs.shape}"
        )
    return dist_coeffs


def _radial_tangential(xy: Float[Array, "*batch N 2"], dist: Float[Array, "*batch 5"]):
    """Brown-Conrady terms of normalised points: radial factor `(..., N)` and tangential
    offset `(..., N, 2)`, so that `distorted = xy * radial + tangential`."""
    d = dist[..., None, :]
    k1, k2, p1, p2, k3 = (d[..., i] for i in range(5))
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    tangential = jnp.stack(
        [2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x), p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y],
        axis=-1,
    )
    return radial, tangential


def distort(
    xy: Float[ArrayLike, "*batch N 2"], dist_coeffs: Float[ArrayLike, "*batch D"] | None
) -> Float[Array, "*batch N 2"]:
    """Brown-Conrady distortion of normalised coordinates `(x/z, y/z)`, `(..., N, 2)`.

    `dist_coeffs` `None` (no distortion), `(D,)` or `(..., D)` with D = 4 or 5 (OpenCV order);
    one set of coefficients per problem, shared by its N points.
    """
    xy = jnp.asarray(xy)
    dist = canonical_dist_coeffs(dist_coeffs)
    if dist is None:
        return xy
    radial, tangential = _radial_tangential(xy, dist)
    return xy * radial[..., None] + tangential


def apply_intrinsics(
    xy: Float[ArrayLike, "*batch N 2"], K: Float[ArrayLike, "*batch 3 3"]
) -> Float[Array, "*batch N 2"]:
    """Pixels `(..., N, 2)` of (distorted) normalised coordinates: the first two rows of
    `K @ [x'', y'', 1]`, skew included."""
    xy = jnp.asarray(xy)
    k = jnp.asarray(K)[..., None, :, :]
    u = k[..., 0, 0] * xy[..., 0] + k[..., 0, 1] * xy[..., 1] + k[..., 0, 2]
    v = k[..., 1, 0] * xy[..., 0] + k[..., 1, 1] * xy[..., 1] + k[..., 1, 2]
    return jnp.stack([u, v], axis=-1)


def project(
    points_cam: Float[ArrayLike, "*batch N 3"],
    K: Float[ArrayLike, "*batch 3 3"],
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
) -> Float[Array, "*batch N 2"]:
    """Pinhole projection of camera-frame points to pixels, with optional distortion.

    `points_cam` `(..., N, 3)` in the camera frame (z > 0 in front of the camera; z = 0 has no
    projection). `K` `(3, 3)` or `(..., 3, 3)`, `dist_coeffs` `None`, `(D,)` or `(..., D)` with
    D = 4 or 5 in OpenCV order `(k1, k2, p1, p2[, k3])`. Leading axes broadcast.
    Returns pixels `(..., N, 2)`, matching `cv2.projectPoints` with zero rvec/tvec.
    """
    points_cam = jnp.asarray(points_cam)
    xy = points_cam[..., :2] / points_cam[..., 2:3]
    return apply_intrinsics(distort(xy, dist_coeffs), K)


def _batch_jacobian(fn, x: Array, ndim_in: int) -> Array:
    """d fn(x)[..., i] / d x[..., j] for fn acting independently on every leading index of x.

    One forward-mode pass per input component (3 or 6), never a dense Jacobian over the batch.
    """
    basis = jnp.eye(ndim_in, dtype=x.dtype)
    cols = jax.vmap(lambda e: jax.jvp(fn, (x,), (jnp.broadcast_to(e, x.shape),))[1])(basis)
    return jnp.moveaxis(cols, 0, -1)


def projection_jacobian(
    points_cam: Float[ArrayLike, "*batch N 3"],
    K: Float[ArrayLike, "*batch 3 3"],
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
) -> Float[Array, "*batch N 2 3"]:
    """Jacobian of `project` with respect to each camera-frame point: `(..., N, 2, 3)`.

    Entry `[..., n, i, j]` is `d pixel_i / d X_j` of point n (forward-mode autodiff).
    """
    points_cam = jnp.asarray(points_cam)
    points_cam = points_cam.astype(jnp.result_type(points_cam, float))
    return _batch_jacobian(lambda p: project(p, K, dist_coeffs), points_cam, 3)


def _transform(pose: SE3, points: Array) -> Array:
    """`pose @ points` with pose batch `(...)` and points `(..., N, 3)`."""
    R = pose.rotation().as_matrix()
    return jnp.matmul(points, jnp.swapaxes(R, -1, -2)) + pose.translation()[..., None, :]


def pose_jacobian(
    camera_T_object: SE3,
    object_points: Float[ArrayLike, "*batch N 3"],
    K: Float[ArrayLike, "*batch 3 3"],
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
) -> Float[Array, "*batch N 2 6"]:
    """Jacobian of the projected pixels with respect to the right perturbation of the pose.

    `d project(camera_T_object @ exp(delta) @ X_n) / d delta` at `delta = 0`, shape
    `(..., N, 2, 6)`, tangent order `(vx, vy, vz, wx, wy, wz)` (object frame). `camera_T_object`
    has batch `(...)`, `object_points` `(..., N, 3)` are in the object frame.
    """
    object_points = jnp.asarray(object_points)
    delta0 = jnp.zeros((*camera_T_object.get_batch_axes(), 6), camera_T_object.wxyz_xyz.dtype)

    def pixels(delta):
        return project(_transform(camera_T_object @ se3_exp(delta), object_points), K, dist_coeffs)

    return _batch_jacobian(pixels, delta0, 6)


def reprojection_error(
    camera_T_object: SE3,
    object_points: Float[ArrayLike, "*batch N 3"],
    image_points: Float[ArrayLike, "*batch N 2"],
    K: Float[ArrayLike, "*batch 3 3"],
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
) -> Float[Array, "*batch N"]:
    """Per-point Euclidean reprojection error in pixels, `(..., N)`.

    `camera_T_object` batch `(...)`, object points `(..., N, 3)` in the object frame, observed
    `image_points` `(..., N, 2)` in pixels.
    """
    predicted = project(_transform(camera_T_object, jnp.asarray(object_points)), K, dist_coeffs)
    return jnp.linalg.norm(predicted - jnp.asarray(image_points), axis=-1)


def undistort_points(
    image_points: Float[ArrayLike, "*batch N 2"],
    K: Float[ArrayLike, "*batch 3 3"],
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
    *,
    iterations: int = 20,
) -> Float[Array, "*batch N 2"]:
    """Pixels to undistorted normalised coordinates `(x/z, y/z)`, `(..., N, 2)`.

    Inverts `K` exactly and the distortion by `iterations` fixed-point steps (OpenCV's scheme,
    as `cv2.undistortPoints` without `P`); converges for the moderate distortion of real lenses.
    """
    image_points = jnp.asarray(image_points)
    k = jnp.asarray(K)[..., None, :, :]
    yd = (image_points[..., 1] - k[..., 1, 2]) / k[..., 1, 1]
    xd = (image_points[..., 0] - k[..., 0, 2] - k[..., 0, 1] * yd) / k[..., 0, 0]
    distorted = jnp.stack([xd, yd], axis=-1)
    dist = canonical_dist_coeffs(dist_coeffs)
    if dist is None:
        return distorted

    def step(_, xy):
        # distorted = xy * radial(xy) + tangential(xy), solved for xy by fixed-point iteration
        radial, tangential = _radial_tangential(xy, dist)
        return (distorted - tangential) / radial[..., None]

    return jax.lax.fori_loop(0, iterations, step, distorted)
