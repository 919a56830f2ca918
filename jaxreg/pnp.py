"""Camera projection and Perspective-n-Point: general PnP and planar PnP with both candidates.

Frames and conventions
----------------------
* `camera_T_object` (a `jaxlie.SE3`) maps object coordinates into the camera frame:
  `X_cam = R @ X_obj + t`. The camera looks down +z, x right, y down (OpenCV).
* Pixels: `[u, v, 1] = K @ [x'', y'', 1]` where `(x'', y'')` are the (optionally distorted)
  normalised coordinates `(x/z, y/z)`; pixel centres sit at integer coordinates (OpenCV).
  `K[2]` must be `(0, 0, 1)`; skew `K[0, 1]` is honoured (OpenCV's model has none).
* Distortion: Brown-Conrady in OpenCV order `(k1, k2, p1, p2[, k3])`, radial terms
  `1 + k1 r^2 + k2 r^4 + k3 r^6` plus tangential `p1, p2`, exactly as `cv2.projectPoints`.
* Tangent vectors are jaxlie's `(vx, vy, vz, wx, wy, wz)`; covariances are of the *right*
  perturbation `T_true = T_est @ SE3.exp(delta)`, i.e. expressed in the object frame.
* Reprojection RMSE is `sqrt(mean_i |pi(X_i) - u_i|^2)` over the valid points, in pixels:
  the root-mean-square of per-point Euclidean distances (what `cv2.calibrateCamera` reports).
  `cv2.solvePnPGeneric` reports the per-coordinate RMS instead, which is this divided by sqrt(2).

Algorithms
----------
* General PnP initialiser: EPnP (Lepetit, Moreno-Noguer, Fua 2009). It is linear, works from
  n = 4 non-coplanar points (a DLT on normalised coordinates needs n >= 6), and costs one SVD of
  a (2n, 12) matrix plus a fixed-size Gauss-Newton on four control-point weights, so it has
  static shapes and vmaps. EPnP's three standard approximations give three starts; since EPnP is
  ill-posed for coplanar points, the two IPPE poses on the best-fit plane of the object points
  are added. With n >= 6 the two starts that reproject best are refined (on coplanar input these
  are the two IPPE candidates, so the flip is resolved by the refined error, not the initial one);
  with n = 4 or 5 all five are, because several poses can then explain the pixels. The refined
  pose with the lowest error wins. (With n = 4 non-coplanar points that can still be a local
  minimum: P4P has several solutions, and no linear method ranks them reliably.)
* Planar PnP: IPPE (Collins & Bartoli 2014). A DLT homography maps the plane (the best-fit plane
  of the object points, which for a tag is its z = 0 plane) to normalised image coordinates; its
  first-order expansion at the centroid determines the 2x2 top-left block of the rotation up to
  the sign of the out-of-plane row, which gives two analytic rotations; each gets its
  least-squares translation. Both are refined and reported, sorted by reprojection error, and
  `ambiguity_ratio = rmse[1] / rmse[0]` measures how decisively the data separate them.
* Refinement: `optimistix.LevenbergMarquardt` on a chart centred on the start pose T0,
  `delta = (v, w) -> T0 @ (SO3.exp(w), v)`: a right perturbation on SO(3) x R^3. At delta = 0 it
  has the same Jacobian as jaxlie's `T0 @ SE3.exp(delta)` (so covariances are in jaxlie's tangent
  convention) and the optimum is chart-independent; it skips SE(3)'s V(w) coupling and lets the
  residual be evaluated as start + increment, which keeps float32 accurate (see
  `_chart_residuals`). The chart is centred on the start, so the corrections refinement makes
  never approach the rotation-vector singularity at pi. Each component is scaled so that a unit
  step moves the residuals by about one pixel, which makes LM's isotropic damping and optimistix's
  Cauchy termination treat depth, in-plane motion and tilts alike. Gradients come from the
  implicit function theorem at the optimum (`optimistix.ImplicitAdjoint`); the start pose is a
  constant for differentiation.
* Covariance: first order, `sigma_px^2 (J^T W J)^-1` with `J = d residual / d delta` at the refined
  pose, for independent isotropic pixel noise of standard deviation `sigma_px` per coordinate.
  Near fronto-parallel views of a small tag the out-of-plane rotation is so weakly determined that
  the first-order covariance underestimates its spread; the ambiguity ratio flags those views.

Failure handling
----------------
Shapes are checked on the host (at trace time): fewer than 4 points, mismatched point counts or
malformed `K` raise `ValueError`. Data-dependent failures are data: every result carries a
`status` (`PnPStatus`, one per batch element) naming the problem - too few valid points after
dropping NaN pixels and zero weights, collinear geometry, non-planar points given to the planar
solver, a solution behind the camera, non-finite values, or Levenberg-Marquardt running out of
steps. The pose of a failed lane is whatever the solver reached; check `status` before using it.
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxlie import SE3, SO3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.lie import geodesic_angle, se3_exp

__all__ = [
    "PnPStatus",
    "PnPResult",
    "PlanarPnPResult",
    "project",
    "projection_jacobian",
    "pose_jacobian",
    "reprojection_error",
    "undistort_points",
    "solve_pnp",
    "solve_pnp_result",
    "solve_pnp_planar",
    "solve_pnp_planar_result",
    "tag_object_points",
    "detect_tags",
]

# Relative thresholds on standard deviations (square roots of PCA eigenvalues).
_COLLINEAR_TOL = 1e-3  # second/first principal std of object or image points
_PLANAR_TOL = 1e-2  # third/first principal std above which points are not coplanar


class PnPStatus(eqx.Enumeration):
    """Outcome of one PnP solve, per batch element. `result.status == PnPStatus.success` is a
    boolean array; `PnPStatus[result.best.status]` is the message of one problem's status."""

    success = "success"
    too_few_points = (
        "fewer than 4 valid correspondences (NaN pixels, NaN object points and zero weights "
        "are dropped)"
    )
    degenerate = (
        "degenerate geometry: the object points or their image points are collinear or coincident"
    )
    not_planar = "the object points are not coplanar: use solve_pnp for 3D point sets"
    behind_camera = (
        "the solution puts object points behind the camera (z <= 0): check K, the corner order "
        "and the object frame"
    )
    nonfinite = "non-finite values in the solve: check for inf coordinates or a singular K"
    max_steps = (
        "Levenberg-Marquardt reached max_steps before converging: the pose may be inaccurate"
    )


class PnPResult(eqx.Module):
    """One PnP solution and its diagnostics. Every leaf has the batch shape `(...)` in front.

    - `pose`: `SE3` camera_T_object, batch `(...)`.
    - `reprojection_rmse_px`: `(...)`, RMS of per-point Euclidean pixel errors over valid points.
    - `covariance`: `(..., 6, 6)` right-perturbation covariance, tangent order
      `(vx, vy, vz, wx, wy, wz)` in the object frame, for `sigma_px` pixel noise per coordinate.
    - `translation_sigma`: `(..., 3)` standard deviation of the object origin along the camera's
      x, y, z axes (z is depth), the same units as the object points.
    - `rotation_sigma_deg`: `(..., 3)` standard deviation of the rotation about the object's own
      x, y, z axes, in degrees (for a tag: x, y are out-of-plane tilts, z the in-plane spin).
    - `num_steps`: `(...)` Levenberg-Marquardt steps taken (0 when not refined).
    - `converged`: `(...)` bool, Levenberg-Marquardt met its tolerance (True when not refined).
    - `status`: `PnPStatus`, per batch element.
    """

    pose: SE3
    reprojection_rmse_px: Float[Array, "*batch"]
    covariance: Float[Array, "*batch 6 6"]
    translation_sigma: Float[Array, "*batch 3"]
    rotation_sigma_deg: Float[Array, "*batch 3"]
    num_steps: Int[Array, "*batch"]
    converged: Bool[Array, "*batch"]
    status: PnPStatus


class PlanarPnPResult(eqx.Module):
    """Both IPPE candidates of a planar PnP problem, sorted by reprojection error.

    - `candidates`: `PnPResult` whose leaves have shape `(..., 2, ...)`: index 0 is the best.
    - `ambiguity_ratio`: `(...)`, `rmse[1] / rmse[0]`. Near 1 the two poses explain the corners
      equally well (a near-fronto-parallel or small tag); threshold it (e.g. > 3) before trusting
      the best candidate's out-of-plane rotation.
    - `separation_deg`: `(...)`, geodesic angle between the two candidate rotations. When
      refinement drives both starts into the same minimum it is ~0 and the ratio ~1: then there
      is one solution, whose out-of-plane uncertainty `candidates.rotation_sigma_deg` shows.
    """

    candidates: PnPResult
    ambiguity_ratio: Float[Array, "*batch"]
    separation_deg: Float[Array, "*batch"]

    @property
    def best(self) -> PnPResult:
        """The lowest-error candidate, as a `PnPResult` with the problem's batch shape."""
        return _take_candidate(self.candidates, 0, self.ambiguity_ratio.ndim)

    @property
    def second(self) -> PnPResult:
        """The other candidate, as a `PnPResult` with the problem's batch shape."""
        return _take_candidate(self.candidates, 1, self.ambiguity_ratio.ndim)


def _take_candidate(candidates: PnPResult, index: int, batch_ndim: int) -> PnPResult:
    prefix = (slice(None),) * batch_ndim
    return jax.tree.map(lambda leaf: leaf[prefix + (index,)], candidates)


# --------------------------------------------------------------------------------------------
# Projection
# --------------------------------------------------------------------------------------------


def _distort(xy: Float[Array, "... 2"], dist_coeffs: Float[Array, "... 5"] | None):
    """Brown-Conrady distortion of normalised coordinates; dist_coeffs broadcast over points."""
    if dist_coeffs is None:
        return xy
    d = dist_coeffs[..., None, :]
    k1, k2, p1, p2, k3 = (d[..., i] for i in range(5))
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return jnp.stack([xd, yd], axis=-1)


def _apply_K(xy: Float[Array, "... N 2"], K: Float[Array, "... 3 3"]) -> Float[Array, "... N 2"]:
    k = K[..., None, :, :]
    u = k[..., 0, 0] * xy[..., 0] + k[..., 0, 1] * xy[..., 1] + k[..., 0, 2]
    v = k[..., 1, 0] * xy[..., 0] + k[..., 1, 1] * xy[..., 1] + k[..., 1, 2]
    return jnp.stack([u, v], axis=-1)


def _pad_dist(dist_coeffs):
    if dist_coeffs is None:
        return None
    dist_coeffs = jnp.asarray(dist_coeffs)
    if dist_coeffs.shape[-1] == 4:
        dist_coeffs = jnp.concatenate([dist_coeffs, jnp.zeros_like(dist_coeffs[..., :1])], axis=-1)
    if dist_coeffs.shape[-1] != 5:
        raise ValueError(
            "dist_coeffs must have 4 or 5 entries (k1, k2, p1, p2[, k3]), "
            f"got shape {dist_coeffs.shape}"
        )
    return dist_coeffs


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
    return _apply_K(_distort(xy, _pad_dist(dist_coeffs)), jnp.asarray(K))


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
    `(..., N, 2, 6)`, tangent order `(vx, vy, vz, wx, wy, wz)` (object frame).
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
    dist_coeffs = _pad_dist(dist_coeffs)
    if dist_coeffs is None:
        return distorted

    d = dist_coeffs[..., None, :]
    k1, k2, p1, p2, k3 = (d[..., i] for i in range(5))

    def step(_, xy):
        # distorted = xy * radial(xy) + tangential(xy), solved for xy by fixed-point iteration
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        tangential = jnp.stack(
            [
                2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
                p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
            ],
            axis=-1,
        )
        return (distorted - tangential) / radial[..., None]

    return jax.lax.fori_loop(0, iterations, step, distorted)


# --------------------------------------------------------------------------------------------
# Small linear-algebra helpers (single problem; vmapped by the callers)
#
# jaxlib 0.10's CPU LAPACK kernels split a large batch over XLA's intra-op thread pool and block
# a pool thread until the pieces finish; two such calls running at once on a 2-thread pool
# wait for each other forever (observed here: eigh and LU side by side, from ~5000 tags up).
# So the solvers make at most one LAPACK call at a time: 2x2 and 3x3 systems are closed form,
# calls that would be independent are batched into one, and `_after` orders the rest.
# --------------------------------------------------------------------------------------------


def _after(x, *deps):
    """`x`, available only once `deps` are computed (a data dependency XLA cannot drop)."""
    return jax.lax.optimization_barrier((x, deps))[0]


def _det3(M: Array) -> Array:
    return jnp.dot(M[0], jnp.cross(M[1], M[2]))


def _inv3(M: Array) -> Array:
    """Inverse of a 3x3 matrix by its adjugate (rows r_i: columns r1 x r2, r2 x r0, r0 x r1)."""
    adj = jnp.stack([jnp.cross(M[1], M[2]), jnp.cross(M[2], M[0]), jnp.cross(M[0], M[1])], -1)
    return adj / _det3(M)


def _weighted_pcas(X: Array, m: Array, w: Array):
    """Weighted PCA of the object points and of the normalised image points (as z = 0 points)
    in one batched eigh: for each, centroid (3,), eigenvalues (3,) ascending, eigenvectors (3, 3)
    as columns."""
    points = jnp.stack([X, jnp.concatenate([m, jnp.zeros_like(m[:, :1])], axis=-1)])
    wsum = jnp.maximum(jnp.sum(w), jnp.finfo(X.dtype).tiny)
    centroids = jnp.einsum("n,kni->ki", w, points) / wsum
    centred = points - centroids[:, None]
    scatter = jnp.einsum("n,kni,knj->kij", w, centred, centred) / wsum
    evals, evecs = jnp.linalg.eigh(scatter)
    evals = jnp.maximum(evals, 0.0)
    return (centroids[0], evals[0], evecs[0]), (centroids[1], evals[1], evecs[1])


def _null_space_rows(A: Array, count: int) -> Array:
    """The `count` right singular vectors of A with the smallest singular values, smallest
    first, as rows `(count, A.shape[1])`. A is zero-padded to be at least square."""
    rows, cols = A.shape
    if rows < cols:
        A = jnp.concatenate([A, jnp.zeros((cols - rows, cols), A.dtype)], axis=0)
    _, _, vh = jnp.linalg.svd(A, full_matrices=False)
    return vh[::-1][:count]


def _normalised_rmse(pose: SE3, X: Array, m: Array, w: Array) -> Array:
    """RMS reprojection error in normalised (K^-1, undistorted) coordinates; inf if not finite."""
    Xc = pose @ X
    err = jnp.sum((Xc[:, :2] / Xc[:, 2:3] - m) ** 2, axis=-1)
    rmse = jnp.sqrt(jnp.sum(w * err) / jnp.maximum(jnp.sum(w), jnp.finfo(err.dtype).tiny))
    return jnp.where(jnp.isfinite(rmse), rmse, jnp.inf)


def _translation_given_rotation(R: Array, X: Array, m: Array, w: Array) -> Array:
    """Least-squares t for fixed R on the algebraic error [1 0 -u; 0 1 -v](R X + t) = 0."""
    rows = jnp.stack(
        [
            jnp.stack([jnp.ones_like(m[:, 0]), jnp.zeros_like(m[:, 0]), -m[:, 0]], axis=-1),
            jnp.stack([jnp.zeros_like(m[:, 1]), jnp.ones_like(m[:, 1]), -m[:, 1]], axis=-1),
        ],
        axis=1,
    )  # (N, 2, 3)
    rx = X @ R.T
    rhs = -jnp.einsum("nij,nj->ni", rows, rx)  # (N, 2)
    normal = jnp.einsum("n,nki,nkj->ij", w, rows, rows)
    b = jnp.einsum("n,nki,nk->i", w, rows, rhs)
    return _inv3(normal) @ b


# --------------------------------------------------------------------------------------------
# Initialisers
# --------------------------------------------------------------------------------------------


def _homography(xy: Array, m: Array, w: Array) -> Array:
    """DLT homography H (3x3) with [m, 1] ~ H [xy, 1], Hartley-normalised, weighted rows."""

    def similarity(p):
        wsum = jnp.maximum(jnp.sum(w), jnp.finfo(p.dtype).tiny)
        mu = jnp.sum(w[:, None] * p, axis=0) / wsum
        spread = jnp.sum(w * jnp.linalg.norm(p - mu, axis=-1)) / wsum
        s = jnp.sqrt(2.0) / jnp.maximum(spread, jnp.finfo(p.dtype).tiny)
        one, zero = jnp.ones_like(s), jnp.zeros_like(s)
        T = jnp.stack(
            [
                jnp.stack([s, zero, -s * mu[0]]),
                jnp.stack([zero, s, -s * mu[1]]),
                jnp.stack([zero, zero, one]),
            ]
        )
        T_inv = jnp.stack(
            [
                jnp.stack([1 / s, zero, mu[0]]),
                jnp.stack([zero, 1 / s, mu[1]]),
                jnp.stack([zero, zero, one]),
            ]
        )
        return T, T_inv, (p - mu) * s

    T_src, _, a = similarity(xy)
    _, T_dst_inv, b = similarity(m)
    one, zero = jnp.ones_like(a[:, :1]), jnp.zeros_like(a[:, :1])
    row_u = jnp.concatenate([a, one, zero, zero, zero, -b[:, :1] * a, -b[:, :1]], axis=-1)
    row_v = jnp.concatenate([zero, zero, zero, a, one, -b[:, 1:] * a, -b[:, 1:]], axis=-1)
    sw = jnp.sqrt(w)[:, None]
    A = jnp.concatenate([row_u * sw, row_v * sw], axis=0)
    Hn = _null_space_rows(A, 1)[0].reshape(3, 3)
    H = T_dst_inv @ Hn @ T_src
    return H / jnp.where(H[2, 2] < 0, -1.0, 1.0)


def _ippe_rotations(H: Array) -> tuple[Array, Array]:
    """The two IPPE rotations camera_R_plane from a plane->normalised-image homography whose
    plane origin is the point of expansion (the plane points' centroid)."""
    p, q = H[0, 2] / H[2, 2], H[1, 2] / H[2, 2]
    # Jacobian of the homography at the plane origin.
    J = (H[:2, :2] - jnp.outer(jnp.stack([p, q]), H[2, :2])) / H[2, 2]
    # Rotation Rv taking the optical axis onto the line of sight through (p, q): with
    # u = e_z x v and c = v . e_z, Rv = I + [u]x + [u]x^2 / (1 + c) (c > 0: no singularity).
    v = jnp.stack([p, q, jnp.ones_like(p)]) / jnp.sqrt(p * p + q * q + 1.0)
    ux = jnp.array([[0.0, 0.0, v[0]], [0.0, 0.0, v[1]], [-v[0], -v[1], 0.0]], H.dtype)
    Rv = jnp.eye(3, dtype=H.dtype) + ux + ux @ ux / (1.0 + v[2])
    # [I2 | -(p, q)] Rv = [B | 0], so J = B R'[:2, :2] / depth with R = Rv R'.
    B = Rv[:2, :2] - jnp.outer(jnp.stack([p, q]), Rv[2, :2])
    B_inv = jnp.array([[B[1, 1], -B[0, 1]], [-B[1, 0], B[0, 0]]]) / (
        B[0, 0] * B[1, 1] - B[0, 1] * B[1, 0]
    )
    A = B_inv @ J
    # The 2x2 top-left block of a rotation has largest singular value 1: gamma = 1 / depth.
    ata = A.T @ A
    gamma = jnp.sqrt(
        0.5 * (ata[0, 0] + ata[1, 1] + jnp.sqrt((ata[0, 0] - ata[1, 1]) ** 2 + 4 * ata[0, 1] ** 2))
    )
    Rt = A / gamma
    b0 = jnp.sqrt(jnp.maximum(1.0 - Rt[0, 0] ** 2 - Rt[1, 0] ** 2, 0.0))
    b1 = jnp.sqrt(jnp.maximum(1.0 - Rt[0, 1] ** 2 - Rt[1, 1] ** 2, 0.0))
    # Orthogonal first two columns: Rt00 Rt01 + Rt10 Rt11 + b0 b1 = 0 fixes sign(b1) given b0.
    b1 = jnp.where(Rt[0, 0] * Rt[0, 1] + Rt[1, 0] * Rt[1, 1] > 0, -b1, b1)

    def complete(s):
        c1 = jnp.stack([Rt[0, 0], Rt[1, 0], s * b0])
        c2 = jnp.stack([Rt[0, 1], Rt[1, 1], s * b1])
        return Rv @ jnp.stack([c1, c2, jnp.cross(c1, c2)], axis=-1)

    return complete(1.0), complete(-1.0)


def _plane_frame(centroid: Array, evecs: Array) -> SE3:
    """plane_T_object from the object points' PCA: origin at the weighted centroid, z along the
    smallest principal axis."""
    normal, e1 = evecs[:, 0], evecs[:, 2]
    e2 = jnp.cross(normal, e1)
    R = jnp.stack([e1, e2, normal], axis=0)  # rows: plane axes in object coordinates
    return SE3.from_rotation_and_translation(SO3.from_matrix(R), -R @ centroid)


def _ippe_candidates(X: Array, m: Array, w: Array, object_pca) -> SE3:
    """The two IPPE poses camera_T_object, stacked as an SE3 of batch (2,)."""
    centroid, _, evecs = object_pca
    plane_T_object = _plane_frame(centroid, evecs)
    P = plane_T_object @ X
    H = _homography(P[:, :2], m, w)
    flat = P.at[:, 2].set(0.0)

    def pose(R):
        t = _translation_given_rotation(R, flat, m, w)
        return SE3.from_rotation_and_translation(SO3.from_matrix(R), t) @ plane_T_object

    return jax.vmap(pose)(jnp.stack(_ippe_rotations(H)))


def _rigid_fit(src: Array, dst: Array, w: Array) -> SE3:
    """Weighted least-squares rotation and translation with `pose @ src ~= dst` (one SVD)."""
    wsum = jnp.maximum(jnp.sum(w), jnp.finfo(src.dtype).tiny)
    mu_s = jnp.sum(w[:, None] * src, axis=0) / wsum
    mu_d = jnp.sum(w[:, None] * dst, axis=0) / wsum
    u, _, vh = jnp.linalg.svd((w[:, None] * (dst - mu_d)).T @ (src - mu_s))
    flip = jnp.where(_det3(u) * _det3(vh) < 0, -1.0, 1.0)
    R = (u * jnp.stack([jnp.ones_like(flip), jnp.ones_like(flip), flip])) @ vh
    return SE3.from_rotation_and_translation(SO3.from_matrix(R), mu_d - R @ mu_s)


def _epnp(X: Array, m: Array, w: Array, object_pca) -> SE3:
    """EPnP's three starts camera_T_object (an SE3 of batch (3,)) for n >= 4 non-coplanar
    points, from normalised image coordinates m."""
    dtype = X.dtype
    centroid, evals, evecs = object_pca
    scale = jnp.sqrt(jnp.maximum(evals, evals[-1] * jnp.finfo(dtype).eps))
    # Control points: the centroid and one point along each principal axis.
    ctrl_w = jnp.concatenate([centroid[None], centroid + (evecs * scale).T], axis=0)  # (4, 3)
    a123 = (X - centroid) @ evecs / scale
    alphas = jnp.concatenate([1.0 - jnp.sum(a123, axis=-1, keepdims=True), a123], axis=-1)
    one, zero = jnp.ones_like(m[:, 0]), jnp.zeros_like(m[:, 0])
    coef_u = jnp.stack([one, zero, -m[:, 0]], axis=-1)  # (N, 3)
    coef_v = jnp.stack([zero, one, -m[:, 1]], axis=-1)
    rows_u = (alphas[:, :, None] * coef_u[:, None, :]).reshape(-1, 12)
    rows_v = (alphas[:, :, None] * coef_v[:, None, :]).reshape(-1, 12)
    sw = jnp.sqrt(w)[:, None]
    M = jnp.concatenate([rows_u * sw, rows_v * sw], axis=0)
    kernel = _null_space_rows(M, 4).reshape(4, 4, 3)  # (k, control, xyz)

    pairs_a = jnp.array([0, 0, 0, 1, 1, 2])
    pairs_b = jnp.array([1, 2, 3, 2, 3, 3])
    dist_w = jnp.sum((ctrl_w[pairs_a] - ctrl_w[pairs_b]) ** 2, axis=-1)  # (6,)
    dk = kernel[:, pairs_a] - kernel[:, pairs_b]  # (4, 6, 3)

    def dist_c(beta):
        d = jnp.einsum("k,kpi->pi", beta, dk)
        return jnp.sum(d * d, axis=-1)

    # Linear estimates of beta from subsets of the products beta_k beta_l (EPnP's N = 4, 2, 3
    # approximations), then Gauss-Newton on all four betas.
    gram = jnp.einsum("kpi,lpi->pkl", dk, dk)  # (6, 4, 4): <dk_k, dk_l> per pair

    approximations = (
        [(0, 0), (0, 1), (0, 2), (0, 3)],
        [(0, 0), (0, 1), (1, 1)],
        [(0, 0), (0, 1), (1, 1), (0, 2), (1, 2)],
    )
    # One batched least-squares solve for all three (zero columns pad them to five unknowns;
    # the minimum-norm solution gives those zero).
    systems = jnp.stack(
        [
            jnp.stack(
                [gram[:, i, j] * (1.0 if i == j else 2.0) for i, j in products]
                + [jnp.zeros_like(dist_w)] * (5 - len(products)),
                axis=-1,
            )
            for products in approximations
        ]
    )
    solutions = jax.vmap(lambda A: jnp.linalg.lstsq(A, dist_w)[0])(systems)

    def linear_init(products, sol):
        value = dict(zip(products, sol[: len(products)], strict=True))
        b11 = value[(0, 0)]
        sign = jnp.where(b11 < 0, -1.0, 1.0)
        b1 = jnp.sqrt(jnp.abs(b11))
        safe_b1 = jnp.where(b1 > 0, b1, 1.0)
        beta = jnp.zeros(4, dtype).at[0].set(b1)
        if (1, 1) in value:
            b2 = jnp.sqrt(jnp.abs(value[(1, 1)]))
            beta = beta.at[1].set(jnp.where(sign * value[(0, 1)] < 0, -b2, b2))
        for k in (1, 2, 3):
            if (0, k) in value and (k, k) not in value:
                beta = beta.at[k].set(sign * value[(0, k)] / safe_b1)
        return beta

    inits = jnp.stack(
        [linear_init(p, sol) for p, sol in zip(approximations, solutions, strict=True)]
    )

    def gauss_newton(beta):
        def step(_, b):
            r = dist_c(b) - dist_w
            Jb = jax.jacfwd(dist_c)(b)
            JtJ = Jb.T @ Jb
            damping = 1e-9 * jnp.trace(JtJ) + jnp.finfo(dtype).tiny
            return b - jnp.linalg.solve(JtJ + damping * jnp.eye(4, dtype=dtype), Jb.T @ r)

        return jax.lax.fori_loop(0, 5, step, beta)

    def pose_from_beta(beta):
        ctrl_c = jnp.einsum("k,kci->ci", beta, kernel)
        Xc = alphas @ ctrl_c
        Xc = jnp.where(jnp.sum(w * Xc[:, 2]) < 0, -Xc, Xc)
        return _rigid_fit(X, Xc, w)

    return jax.vmap(lambda b: pose_from_beta(gauss_newton(b)))(inits)


# --------------------------------------------------------------------------------------------
# Refinement, covariance, status
# --------------------------------------------------------------------------------------------


def _tolerances(dtype) -> tuple[float, float]:
    """(rtol, atol) of optimistix's Cauchy test, in the pixel-scaled LM units of `_refine`."""
    return (1e-5, 1e-5) if jnp.finfo(dtype).bits <= 32 else (1e-8, 1e-8)


class _LevenbergMarquardt(optx.LevenbergMarquardt):
    """optimistix's Levenberg-Marquardt plus MINPACK's step-size test: stop when, after a
    rejected step, the next proposed step is below the Cauchy tolerance. optimistix only tests
    accepted steps; at the optimum a float32 loss stops resolving the predicted decrease, every
    step is rejected and the solve would spin until max_steps (keeping a whole vmapped batch
    iterating) although the iterate no longer moves."""

    def terminate(self, fn, y, args, options, state, tags):
        done, result = super().terminate(fn, y, args, options, state, tags)
        step = jnp.abs(state.y_eval - y) / (self.atol + self.rtol * jnp.abs(y))
        stalled = (state.num_steps_since_acceptance > 0) & (self.norm(step) < 1)
        return done | stalled, result


def _rotation_increment(w: Array, X: Array) -> Array:
    """`SO3.exp(w) @ X - X` for points X (N, 3), without the cancellation of subtracting X:
    `A w x X + B w x (w x X)` with A = sin(t)/t, B = (1 - cos t)/t^2 (double-where at t = 0)."""
    theta_sq = jnp.sum(w * w)
    small = theta_sq < (1e-5 if jnp.finfo(w.dtype).bits <= 32 else 1e-10)
    theta = jnp.sqrt(jnp.where(small, 1.0, theta_sq))
    a = jnp.where(small, 1.0 - theta_sq / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta_sq / 24.0, 2.0 * (jnp.sin(0.5 * theta) / theta) ** 2)
    wx = jnp.cross(w, X)
    return a * wx + b * jnp.cross(w, wx)


def _chart(T0: SE3, delta: Array) -> SE3:
    """The pose at chart coordinate delta = (v, w): X -> T0 (exp(w) X + v)."""
    step = SE3.from_rotation_and_translation(SO3.exp(delta[3:]), delta[:3])
    return T0 @ step


def _distortion_increment(xy0: Array, dxy: Array, dist: Array | None) -> Array:
    """`_distort(xy0 + dxy) - _distort(xy0)` for one problem, without cancellation: every term
    is a product with an increment, so float32 keeps its relative precision on small steps."""
    if dist is None:
        return dxy
    k1, k2, p1, p2, k3 = (dist[i] for i in range(5))
    x0, y0 = xy0[:, 0], xy0[:, 1]
    dx, dy = dxy[:, 0], dxy[:, 1]
    x1, y1 = x0 + dx, y0 + dy
    r0 = x0 * x0 + y0 * y0
    r1 = x1 * x1 + y1 * y1
    dx2 = dx * (2.0 * x0 + dx)  # x1^2 - x0^2
    dy2 = dy * (2.0 * y0 + dy)
    dr = dx2 + dy2
    dxy_ = dx * y1 + x0 * dy  # x1 y1 - x0 y0
    radial1 = 1.0 + r1 * (k1 + r1 * (k2 + r1 * k3))
    dradial = dr * (k1 + k2 * (r1 + r0) + k3 * (r1 * r1 + r1 * r0 + r0 * r0))
    ddx = dx * radial1 + x0 * dradial + 2.0 * p1 * dxy_ + p2 * (dr + 2.0 * dx2)
    ddy = dy * radial1 + y0 * dradial + p1 * (dr + 2.0 * dy2) + 2.0 * p2 * dxy_
    return jnp.stack([ddx, ddy], axis=-1)


def _chart_residuals(R0: Array, t0: Array, delta: Array, X, uv, K, dist, sw) -> Array:
    """Weighted pixel residuals (2N,) of the pose `_chart((R0, t0), delta)`.

    Evaluated as the residual at delta = 0 plus the change delta causes. Computed directly,
    pixel coordinates (~1e3) and depths round at ~1e-4 px in float32, a floor on which LM
    rejects every step; as start + increment the residual resolves changes of ~1e-7 of its
    own size. Its Jacobian at delta = 0 is that of the right perturbation `T0 @ SE3.exp(delta)`.
    """
    Xc = X @ R0.T + t0
    xy0 = Xc[:, :2] / Xc[:, 2:3]
    r0 = _apply_K(_distort(xy0, dist), K) - uv
    dXc = (_rotation_increment(delta[3:], X) + delta[:3]) @ R0.T
    z1 = Xc[:, 2:3] + dXc[:, 2:3]
    dxy = (dXc[:, :2] * Xc[:, 2:3] - Xc[:, :2] * dXc[:, 2:3]) / (Xc[:, 2:3] * z1)
    dd = _distortion_increment(xy0, dxy, dist)
    du = dd @ K[:2, :2].T
    return ((r0 + du) * sw[:, None]).reshape(-1)


def _jacobian(pose: SE3, X, uv, K, dist, sw) -> Array:
    """d residual / d delta (2N, 6) of the right perturbation at `pose`."""
    R0, t0 = pose.rotation().as_matrix(), pose.translation()
    return jax.jacfwd(lambda d: _chart_residuals(R0, t0, d, X, uv, K, dist, sw))(
        jnp.zeros(6, X.dtype)
    )


def _refine(T0: SE3, X, uv, K, dist, w, active, *, max_steps: int):
    """Levenberg-Marquardt from T0 (a constant for differentiation).

    The variable is y = s * delta with s the column norms of the residual Jacobian at T0, so a
    unit change of any component moves the residuals by about one pixel: LM's isotropic damping
    and the Cauchy tolerances then mean the same for depth, in-plane motion and tilts, which
    differ by orders of magnitude in pixels per unit. A lane that is not `active` (its input
    already failed) or has a non-finite start gets an all-zero problem that stops at once, so it
    neither returns NaN gradients nor keeps a vmapped batch iterating; it returns T0 unchanged.
    Returns (pose, num_steps, converged).
    """
    T0 = jax.lax.stop_gradient(T0)
    ok = active & jnp.all(jnp.isfinite(T0.wxyz_xyz))
    dummy = jnp.zeros_like(T0.wxyz_xyz).at[0].set(1.0).at[6].set(1.0)  # identity, z = 1
    start = SE3(jnp.where(ok, T0.wxyz_xyz, dummy))
    X, uv = jnp.where(ok, X, 0.0), jnp.where(ok, uv, 0.0)
    sw = jnp.sqrt(jnp.where(ok, w, 0.0))
    R0, t0 = start.rotation().as_matrix(), start.translation()
    scale = jnp.linalg.norm(_jacobian(start, X, uv, K, dist, sw), axis=0)
    scale = jax.lax.stop_gradient(jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0))

    def fn(y, args):
        return _chart_residuals(R0, t0, y / scale, *args, sw)

    rtol, atol = _tolerances(X.dtype)
    sol = optx.least_squares(
        fn,
        _LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.QR()),
        jnp.zeros(6, X.dtype),
        args=(X, uv, K, dist),
        max_steps=max_steps,
        throw=False,
        adjoint=optx.ImplicitAdjoint(linear_solver=lx.AutoLinearSolver(well_posed=None)),
    )
    pose = SE3(jnp.where(ok, _chart(start, sol.value / scale).wxyz_xyz, T0.wxyz_xyz))
    return pose, sol.stats["num_steps"], sol.result == optx.RESULTS.successful


def _residuals(pose: SE3, X, uv, K, dist, sw) -> Array:
    """Weighted pixel residuals (2N,) at `pose`."""
    return ((project(pose @ X, K, dist) - uv) * sw[:, None]).reshape(-1)


def _pixel_rmse(pose: SE3, X, uv, K, dist, w) -> Array:
    """Reprojection RMSE in pixels over the valid points (see the module docstring)."""
    res = _residuals(pose, X, uv, K, dist, jnp.sqrt(w))
    return jnp.sqrt(jnp.sum(res * res) / jnp.maximum(jnp.sum(w), jnp.finfo(res.dtype).tiny))


def _covariance(pose: SE3, X, uv, K, dist, w, sigma_px):
    """sigma^2 (J^T W J)^-1 at `pose`, and the per-axis sigmas described in `PnPResult`."""
    J = _jacobian(pose, X, uv, K, dist, jnp.sqrt(w))
    cov = sigma_px**2 * jnp.linalg.inv(J.T @ J)
    R = pose.rotation().as_matrix()
    t_cov = R @ cov[:3, :3] @ R.T
    t_sigma = jnp.sqrt(jnp.maximum(jnp.diagonal(t_cov), 0.0))
    r_sigma = jnp.rad2deg(jnp.sqrt(jnp.maximum(jnp.diagonal(cov[3:, 3:]), 0.0)))
    return cov, t_sigma, r_sigma


def _sanitise(X, uv, w):
    """Zero out invalid points (NaN pixel or object point, non-positive weight)."""
    valid = jnp.all(jnp.isfinite(uv), -1) & jnp.all(jnp.isfinite(X), -1) & (w > 0)
    valid &= jnp.isfinite(w)
    w = jnp.where(valid, w, 0.0)
    X = jnp.where(valid[:, None], X, 0.0)
    uv = jnp.where(valid[:, None], uv, 0.0)
    return X, uv, w, jnp.sum(valid)


def _geometry_status(obj_evals, img_evals, count, *, planar: bool) -> PnPStatus:
    """Data-dependent checks on the input (PCA eigenvalues, ascending), most fundamental last
    (it wins)."""
    obj_std = jnp.sqrt(obj_evals[::-1])
    img_std = jnp.sqrt(img_evals[::-1])
    collinear = (obj_std[1] <= _COLLINEAR_TOL * obj_std[0]) | (
        img_std[1] <= _COLLINEAR_TOL * img_std[0]
    )
    status = PnPStatus.success
    if planar:
        status = PnPStatus.where(
            obj_std[2] > _PLANAR_TOL * obj_std[0], PnPStatus.not_planar, status
        )
    status = PnPStatus.where(collinear, PnPStatus.degenerate, status)
    return PnPStatus.where(count < 4, PnPStatus.too_few_points, status)


def _finish(pose, X, uv, K, dist, w, sigma_px, num_steps, converged, status) -> PnPResult:
    cov, t_sigma, r_sigma = _covariance(pose, X, uv, K, dist, w, sigma_px)
    rmse = _pixel_rmse(pose, X, uv, K, dist, w)
    depth = (pose @ X)[:, 2]
    behind = jnp.any((depth <= 0) & (w > 0))
    finite = jnp.all(jnp.isfinite(pose.wxyz_xyz)) & jnp.isfinite(rmse)
    late = PnPStatus.where(converged, PnPStatus.success, PnPStatus.max_steps)
    late = PnPStatus.where(behind, PnPStatus.behind_camera, late)
    late = PnPStatus.where(finite, late, PnPStatus.nonfinite)
    status = PnPStatus.where(status == PnPStatus.success, late, status)
    return PnPResult(
        pose=pose,
        reprojection_rmse_px=rmse,
        covariance=cov,
        translation_sigma=t_sigma,
        rotation_sigma_deg=r_sigma,
        num_steps=jnp.asarray(num_steps, jnp.int32),
        converged=jnp.asarray(converged),
        status=status,
    )


def _general_core(X, uv, K, dist, w, sigma_px, *, max_steps: int) -> PnPResult:
    X, uv, w, count = _sanitise(X, uv, w)
    m = undistort_points(uv, K, dist)
    object_pca, image_pca = _weighted_pcas(X, m, w)
    status = _geometry_status(object_pca[1], image_pca[1], count, planar=False)
    epnp = _epnp(X, m, w, object_pca)
    ippe = _ippe_candidates(X, _after(m, epnp.wxyz_xyz), w, object_pca)  # one LAPACK call at a time
    starts = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), epnp, ippe)
    # With N <= 5 points several poses can fit (and EPnP's approximations are rough): refine
    # all five starts. With more points the two best starts cover the planar two-fold ambiguity.
    num_starts = 5 if X.shape[0] <= 5 else 2
    init_errs = jax.vmap(lambda T: _normalised_rmse(T, X, m, w))(starts)
    starts = jax.tree.map(lambda leaf: leaf[jnp.argsort(init_errs)[:num_starts]], starts)
    active = status == PnPStatus.success
    poses, steps, converged = jax.vmap(
        lambda T0: _refine(T0, X, uv, K, dist, w, active, max_steps=max_steps)
    )(starts)
    # The best fit wins even with points behind the camera: its status then says so.
    errs = jax.vmap(lambda T: _pixel_rmse(T, X, uv, K, dist, w))(poses)
    best = jnp.argmin(jnp.where(jnp.isfinite(errs), errs, jnp.inf))
    pose, steps, converged = jax.tree.map(lambda leaf: leaf[best], (poses, steps, converged))
    return _finish(pose, X, uv, K, dist, w, sigma_px, steps, converged, status)


def _planar_core(X, uv, K, dist, w, sigma_px, *, max_steps: int, refine: bool):
    X, uv, w, count = _sanitise(X, uv, w)
    m = undistort_points(uv, K, dist)
    object_pca, image_pca = _weighted_pcas(X, m, w)
    status = _geometry_status(object_pca[1], image_pca[1], count, planar=True)

    def one(T0):
        if refine:
            active = status == PnPStatus.success
            pose, steps, converged = _refine(T0, X, uv, K, dist, w, active, max_steps=max_steps)
        else:
            pose, steps, converged = T0, jnp.array(0), jnp.array(True)
        return _finish(pose, X, uv, K, dist, w, sigma_px, steps, converged, status)

    both = jax.vmap(one)(_ippe_candidates(X, m, w, object_pca))
    rmse = both.reprojection_rmse_px
    order = jnp.where(rmse[1] < rmse[0], jnp.array([1, 0]), jnp.array([0, 1]))
    both = jax.tree.map(lambda leaf: leaf[order], both)
    rmse = both.reprojection_rmse_px
    ratio = rmse[1] / jnp.maximum(rmse[0], jnp.finfo(rmse.dtype).tiny)
    rotations = both.pose.rotation()
    separation = jnp.rad2deg(geodesic_angle(SO3(rotations.wxyz[0]), SO3(rotations.wxyz[1])))
    return PlanarPnPResult(candidates=both, ambiguity_ratio=ratio, separation_deg=separation)


# --------------------------------------------------------------------------------------------
# Batching and host-side validation
# --------------------------------------------------------------------------------------------


# Trailing (core) dimensions of object_points, image_points, K, dist_coeffs, weights.
_CORE_NDIMS = (2, 2, 2, 1, 1)


def _prepare(name, object_points, image_points, K, dist_coeffs, weights):
    """Host-side shape checks; returns float arrays of one dtype and the broadcast batch shape."""
    object_points, image_points, K = (jnp.asarray(a) for a in (object_points, image_points, K))
    dist_coeffs = None if dist_coeffs is None else jnp.asarray(dist_coeffs)
    if object_points.ndim < 2 or object_points.shape[-1] != 3:
        raise ValueError(f"{name}: object_points must be (..., N, 3), got {object_points.shape}")
    if image_points.ndim < 2 or image_points.shape[-1] != 2:
        raise ValueError(f"{name}: image_points must be (..., N, 2), got {image_points.shape}")
    n = object_points.shape[-2]
    if image_points.shape[-2] != n:
        raise ValueError(f"{name}: {n} object points but {image_points.shape[-2]} image points")
    if n < 4:
        raise ValueError(f"{name} needs at least 4 correspondences, got {n}")
    if K.ndim < 2 or K.shape[-2:] != (3, 3):
        raise ValueError(f"{name}: K must be (3, 3) or (..., 3, 3), got {K.shape}")
    dist_coeffs = _pad_dist(dist_coeffs)
    weights = jnp.ones(object_points.shape[:-1]) if weights is None else jnp.asarray(weights)
    if weights.ndim < 1 or weights.shape[-1] != n:
        raise ValueError(f"{name}: weights must be (..., {n}), got {weights.shape}")
    arrays = [object_points, image_points, K, dist_coeffs, weights]
    dtype = np.result_type(*(a.dtype for a in arrays if a is not None), np.float32)
    dtype = jax.dtypes.canonicalize_dtype(dtype if np.issubdtype(dtype, np.floating) else float)
    arrays = [None if a is None else a.astype(dtype) for a in arrays]
    core_ndims = _CORE_NDIMS
    try:
        batch = np.broadcast_shapes(
            *(
                a.shape[: a.ndim - k]
                for a, k in zip(arrays, core_ndims, strict=True)
                if a is not None
            )
        )
    except ValueError as err:
        shapes = [None if a is None else a.shape for a in arrays]
        raise ValueError(f"{name}: batch axes do not broadcast: {shapes}") from err
    return arrays, tuple(batch)


def _vmap_batch(core, arrays, core_ndims, batch, *extra):
    """Run an unbatched `core(*arrays, *extra)` over the broadcast leading `batch` axes."""
    if not batch:
        return core(*arrays, *extra)
    size = int(np.prod(batch))
    flat, axes = [], []
    for a, k in zip(arrays, core_ndims, strict=True):
        if a is None or a.ndim == k:
            flat.append(a)
            axes.append(None)
        else:
            flat.append(
                jnp.broadcast_to(a, batch + a.shape[a.ndim - k :]).reshape(
                    size, *a.shape[a.ndim - k :]
                )
            )
            axes.append(0)
    out = jax.vmap(core, in_axes=(*axes, *(None,) * len(extra)))(*flat, *extra)
    return jax.tree.map(lambda leaf: leaf.reshape(*batch, *leaf.shape[1:]), out)


@functools.partial(jax.jit, static_argnames=("batch", "max_steps"))
def _solve_general(arrays, sigma_px, *, batch, max_steps):
    core = functools.partial(_general_core, max_steps=max_steps)
    return _vmap_batch(core, arrays, _CORE_NDIMS, batch, sigma_px)


@functools.partial(jax.jit, static_argnames=("batch", "max_steps", "refine"))
def _solve_planar(arrays, sigma_px, *, batch, max_steps, refine):
    core = functools.partial(_planar_core, max_steps=max_steps, refine=refine)
    return _vmap_batch(core, arrays, _CORE_NDIMS, batch, sigma_px)


# --------------------------------------------------------------------------------------------
# Public solvers
# --------------------------------------------------------------------------------------------


def solve_pnp_result(
    object_points: Float[ArrayLike, "*batch N 3"],
    image_points: Float[ArrayLike, "*batch N 2"],
    K: Float[ArrayLike, "*batch 3 3"],
    *,
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
    weights: Float[ArrayLike, "*batch N"] | None = None,
    sigma_px: float | Float[ArrayLike, ""] = 1.0,
    max_steps: int = 100,
) -> PnPResult:
    """General PnP with diagnostics: EPnP / IPPE start, Levenberg-Marquardt refinement.

    - `object_points` `(..., N, 3)`: points in the object frame, N >= 4 (coplanar allowed).
    - `image_points` `(..., N, 2)`: observed pixels (with distortion, if any). NaN rows are
      dropped like zero weights.
    - `K` `(3, 3)` or `(..., 3, 3)`, `dist_coeffs` `None` or `(..., 4|5)` (OpenCV order).
    - `weights` `(..., N)`: 0 marks padding; otherwise relative inverse variances of the pixels.
    - `sigma_px`: pixel noise std per coordinate, scales `covariance` and the sigmas.
    - `max_steps`: LM step budget (static).

    Leading batch axes of all arguments broadcast; one call solves every problem (vmap inside,
    one compile per shape). Returns a `PnPResult` (pose camera_T_object); differentiable with
    respect to every floating input by implicit differentiation at the optimum.
    Raises `ValueError` for N < 4 or malformed shapes.
    """
    arrays, batch = _prepare("solve_pnp", object_points, image_points, K, dist_coeffs, weights)
    sigma_px = jnp.asarray(sigma_px, arrays[0].dtype)
    if sigma_px.ndim != 0:
        raise ValueError("solve_pnp: sigma_px must be a scalar")
    return _solve_general(arrays, sigma_px, batch=batch, max_steps=max_steps)


def solve_pnp(
    object_points: Float[ArrayLike, "*batch N 3"],
    image_points: Float[ArrayLike, "*batch N 2"],
    K: Float[ArrayLike, "*batch 3 3"],
    *,
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
) -> SE3:
    """camera_T_object from N >= 4 point correspondences (batch `(...)`).

    Same arguments as `solve_pnp_result`, which also returns the reprojection error,
    covariance and `status`; use that under jit, where failure is only visible as data.
    """
    return solve_pnp_result(object_points, image_points, K, dist_coeffs=dist_coeffs).pose


def solve_pnp_planar_result(
    object_points: Float[ArrayLike, "*batch N 3"],
    image_points: Float[ArrayLike, "*batch N 2"],
    K: Float[ArrayLike, "*batch 3 3"],
    *,
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
    weights: Float[ArrayLike, "*batch N"] | None = None,
    sigma_px: float | Float[ArrayLike, ""] = 1.0,
    refine: bool = True,
    max_steps: int = 100,
) -> PlanarPnPResult:
    """Planar PnP (IPPE) returning both candidate poses with diagnostics.

    `object_points` `(..., N, 3)` must be coplanar (any plane; a tag's corners are usually
    `tag_object_points(size)`, on z = 0); other arguments as in `solve_pnp_result`. With
    `refine=False` the candidates are IPPE's analytic poses (what `cv2.solvePnPGeneric` with
    `SOLVEPNP_IPPE`/`IPPE_SQUARE` returns); by default each is refined by Levenberg-Marquardt
    to the nearest minimum of the pixel reprojection error, which for a 45 mm tag at 0.55 m with
    0.2 px corner noise moves the analytic pose by up to ~0.7 mm and a few degrees of tilt (the
    weakly determined directions). Candidates are sorted by error; the ambiguity ratio and the
    candidates' separation are in the returned `PlanarPnPResult`.
    """
    arrays, batch = _prepare(
        "solve_pnp_planar", object_points, image_points, K, dist_coeffs, weights
    )
    sigma_px = jnp.asarray(sigma_px, arrays[0].dtype)
    if sigma_px.ndim != 0:
        raise ValueError("solve_pnp_planar: sigma_px must be a scalar")
    return _solve_planar(arrays, sigma_px, batch=batch, max_steps=max_steps, refine=refine)


def solve_pnp_planar(
    object_points: Float[ArrayLike, "*batch N 3"],
    image_points: Float[ArrayLike, "*batch N 2"],
    K: Float[ArrayLike, "*batch 3 3"],
    *,
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
) -> tuple[SE3, Float[Array, "*batch 2"]]:
    """Both planar-PnP candidates: `(poses, rmse)`.

    `poses` is an `SE3` of batch `(..., 2)` (camera_T_object, best first) and `rmse` `(..., 2)`
    their reprojection RMSE in pixels. The ambiguity ratio is `rmse[..., 1] / rmse[..., 0]`;
    `solve_pnp_planar_result` returns it together with covariances and per-candidate status.
    """
    result = solve_pnp_planar_result(object_points, image_points, K, dist_coeffs=dist_coeffs)
    return result.candidates.pose, result.candidates.reprojection_rmse_px


# --------------------------------------------------------------------------------------------
# Tags
# --------------------------------------------------------------------------------------------


def tag_object_points(tag_size: float) -> Float[Array, "4 3"]:
    """Corners of a square tag of side `tag_size` in its own frame (z = 0, z out of the front
    face, x right, y up), in the order ArUco detectors and `cv2.SOLVEPNP_IPPE_SQUARE` use:
    top-left, top-right, bottom-right, bottom-left as seen in the image."""
    h = 0.5 * tag_size
    return jnp.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def detect_tags(
    image: np.ndarray,
    dictionary: str | int | Any = "DICT_4X4_50",
    *,
    subpixel: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Detect ArUco/AprilTag markers with OpenCV (>= 4.7, optional `peers` extra).

    - `image`: `(H, W)` grayscale or `(H, W, 3)` BGR `uint8`.
    - `dictionary`: a `cv2.aruco` predefined dictionary name (e.g. "DICT_4X4_50",
      "DICT_APRILTAG_36h11"), its integer id, or a `cv2.aruco.Dictionary`.
    - `subpixel`: refine corners to sub-pixel accuracy (`CORNER_REFINE_SUBPIX`).

    Returns `corners` `(T, 4, 2)` float64 pixels in `tag_object_points` order and `ids` `(T,)`
    int (T = 0 when nothing is found). Host-only (numpy); not jittable. OpenCV's sub-pixel
    refinement places the outer corners of a ~50 px tag ~0.25 px inside the true ones (a ~1%
    scale bias, hence ~1% in depth); it is the detector's, not the solver's.
    """
    try:
        import cv2
    except ImportError as err:
        raise ImportError(
            "detect_tags needs OpenCV: pip install 'jaxreg[peers]' (opencv-python-headless)"
        ) from err
    aruco = cv2.aruco
    if isinstance(dictionary, str):
        if not hasattr(aruco, dictionary):
            raise ValueError(f"unknown cv2.aruco dictionary {dictionary!r}")
        dictionary = getattr(aruco, dictionary)
    if isinstance(dictionary, (int, np.integer)):
        dictionary = aruco.getPredefinedDictionary(int(dictionary))
    params = aruco.DetectorParameters()
    if subpixel:
        params.cornerRefinementMethod = aruco.CORNER_REFINE_SUBPIX
    detector = aruco.ArucoDetector(dictionary, params)
    corners, ids, _ = detector.detectMarkers(np.asarray(image))
    if ids is None or len(corners) == 0:
        return np.zeros((0, 4, 2)), np.zeros((0,), dtype=int)
    return (
        np.stack([np.asarray(c, np.float64).reshape(4, 2) for c in corners]),
        np.asarray(ids, dtype=int).reshape(-1),
    )
