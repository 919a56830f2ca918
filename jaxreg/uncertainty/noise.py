"""Measurement noise models and the root-sum-square of independent error contributions.

* Noise models (:class:`IsotropicNoise`, :class:`PointCovariance`, :class:`DepthNoise` for
  points lifted from a depth image through the hand-eye transform) give each point's
  covariance and draw noisy copies for Monte Carlo studies. :func:`jaxreg.icp_covariance`
  (in :mod:`jaxreg.registration.icp`, beside the solver whose Hessian it shares) propagates them to
  the covariance of a registered pose.
* :func:`error_budget` combines independent per-stage sigmas into one (its result feeds
  :func:`jaxreg.uncertainty.grasp.grasp_success_probability`).

Conventions (those of :mod:`jaxreg.geometry.lie`): a pose maps source/model coordinates into
target/scene/base coordinates; tangents are jaxlie's ``(vx, vy, vz, wx, wy, wz)``;
covariances are of the *right* perturbation ``T_true = T_est @ exp(delta)``,
``delta ~ N(0, Sigma)``, so ``Sigma`` is expressed in the source (object) frame. Use
:func:`jaxreg.geometry.lie.adjoint_transport` for the same covariance in the target frame.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Float

from jaxreg.core._leaves import as_leaf

__all__ = [
    "AbstractPointNoise",
    "DepthNoise",
    "ErrorBudget",
    "IsotropicNoise",
    "PointCovariance",
    "error_budget",
]


# --------------------------------------------------------------------------------------------
# Measurement noise models.


class AbstractPointNoise(eqx.Module):
    """Independent zero-mean Gaussian noise on each point of a cloud."""

    @abc.abstractmethod
    def covariance(self, points: Float[Array, "N 3"]) -> Float[Array, "N 3 3"]:
        """Per-point covariances ``(N, 3, 3)`` (square metres) in the frame of ``points``."""

    def sample(self, key: Array, points: Float[ArrayLike, "N 3"]) -> Float[Array, "N 3"]:
        """``points`` plus one draw of the noise (for Monte Carlo studies)."""
        points = jnp.asarray(points)
        lam, vec = jnp.linalg.eigh(self.covariance(points))
        z = jax.random.normal(key, points.shape, points.dtype)
        return points + jnp.einsum("nij,nj->ni", vec * jnp.sqrt(jnp.maximum(lam, 0))[:, None], z)


class IsotropicNoise(AbstractPointNoise):
    """The same isotropic noise on every point: covariance ``sigma**2 I`` (``sigma`` in
    metres, per axis)."""

    sigma: Float[Array, ""]

    def __init__(self, sigma: Float[ArrayLike, ""]):
        self.sigma = jnp.asarray(sigma)

    def covariance(self, points):
        eye = jnp.eye(3, dtype=points.dtype)
        return jnp.broadcast_to(self.sigma.astype(points.dtype) ** 2 * eye, (*points.shape, 3))


class PointCovariance(AbstractPointNoise):
    """Explicit per-point covariances ``(N, 3, 3)`` in the frame of the cloud they belong to."""

    covariances: Float[Array, "N 3 3"]

    def __init__(self, covariances: Float[ArrayLike, "N 3 3"]):
        self.covariances = jnp.asarray(covariances)

    def covariance(self, points):
        if self.covariances.shape != (*points.shape, 3):
            raise ValueError(
                f"PointCovariance holds {self.covariances.shape}, the cloud needs "
                f"{(*points.shape, 3)}"
            )
        return self.covariances.astype(points.dtype)


class DepthNoise(AbstractPointNoise):
    """Noise of points lifted from a depth image: axial along each camera ray, growing with
    depth, plus optional lateral noise from pixel jitter through the focal length.

    A pixel ``(u, v)`` with depth ``z`` lifts to the camera-frame point
    ``p_c = z ((u - cx) / fx, (v - cy) / fy, 1)``. Depth noise ``dz ~ N(0, sigma_z(z)^2)``
    moves it along its ray by ``dz * p_c / z`` (the ray scaled to unit depth, which is
    ``K^-1 (u, v, 1)``); pixel noise ``du, dv ~ N(0, pixel_sigma^2)`` moves it by
    ``z du / fx`` along the camera x axis and ``z dv / fy`` along y. The camera-frame
    covariance

        ``C_c = sigma_z(z)^2 r r^T + pixel_sigma^2 z^2 diag(1/fx^2, 1/fy^2, 0)``,
        ``r = p_c / z``, ``sigma_z(z) = c0 + c1 z + c2 z^2 + ...``

    is rotated into the frame the cloud is expressed in by ``base_T_camera``:
    ``C = R C_c R^T``, with ``p_c = base_T_camera^-1 @ p``. ``base_T_camera`` is the
    hand-eye transform (camera -> robot base) for a cloud in the base frame, the identity
    for a cloud in the camera frame, and in general whatever maps camera coordinates into
    the cloud's coordinates.

    Attributes:
        coefficients: ``(C,)`` polynomial coefficients of ``sigma_z`` in the depth ``z``
            (metres), lowest order first: ``(a, 0, b)`` is the common structured-light /
            stereo model ``sigma_z = a + b z^2``.
        base_T_camera: ``SE3`` camera -> cloud frame (identity by default).
        pixel_sigma: ``()`` pixel noise in pixels per image axis (0: axial noise only).
        focal_length: ``(2,)`` ``(fx, fy)`` in pixels; needed only with ``pixel_sigma > 0``.
    """

    coefficients: Float[Array, " C"]
    base_T_camera: SE3
    pixel_sigma: Float[Array, ""]
    focal_length: Float[Array, " 2"]

    def __init__(
        self,
        coefficients: Float[ArrayLike, " C"],
        base_T_camera: SE3 | None = None,
        pixel_sigma: Float[ArrayLike, ""] = 0.0,
        focal_length: Float[ArrayLike, " 2"] | None = None,
    ):
        # Concrete values become leaves on the host (`as_leaf`): no JAX program per shape.
        if isinstance(coefficients, jax.core.Tracer):
            self.coefficients = jnp.atleast_1d(coefficients)
        else:
            self.coefficients = as_leaf(np.atleast_1d(np.asarray(coefficients)))
        if self.coefficients.ndim != 1:
            raise ValueError(f"coefficients must be a vector, got {self.coefficients.shape}")
        if base_T_camera is None:
            base_T_camera = SE3(as_leaf(np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])))
        self.base_T_camera = base_T_camera
        # a Python scalar stays weakly typed, as jnp.asarray would leave it
        scalar = isinstance(pixel_sigma, (int, float))
        self.pixel_sigma = jax.device_put(pixel_sigma) if scalar else as_leaf(pixel_sigma)
        if focal_length is None:
            if isinstance(pixel_sigma, jax.core.Tracer) or np.any(np.asarray(pixel_sigma) != 0):
                raise ValueError("DepthNoise with pixel_sigma needs focal_length=(fx, fy)")
            focal_length = (1.0, 1.0)  # multiplies a zero pixel noise
        if isinstance(focal_length, jax.core.Tracer):
            self.focal_length = jnp.broadcast_to(focal_length, (2,))
        else:
            focal = np.broadcast_to(np.asarray(focal_length), (2,))
            floating = np.issubdtype(focal.dtype, np.floating)
            self.focal_length = as_leaf(focal, None if floating else jnp.result_type(float))

    @classmethod
    def structured_light(
        cls, focal_length: Float[ArrayLike, " 2"], base_T_camera: SE3 | None = None
    ) -> DepthNoise:
        """A structured-light camera of the Kinect v1 / PrimeSense class (Kinect for Xbox
        360, Asus Xtion Pro Live, PrimeSense Carmine), from Nguyen, Izadi and Lovell,
        "Modeling Kinect Sensor Noise for Improved 3D Reconstruction and Tracking" (3DIMPVT
        2012), measured for surfaces within 60 degrees of the ray: axial
        ``sigma_z = 0.0012 + 0.0019 (z - 0.4)^2`` metres (1.2 mm at 0.5 m, 1.9 mm at 1 m,
        4.2 mm at 1.6 m) and 0.8 pixels of lateral noise. ``focal_length``: ``(fx, fy)``
        in pixels of the depth image the points come from."""
        coefficients = (0.0012 + 0.0019 * 0.16, -0.0019 * 0.8, 0.0019)
        return cls(coefficients, base_T_camera, 0.8, focal_length)

    def axial_sigma(self, depth: Float[ArrayLike, "..."]) -> Float[ArrayLike, "..."]:
        """``sigma_z`` (metres) at camera depth ``depth`` (metres, any shape):
        ``c0 + c1 z + c2 z^2 + ...``, the one evaluation of the polynomial everything that
        weighs depth against its noise uses. A JAX array or a tracer (or traced coefficients)
        gives a JAX array of the depth's dtype, under ``jit`` and ``grad``; a number or a numpy
        array gives a float64 numpy array, computed on the host without a device program (the
        pipeline's host stages call it per pixel)."""
        traced = isinstance(self.coefficients, jax.core.Tracer)
        if traced or isinstance(depth, jax.Array | jax.core.Tracer):
            depth = jnp.asarray(depth)
            powers = depth[..., None] ** jnp.arange(self.coefficients.shape[0], dtype=depth.dtype)
            return jnp.sum(self.coefficients.astype(depth.dtype) * powers, axis=-1)
        coefficients = np.asarray(self.coefficients, np.float64)
        return np.polynomial.polynomial.polyval(np.asarray(depth, np.float64), coefficients)

    def _camera(self, points: Array) -> tuple[Array, Array, Array, Array, Array]:
        """Rotation and translation of ``base_T_camera``, camera-frame rays scaled to unit
        depth, safe depths and the in-front-of-camera mask of ``points``."""
        pose = SE3(self.base_T_camera.wxyz_xyz.astype(points.dtype))
        rot = pose.rotation().as_matrix()
        p_c = (points - pose.translation()) @ rot  # R^T (p - t)
        ok = p_c[:, 2] > 0
        z = jnp.where(ok, p_c[:, 2], 1.0)
        return rot, pose.translation(), p_c / z[:, None], z, ok

    def sample(self, key, points):
        """``points`` re-measured: depth ``z + dz`` along each ray, pixel ``(u + du, v + dv)``
        (exact lifting, not linearised). Points behind the camera are returned unchanged."""
        points = jnp.asarray(points)
        rot, trans, ray, z, ok = self._camera(points)
        key_z, key_uv = jax.random.split(key)
        dz = self.axial_sigma(z) * jax.random.normal(key_z, z.shape, z.dtype)
        duv = self.pixel_sigma.astype(z.dtype) * jax.random.normal(key_uv, (*z.shape, 2), z.dtype)
        shift = jnp.concatenate([duv / self.focal_length.astype(z.dtype), 0 * duv[:, :1]], -1)
        moved = ((z + dz)[:, None] * (ray + shift)) @ rot.T + trans
        return jnp.where(ok[:, None], moved, points)

    def covariance(self, points):
        dtype = points.dtype
        rot, _, ray, z_safe, ok = self._camera(points)
        sigma_z = self.axial_sigma(z_safe)
        cov = (sigma_z**2)[:, None, None] * ray[:, :, None] * ray[:, None, :]
        lateral = (self.pixel_sigma.astype(dtype) * z_safe)[:, None] / self.focal_length.astype(
            dtype
        )
        lateral = jnp.concatenate([lateral**2, jnp.zeros_like(lateral[:, :1])], axis=-1)
        cov = cov + jax.vmap(jnp.diag)(lateral)
        cov = jnp.where(ok[:, None, None], cov, 0.0)
        return rot @ cov @ rot.T


# --------------------------------------------------------------------------------------------
# Independent error contributions.


class ErrorBudget(eqx.Module):
    """Root-sum-square of independent error contributions; see :func:`error_budget`.

    Attributes:
        total: the RSS ``sqrt(sum_i c_i^2)``.
        contributions: ``name -> c_i`` as given.
        shares: ``name -> c_i^2 / total^2``, each stage's fraction of the variance (they sum
            to 1: a stage with half the total sigma owns a quarter of the budget).
    """

    total: Float[Array, "..."]
    contributions: dict[str, Float[Array, "..."]]
    shares: dict[str, Float[Array, "..."]]


def error_budget(contributions: dict[str, Float[ArrayLike, "..."]]) -> ErrorBudget:
    """Combine per-stage standard deviations (e.g. intrinsics, depth noise, hand-eye,
    registration, in mm) into one by root-sum-square, assuming they are independent and
    zero-mean. Values may be arrays (they broadcast). Systematic offsets are not sigmas:
    add biases linearly and pass them to :func:`grasp_success_probability` as ``bias``.

    Raises:
        ValueError: an empty dict or a negative contribution.
    """
    if not contributions:
        raise ValueError("error_budget needs at least one contribution")
    values = {name: jnp.asarray(c, jnp.result_type(float)) for name, c in contributions.items()}
    for name, c in values.items():
        if not isinstance(c, jax.core.Tracer) and bool(jnp.any(c < 0)):
            raise ValueError(f"contribution {name!r} is negative: give standard deviations")
    variance = sum(c**2 for c in values.values())
    total = jnp.sqrt(variance)
    safe = jnp.where(variance > 0, variance, 1.0)
    shares = {name: jnp.where(variance > 0, c**2 / safe, 0.0) for name, c in values.items()}
    return ErrorBudget(total=total, contributions=values, shares=shares)
