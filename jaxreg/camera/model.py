"""The camera model: pinhole projection with Brown-Conrady distortion, and its inverse.

Every pixel-space computation in jaxreg (PnP, tags, RGB-D frames) goes through this module, so
the conventions live in one place; `Intrinsics` and `RGBDFrame` (a depth image with its camera
and hand-eye pose) are the objects the pipeline and the synthetic scenes pass around:

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
differentiable; `undistort_points` is a fixed number of fixed-point steps. The Jacobians are
closed form (elementwise over the batch).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Bool, Float, Int, Shaped

from jaxreg.core._leaves import as_leaf
from jaxreg.geometry.lie import se3_from_matrix

__all__ = [
    "Intrinsics",
    "RGBDFrame",
    "apply_intrinsics",
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
    return None if dist_coeffs is None else _canonical_dist(jnp.asarray(dist_coeffs))


def _canonical_dist(dist):
    """`canonical_dist_coeffs` of a numpy or JAX array, in its own kind."""
    if dist.shape[-1:] == (4,):
        xp = np if isinstance(dist, np.ndarray) else jnp
        dist = xp.concatenate([dist, xp.zeros_like(dist[..., :1])], axis=-1)
    if dist.shape[-1:] != (5,):
        raise ValueError(
            f"dist_coeffs must have 4 or 5 entries (k1, k2, p1, p2[, k3]), got shape {dist.shape}"
        )
    return dist


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


def _distortion_jacobian(xy: Array, dist: Array | None) -> tuple[Array, Array, Array, Array]:
    """Entries `(d00, d01, d10, d11)`, each `(..., N)`, of `d distort(xy) / d xy` (the
    identity without distortion)."""
    x, y = xy[..., 0], xy[..., 1]
    if dist is None:
        one, zero = jnp.ones_like(x), jnp.zeros_like(x)
        return one, zero, zero, one
    d = dist[..., None, :]
    k1, k2, p1, p2, k3 = (d[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3))  # d radial / d r2, times 2
    cross = x * y * dradial + 2.0 * (p1 * x + p2 * y)
    return (
        radial + x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x,
        cross,
        cross,
        radial + y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x,
    )


def _projection_jacobian(points_cam: Array, K: Array, dist: Array | None) -> Array:
    """`K[:2, :2] @ D @ P`, `(..., N, 2, 3)`: P the Jacobian of `(x/z, y/z)`, D the
    distortion's; closed form, elementwise."""
    k = K[..., None, :, :]
    inv_z = 1.0 / points_cam[..., 2]
    x, y = points_cam[..., 0] * inv_z, points_cam[..., 1] * inv_z
    d00, d01, d10, d11 = _distortion_jacobian(jnp.stack([x, y], axis=-1), dist)
    # rows of K2 @ D, then times P = [[1, 0, -x], [0, 1, -y]] / z
    a00 = k[..., 0, 0] * d00 + k[..., 0, 1] * d10
    a01 = k[..., 0, 0] * d01 + k[..., 0, 1] * d11
    a10 = k[..., 1, 0] * d00 + k[..., 1, 1] * d10
    a11 = k[..., 1, 0] * d01 + k[..., 1, 1] * d11
    row0 = jnp.stack([a00 * inv_z, a01 * inv_z, -(a00 * x + a01 * y) * inv_z], axis=-1)
    row1 = jnp.stack([a10 * inv_z, a11 * inv_z, -(a10 * x + a11 * y) * inv_z], axis=-1)
    return jnp.stack([row0, row1], axis=-2)


def projection_jacobian(
    points_cam: Float[ArrayLike, "*batch N 3"],
    K: Float[ArrayLike, "*batch 3 3"],
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
) -> Float[Array, "*batch N 2 3"]:
    """Jacobian of `project` with respect to each camera-frame point: `(..., N, 2, 3)`.

    Entry `[..., n, i, j]` is `d pixel_i / d X_j` of point n (closed form).
    """
    points_cam = jnp.asarray(points_cam)
    points_cam = points_cam.astype(jnp.result_type(points_cam, float))
    K = jnp.asarray(K, points_cam.dtype)
    return _projection_jacobian(points_cam, K, canonical_dist_coeffs(dist_coeffs))


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
    has batch `(...)`, `object_points` `(..., N, 3)` are in the object frame. Closed form: the
    point moves by `R (v + w x X)`, so with `A = d pixel / d X_cam @ R` the translation block
    is `A` and the rotation block's rows are `X x a` for the rows `a` of `A`.
    """
    object_points = jnp.asarray(object_points)
    dtype = jnp.result_type(object_points, camera_T_object.wxyz_xyz.dtype, float)
    object_points = object_points.astype(dtype)
    R = camera_T_object.rotation().as_matrix().astype(dtype)
    # Products of 3-vectors written out: XLA's CPU dot is slow on batches of tiny matrices.
    points_cam = jnp.sum(object_points[..., None, :] * R[..., None, :, :], axis=-1)
    points_cam = points_cam + camera_T_object.translation().astype(dtype)[..., None, :]
    J = _projection_jacobian(points_cam, jnp.asarray(K, dtype), canonical_dist_coeffs(dist_coeffs))
    A = jnp.sum(J[..., :, :, None] * R[..., None, None, :, :], axis=-2)  # (..., N, 2, 3)
    X = jnp.broadcast_to(object_points[..., None, :], A.shape)
    return jnp.concatenate([A, jnp.cross(X, A)], axis=-1)


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


# --------------------------------------------------------------------------------------------
# Intrinsics and RGB-D frames
# --------------------------------------------------------------------------------------------


def _positive_scalar(name: str, value) -> Array:
    """`value` as a float array leaf; a concrete value must be finite and positive."""
    array = as_leaf(value, jnp.result_type(float))
    if array.shape != ():
        raise ValueError(f"{name} must be a scalar, got shape {array.shape}")
    if not isinstance(array, jax.core.Tracer):
        host = np.asarray(array)
        if not (np.isfinite(host) and host > 0):
            raise ValueError(f"{name} must be finite and positive, got {float(host)}")
    return array


class Intrinsics(eqx.Module):
    """Pinhole intrinsics of one image size, with optional Brown-Conrady distortion.

    Pixel centres sit at integer coordinates (OpenCV): pixel `(u, v)` (column, row) of an
    image `height` x `width` spans `[u - 0.5, u + 0.5]`, and the principal point `(cx, cy)` of
    an ideal centred lens is `((width - 1) / 2, (height - 1) / 2)`. A camera-frame point
    `(x, y, z)` (z forward, x right, y down; metres) projects to
    `u = fx x'' + cx`, `v = fy y'' + cy`, where `(x'', y'')` is `(x / z, y / z)` distorted by
    `dist_coeffs` (OpenCV order `(k1, k2, p1, p2, k3)`; `None` for none), exactly as `project`.

    `fx, fy, cx, cy` (pixels) and `dist_coeffs` are array leaves: they can be differentiated,
    and `jax.vmap` over a stack of intrinsics batches them. `width` and `height` (pixels) are
    static: they fix array shapes.
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    dist_coeffs: Float[Array, "5"] | None
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(
        self,
        fx: Float[ArrayLike, ""],
        fy: Float[ArrayLike, ""],
        cx: Float[ArrayLike, ""],
        cy: Float[ArrayLike, ""],
        width: int,
        height: int,
        dist_coeffs: Float[ArrayLike, "D"] | None = None,
    ):
        for name, size in (("width", width), ("height", height)):
            if isinstance(size, bool) or not isinstance(size, int | np.integer) or size <= 0:
                raise ValueError(f"{name} must be a positive int (pixels), got {size!r}")
        self.fx = _positive_scalar("fx", fx)
        self.fy = _positive_scalar("fy", fy)
        self.cx = as_leaf(cx, self.fx.dtype)
        self.cy = as_leaf(cy, self.fx.dtype)
        if dist_coeffs is None or isinstance(dist_coeffs, jax.core.Tracer):
            self.dist_coeffs = canonical_dist_coeffs(dist_coeffs)
        else:
            self.dist_coeffs = as_leaf(_canonical_dist(np.asarray(dist_coeffs)))
        if self.dist_coeffs is not None and self.dist_coeffs.shape != (5,):
            raise ValueError(
                f"dist_coeffs must be one vector of 4 or 5, got {self.dist_coeffs.shape}"
            )
        self.width = int(width)
        self.height = int(height)

    @classmethod
    def from_matrix(
        cls,
        K: Float[ArrayLike, "3 3"],
        width: int,
        height: int,
        dist_coeffs: Float[ArrayLike, "D"] | None = None,
    ) -> Intrinsics:
        """Intrinsics from a `(3, 3)` camera matrix `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`.

        Raises `ValueError` for a matrix of another shape or with skew (`K[0, 1] != 0`: not
        representable here; use `project` with the full `K`).
        """
        K = jnp.asarray(K)
        if K.shape != (3, 3):
            raise ValueError(f"K must be (3, 3), got {K.shape}")
        if not isinstance(K, jax.core.Tracer) and (
            K[0, 1] != 0 or K[1, 0] != 0 or np.any(np.asarray(K[2]) != (0.0, 0.0, 1.0))
        ):
            raise ValueError(f"K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height, dist_coeffs)

    @property
    def K(self) -> Float[Array, "3 3"]:
        """The `(3, 3)` camera matrix."""
        zero, one = jnp.zeros_like(self.fx), jnp.ones_like(self.fx)
        return jnp.stack(
            [
                jnp.stack([self.fx, zero, self.cx]),
                jnp.stack([zero, self.fy, self.cy]),
                jnp.stack([zero, zero, one]),
            ]
        )

    @property
    def shape(self) -> tuple[int, int]:
        """`(height, width)`: the shape of a depth image of this camera."""
        return (self.height, self.width)

    def project(self, points_cam: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 2"]:
        """Pixels `(..., 2)` (u, v) of camera-frame points `(..., 3)` (metres, z > 0)."""
        points_cam = jnp.asarray(points_cam)
        flat = points_cam.reshape(-1, 3)
        return project(flat, self.K, self.dist_coeffs).reshape(*points_cam.shape[:-1], 2)

    def rays(self, pixels: Float[ArrayLike, "*batch 2"]) -> Float[Array, "*batch 3"]:
        """Unit-depth rays `(x/z, y/z, 1)` `(..., 3)` of pixels `(..., 2)` (u, v), undistorted.

        A pixel with depth `z` lifts to the camera-frame point `z * rays(pixel)`.
        """
        pixels = jnp.asarray(pixels)
        flat = pixels.reshape(-1, 2).astype(self.fx.dtype)
        xy = undistort_points(flat, self.K, self.dist_coeffs)
        rays = jnp.concatenate([xy, jnp.ones_like(xy[:, :1])], axis=-1)
        return rays.reshape(*pixels.shape[:-1], 3)

    def pixel_grid(self) -> Float[Array, "H W 2"]:
        """`(height, width, 2)` pixel-centre coordinates `(u, v)` of every pixel."""
        v, u = jnp.meshgrid(
            jnp.arange(self.height, dtype=self.fx.dtype),
            jnp.arange(self.width, dtype=self.fx.dtype),
            indexing="ij",
        )
        return jnp.stack([u, v], axis=-1)

    def pixel_rays(self) -> Float[Array, "H W 3"]:
        """`(height, width, 3)` unit-depth rays of every pixel centre (`rays(pixel_grid())`)."""
        return self.rays(self.pixel_grid())


class RGBDFrame(eqx.Module):
    """One depth image (with optional colour) of a calibrated camera on a robot.

    Attributes:
        depth: `(H, W)` z-depth in metres along the camera's optical axis (not the range
            along the ray), NaN where the sensor has no return. The constructor turns 0,
            negative and non-finite values (the file conventions for holes) into NaN.
        intrinsics: `Intrinsics` with `(height, width) == (H, W)`.
        rgb: `(H, W, 3)` uint8 colour registered to the depth pixels, or `None`.
        base_T_camera: `SE3` hand-eye transform mapping camera coordinates into the robot's
            base frame (identity: the base is the camera).

    `points` and `camera_points` are differentiable in `intrinsics` and `base_T_camera`
    (holes give NaN values but zero, never NaN, gradients).
    """

    depth: Float[Array, "H W"]
    intrinsics: Intrinsics
    rgb: Shaped[Array, "H W 3"] | None
    base_T_camera: SE3

    def __init__(
        self,
        depth: Float[ArrayLike, "H W"],
        intrinsics: Intrinsics,
        rgb: Shaped[ArrayLike, "H W 3"] | None = None,
        base_T_camera: SE3 | Float[ArrayLike, "4 4"] | None = None,
    ):
        # concrete images are cleaned on the host: no JAX program to compile (`as_leaf`)
        xp = jnp if isinstance(depth, jax.core.Tracer) else np
        depth = xp.asarray(depth)
        if depth.shape != intrinsics.shape:
            raise ValueError(
                f"depth has shape {depth.shape} but the intrinsics are for "
                f"(height, width) = {intrinsics.shape}: pass the intrinsics of this image size"
            )
        depth = depth.astype(jnp.result_type(depth.dtype, float))
        with np.errstate(invalid="ignore"):
            self.depth = as_leaf(xp.where(xp.isfinite(depth) & (depth > 0), depth, np.nan))
        self.intrinsics = intrinsics
        if rgb is not None:
            rgb = as_leaf(rgb)
            if rgb.shape != (*intrinsics.shape, 3):
                raise ValueError(
                    f"rgb must be (H, W, 3) = {(*intrinsics.shape, 3)} registered to the depth "
                    f"image, got {rgb.shape}"
                )
        self.rgb = rgb
        if base_T_camera is None:
            base_T_camera = SE3(as_leaf(np.array([1.0, 0, 0, 0, 0, 0, 0]), self.depth.dtype))
        elif not isinstance(base_T_camera, SE3):
            base_T_camera = se3_from_matrix(base_T_camera)
        self.base_T_camera = base_T_camera

    @property
    def valid(self) -> Bool[Array, "H W"]:
        """`(H, W)` True where the depth is a measurement (not a hole)."""
        return jnp.isfinite(self.depth)

    def _lift(self, mask) -> tuple[Array, Array]:
        """Camera-frame points with holes and masked pixels at the origin, and the kept mask."""
        keep = self.valid
        if mask is not None:
            mask = jnp.asarray(mask, dtype=bool)
            if mask.shape != self.depth.shape:
                raise ValueError(f"mask must be (H, W) = {self.depth.shape}, got {mask.shape}")
            keep = keep & mask
        safe_depth = jnp.where(keep, self.depth, 0.0)  # holes give zero gradients, not NaN
        return safe_depth[..., None] * self.intrinsics.pixel_rays(), keep

    def camera_points(self, mask: Bool[ArrayLike, "H W"] | None = None) -> Float[Array, "H W 3"]:
        """`(H, W, 3)` camera-frame points (metres) of every pixel; NaN at holes and where the
        optional `(H, W)` bool `mask` is False."""
        points, keep = self._lift(mask)
        return jnp.where(keep[..., None], points, jnp.nan)

    def points_at(
        self, rows: Int[ArrayLike, "*batch"], cols: Int[ArrayLike, "*batch"]
    ) -> Float[Array, "*batch 3"]:
        """`(*batch, 3)` base-frame points (metres) of the pixels `(rows, cols)` alone (integer
        indices, in range); NaN at holes. The same points as `points()[rows, cols]`, without
        lifting the other pixels."""
        rows, cols = jnp.asarray(rows), jnp.asarray(cols)
        z = self.depth[rows, cols]
        pixels = jnp.stack([cols, rows], -1)
        camera = jnp.where(jnp.isfinite(z), z, 0.0)[..., None] * self.intrinsics.rays(pixels)
        pose = self.base_T_camera
        base = camera @ pose.rotation().as_matrix().T + pose.translation()
        return jnp.where(jnp.isfinite(z)[..., None], base, jnp.nan)

    def points(self, mask: Bool[ArrayLike, "H W"] | None = None) -> Float[Array, "H W 3"]:
        """`(H, W, 3)` base-frame points `base_T_camera @ camera_points(mask)` (metres); NaN at
        holes and outside `mask`."""
        points, keep = self._lift(mask)
        rotation = self.base_T_camera.rotation().as_matrix()
        points = points @ rotation.T + self.base_T_camera.translation()
        return jnp.where(keep[..., None], points, jnp.nan)
