"""Pose uncertainty: measurement noise models, repeatability statistics, grasp success.

Three pieces that turn a registered pose into a grasp decision:

* Noise models (:class:`IsotropicNoise`, :class:`PointCovariance`, :class:`DepthNoise` for
  points lifted from a depth image through the hand-eye transform) give each point's
  covariance and draw noisy copies for Monte Carlo studies. :func:`jaxreg.icp_covariance`
  (in :mod:`jaxreg.icp`, beside the solver whose Hessian it shares) propagates them to the
  covariance of a registered pose.
* :func:`pose_statistics` measures the spread of repeated pose estimates: Karcher mean,
  per-axis sigma and bias, rotation spread as geodesic angles, symmetry canonicalisation,
  and the per-viewpoint clustering that betrays a hand-eye bias.
* :func:`grasp_success_probability`, :func:`grasp_margin` and :func:`error_budget` turn
  sigma and bias into the probability that the gripper closes around the object.

Conventions (those of :mod:`jaxreg.lie`): a pose maps source/model coordinates into
target/scene/base coordinates; tangents are jaxlie's ``(vx, vy, vz, wx, wy, wz)``;
covariances are of the *right* perturbation ``T_true = T_est @ exp(delta)``,
``delta ~ N(0, Sigma)``, so ``Sigma`` is expressed in the source (object) frame. Use
:func:`jaxreg.lie.adjoint_transport` for the same covariance in the target frame.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg._leaves import as_leaf
from jaxreg.lie import geodesic_angle, karcher_mean
from jaxreg.metrics import Symmetry

__all__ = [
    "AbstractPointNoise",
    "DepthNoise",
    "ErrorBudget",
    "GroupStatistics",
    "IsotropicNoise",
    "PointCovariance",
    "PoseStatistics",
    "error_budget",
    "grasp_margin",
    "grasp_success_probability",
    "pose_statistics",
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

    def axial_sigma(self, depth: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
        """``sigma_z`` (metres) at camera depth ``depth`` (metres)."""
        depth = jnp.asarray(depth)
        powers = depth[..., None] ** jnp.arange(self.coefficients.shape[0], dtype=depth.dtype)
        return jnp.sum(self.coefficients.astype(depth.dtype) * powers, axis=-1)

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
# Repeatability statistics of a set of pose estimates.


class GroupStatistics(eqx.Module):
    """Per-group statistics of labelled poses (e.g. by camera viewpoint); see
    :func:`pose_statistics`. ``G`` groups; per-axis quantities are in the base frame's axes,
    ``(x, y, z)`` for translations (metres) and rotation vectors (degrees).

    Attributes:
        mean: ``SE3`` batch ``(G,)``, Karcher mean of each group.
        count: ``(G,)`` poses with positive weight in each group.
        translation_sigma: ``(G, 3)`` within-group standard deviation of the position.
        rotation_sigma_deg: ``(G, 3)`` within-group standard deviation of the rotation vector
            ``log(R_k R_mean^-1)``.
        translation_offset: ``(G, 3)`` group mean position minus the overall mean position.
        rotation_offset_deg: ``(G, 3)`` group mean rotation vector relative to the overall mean.
        offset_ratio: ``(6,)`` per axis ``(tx, ty, tz, rx, ry, rz)``: RMS of the group offsets
            over the pooled within-group standard deviation. About ``1/sqrt(n)`` when groups
            differ only by noise (``n`` poses per group); above 1 the clusters visibly separate.
        p_value: ``(6,)`` one-way ANOVA F-test per axis: the probability of group offsets at
            least this large if all groups shared one mean.
        bias_detected: ``()`` some axis has ``p_value < 0.01`` and ``offset_ratio > 1``:
            tight clusters, mutually offset. Between viewpoints this is the signature of a
            hand-eye (or intrinsics) bias, which no repetition from a single viewpoint reveals.
    """

    mean: SE3
    count: Int[Array, " G"]
    translation_sigma: Float[Array, "G 3"]
    rotation_sigma_deg: Float[Array, "G 3"]
    translation_offset: Float[Array, "G 3"]
    rotation_offset_deg: Float[Array, "G 3"]
    offset_ratio: Float[Array, " 6"]
    p_value: Float[Array, " 6"]
    bias_detected: Bool[Array, ""]


class PoseStatistics(eqx.Module):
    """Spread and bias of ``K`` repeated pose estimates; see :func:`pose_statistics`.

    Frames: per-axis quantities use the axes of the frame the poses map into (the base, or
    target, frame): positions ``t_k`` of the object origin, and rotation vectors
    ``log(R_k R_mean^-1)`` (a left perturbation, about base axes). ``covariance`` instead
    follows jaxreg's convention (right perturbation, object frame) so that it can be set
    beside :func:`jaxreg.icp_covariance`.

    Attributes:
        mean: ``SE3``, Karcher mean of the canonicalised poses.
        count: ``()`` poses with positive weight.
        translation_sigma: ``(3,)`` standard deviation of the position per base axis (metres).
        rotation_sigma_deg: ``(3,)`` standard deviation of the rotation vector per base axis.
        rotation_angles_deg: ``(K,)`` geodesic angle of each canonical pose to the mean.
        rotation_spread_deg: ``()`` RMS of those angles (about ``sqrt(3)`` times a per-axis
            sigma for isotropic spread).
        covariance: ``(6, 6)`` sample covariance of ``log(mean^-1 @ T_k)`` (right
            perturbation, jaxlie order ``(v, w)``, metres and radians).
        translation_bias: ``(3,)`` mean position minus the reference position (base frame,
            metres); ``None`` without a reference.
        rotation_bias_deg: ``(3,)`` rotation vector ``log(R_mean R_ref^-1)`` (base axes,
            degrees); its norm is the geodesic angle between mean and reference. ``None``
            without a reference.
        canonical: ``SE3`` batch ``(K,)``, the poses after symmetry canonicalisation.
        symmetry: ``SE3`` batch ``(K,)``, the object-frame symmetry applied to each pose
            (``canonical = pose @ symmetry``; the identity when none was needed).
        groups: :class:`GroupStatistics`, or ``None`` without group labels.
    """

    mean: SE3
    count: Int[Array, ""]
    translation_sigma: Float[Array, " 3"]
    rotation_sigma_deg: Float[Array, " 3"]
    rotation_angles_deg: Float[Array, " K"]
    rotation_spread_deg: Float[Array, ""]
    covariance: Float[Array, "6 6"]
    translation_bias: Float[Array, " 3"] | None
    rotation_bias_deg: Float[Array, " 3"] | None
    canonical: SE3
    symmetry: SE3
    groups: GroupStatistics | None


def _canonicalise(poses: SE3, anchor: SE3, symmetries: SE3) -> tuple[SE3, SE3]:
    """Each pose's symmetric equivalent ``pose @ S`` whose rotation is closest to ``anchor``."""
    candidates = SE3(poses.wxyz_xyz[:, None]) @ SE3(symmetries.wxyz_xyz[None])
    angles = geodesic_angle(anchor.rotation(), candidates.rotation())
    best = jnp.argmin(angles, axis=1)
    chosen = SE3(jnp.take(symmetries.wxyz_xyz, best, axis=0))
    return poses @ chosen, chosen


def _weighted_moments(x: Array, w: Array) -> tuple[Array, Array]:
    """Weighted mean and unbiased (reliability-weight) covariance of ``x (K, D)``; ``w``
    sums to 1."""
    mean = w @ x
    centred = x - mean
    correction = 1.0 - jnp.sum(w * w)
    cov = jnp.einsum("k,ki,kj->ij", w, centred, centred) / jnp.where(
        correction > 0, correction, jnp.nan
    )
    return mean, cov


def _base_coordinates(poses: SE3, mean: SE3, center: Array) -> Array:
    """``(K, 6)``: position minus ``center`` and rotation vector ``log(R_k R_mean^-1)``."""
    rot = (poses.rotation() @ mean.rotation().inverse()).log()
    return jnp.concatenate([poses.translation() - center, rot], axis=-1)


@eqx.filter_jit
def _statistics(poses, weights, reference, symmetries, onehot, rounds):
    dtype = poses.wxyz_xyz.dtype
    valid = weights > 0
    w = jnp.where(valid, weights, 0.0)
    w = w / jnp.sum(w)
    # Dropped poses (padding, possibly NaN) become the identity: their weight is 0.
    poses = SE3(jnp.where(valid[:, None], poses.wxyz_xyz, SE3.identity().wxyz_xyz.astype(dtype)))
    if reference is None:
        anchor = SE3(poses.wxyz_xyz[jnp.argmax(valid)])
    else:
        anchor = reference
    # Canonicalise against the anchor, then against the mean of the canonical set, which no
    # longer depends on which branch the first pose happened to sit on.
    for _ in range(rounds):
        canonical, chosen = _canonicalise(poses, anchor, symmetries)
        anchor = karcher_mean(canonical, w)
    canonical, chosen = _canonicalise(poses, anchor, symmetries)
    mean = karcher_mean(canonical, w)

    positions = canonical.translation()
    center = w @ positions
    coords = _base_coordinates(canonical, mean, center)
    _, cov_base = _weighted_moments(coords, w)
    sigma = jnp.sqrt(jnp.diag(cov_base))
    deg = 180.0 / jnp.pi
    right = (SE3(mean.wxyz_xyz[None]).inverse() @ canonical).log()
    _, covariance = _weighted_moments(right, w)
    angles = geodesic_angle(mean.rotation(), canonical.rotation())
    correction = 1.0 - jnp.sum(w * w)
    spread = jnp.sqrt(jnp.sum(w * angles**2) / correction)

    if reference is None:
        t_bias = r_bias = None
    else:
        ref, _ = _canonicalise(SE3(reference.wxyz_xyz[None]), mean, symmetries)
        ref = SE3(ref.wxyz_xyz[0])
        t_bias = center - ref.translation()
        r_bias = (mean.rotation() @ ref.rotation().inverse()).log() * deg

    groups = None
    if onehot is not None:
        groups = _group_statistics(canonical, coords, w, onehot, valid)
    return PoseStatistics(
        mean=mean,
        count=jnp.sum(valid, dtype=jnp.int32),
        translation_sigma=sigma[:3],
        rotation_sigma_deg=sigma[3:] * deg,
        rotation_angles_deg=jnp.where(valid, angles * deg, jnp.nan).astype(dtype),
        rotation_spread_deg=spread * deg,
        covariance=covariance,
        translation_bias=t_bias,
        rotation_bias_deg=r_bias,
        canonical=canonical,
        symmetry=chosen,
        groups=groups,
    )


def _group_statistics(canonical, coords, w, onehot, valid) -> GroupStatistics:
    """Per-group means and spreads, and a one-way ANOVA per axis on ``coords (K, 6)``."""
    deg = 180.0 / jnp.pi
    k_valid = jnp.sum(valid)
    # Weights rescaled to sum to the number of poses: unit weights give the textbook ANOVA.
    wk = w * k_valid
    gw = onehot * wk  # (G, K)
    total = jnp.sum(gw, axis=1)  # (G,)
    present = total > 0
    safe_total = jnp.where(present, total, 1.0)
    means = (gw @ coords) / safe_total[:, None]  # (G, 6)
    centred = coords[None] - means[:, None]  # (G, K, 6)
    within_ss = jnp.einsum("gk,gkd->gd", gw, centred**2)  # (G, 6)
    counts = jnp.sum(onehot * valid, axis=1).astype(jnp.int32)
    # Reliability-weight Bessel correction per group (n / (n - 1) for unit weights).
    sq = jnp.sum(gw * gw, axis=1)
    dof = total - sq / safe_total
    group_sigma = jnp.sqrt(within_ss / jnp.where(dof > 0, dof, jnp.nan)[:, None])
    num_groups = jnp.sum(present)
    grand = (total @ means) / jnp.sum(total)
    between_ss = total @ (means - grand) ** 2  # (6,)
    within_dof = k_valid - num_groups
    pooled_var = jnp.sum(within_ss, axis=0) / jnp.where(within_dof > 0, within_dof, jnp.nan)
    between_dof = num_groups - 1
    f_stat = (between_ss / jnp.maximum(between_dof, 1)) / pooled_var
    d1, d2 = between_dof.astype(coords.dtype), within_dof.astype(coords.dtype)
    x = d2 / (d2 + d1 * f_stat)
    p_value = jnp.where(between_dof > 0, jax.scipy.special.betainc(d2 / 2, d1 / 2, x), 1.0)
    rms_offset = jnp.sqrt(
        jnp.sum(jnp.where(present[:, None], (means - grand) ** 2, 0.0), 0) / num_groups
    )
    ratio = rms_offset / jnp.sqrt(pooled_var)
    group_w = jnp.where(onehot * valid, 1.0, 0.0)
    return GroupStatistics(
        mean=karcher_mean(SE3(jnp.broadcast_to(canonical.wxyz_xyz, (*onehot.shape, 7))), group_w),
        count=counts,
        translation_sigma=group_sigma[:, :3],
        rotation_sigma_deg=group_sigma[:, 3:] * deg,
        translation_offset=means[:, :3] - grand[:3],
        rotation_offset_deg=(means[:, 3:] - grand[3:]) * deg,
        offset_ratio=ratio,
        p_value=p_value,
        bias_detected=jnp.any((p_value < 0.01) & (ratio > 1.0)),
    )


def pose_statistics(
    poses: SE3,
    *,
    reference: SE3 | None = None,
    symmetry: Symmetry | SE3 | None = None,
    symmetry_steps: int = 360,
    groups: Int[ArrayLike, " K"] | None = None,
    weights: Float[ArrayLike, " K"] | None = None,
    num_groups: int | None = None,
) -> PoseStatistics:
    """Statistics of ``K`` repeated estimates of one pose (a repeatability study).

    1. **Symmetry.** With ``symmetry`` (the object-frame transforms ``S`` that map the object
       onto itself, e.g. a square container's rotations by 0, 90, 180 and 270 degrees about
       its axis: a :class:`jaxreg.metrics.Symmetry`, the description the metrics and the
       synthetic scenes use, or an ``SE3`` batch for transforms about an axis off the object
       origin; the identity is always included), each pose ``T_k`` is replaced by the
       equivalent ``T_k @ S`` whose rotation is closest to an anchor: first ``reference``
       (or the first pose), then twice the Karcher mean of the canonical set. Without this,
       estimates that hop between equally good branches average to an invalid pose and
       their sigma is fiction.
    2. **Mean and spread.** ``mean`` is the Karcher mean on SE(3) (:func:`jaxreg.lie.karcher_mean`).
       Per-axis statistics are taken in the base frame: positions ``t_k`` (about their
       weighted mean) and rotation vectors ``log(R_k R_mean^-1)`` (the log map, never
       differenced Euler angles, which wrap and couple axes); sigmas use the unbiased
       ``1 / (1 - sum w^2)`` correction (``1 / (K - 1)`` for equal weights).
    3. **Bias.** Against ``reference`` (the true pose, or a fiducial's): mean position minus
       reference position, and the rotation vector from reference to mean, after moving the
       reference to its symmetric equivalent nearest the mean.
    4. **Groups.** With ``groups`` labels (e.g. the camera viewpoint of each estimate),
       :class:`GroupStatistics` reports each group's mean, within-group sigma and offset from
       the overall mean, and flags clusters that are tight but mutually offset.

    To study a point other than the object origin (the grasp point, say), pass
    ``poses @ SE3.from_translation(point)``.

    Args:
        poses: ``SE3`` batch ``(K,)`` mapping object into base coordinates.
        reference: optional ``SE3`` (unbatched) in the same sense.
        symmetry: optional :class:`jaxreg.metrics.Symmetry`, or an ``SE3`` batch ``(S,)`` of
            object-frame symmetry transforms.
        symmetry_steps: turns a continuous symmetry axis is discretised into (static;
            360 is 1-degree steps, so canonical rotations are within 0.5 degrees).
        groups: optional ``(K,)`` integer labels ``0 .. G-1``.
        weights: optional ``(K,)`` non-negative weights; 0 drops a pose (padding).
        num_groups: ``G``, static; inferred from concrete ``groups`` when omitted.

    Returns:
        :class:`PoseStatistics`.

    Raises:
        ValueError: not a ``(K,)`` batch, mismatched shapes, fewer than 2 weighted poses, or
            labels outside ``0 .. G-1``.
    """
    if not isinstance(poses, SE3) or len(poses.get_batch_axes()) != 1:
        raise ValueError("poses must be a jaxlie.SE3 batch of shape (K,)")
    (k,) = poses.get_batch_axes()
    dtype = poses.wxyz_xyz.dtype
    w = jnp.ones(k, dtype) if weights is None else jnp.asarray(weights, dtype)
    if w.shape != (k,):
        raise ValueError(f"weights must have shape ({k},), got {w.shape}")
    if not isinstance(w, jax.core.Tracer) and int(np.sum(np.asarray(w) > 0)) < 2:
        raise ValueError("pose_statistics needs at least 2 poses with positive weight")
    if reference is not None:
        if not isinstance(reference, SE3) or reference.get_batch_axes() != ():
            raise ValueError("reference must be one (unbatched) jaxlie.SE3")
        reference = SE3(reference.wxyz_xyz.astype(dtype))
    identity = SE3.identity().wxyz_xyz.astype(dtype)[None]
    if isinstance(symmetry, Symmetry):
        symmetry = symmetry.transforms(steps=symmetry_steps)
    if symmetry is None:
        sym = SE3(identity)
    else:
        if not isinstance(symmetry, SE3) or len(symmetry.get_batch_axes()) != 1:
            raise ValueError(
                "symmetry must be a jaxreg.metrics.Symmetry or a jaxlie.SE3 batch of shape (S,)"
            )
        sym = SE3(jnp.concatenate([identity, symmetry.wxyz_xyz.astype(dtype)]))
    onehot = None
    if groups is not None:
        labels = jnp.asarray(groups)
        if labels.shape != (k,) or not jnp.issubdtype(labels.dtype, jnp.integer):
            raise ValueError(
                f"groups must be ({k},) integer labels, got {labels.dtype}{labels.shape}"
            )
        if num_groups is None:
            if isinstance(labels, jax.core.Tracer):
                raise ValueError("pass num_groups when groups is traced")
            num_groups = int(np.max(np.asarray(labels))) + 1
        if not isinstance(labels, jax.core.Tracer):
            lab = np.asarray(labels)
            if lab.min() < 0 or lab.max() >= num_groups:
                raise ValueError(f"group labels must lie in 0 .. {num_groups - 1}")
        onehot = (labels[None, :] == jnp.arange(num_groups)[:, None]).astype(dtype)
    return _statistics(poses, w, reference, sym, onehot, 2)


# --------------------------------------------------------------------------------------------
# From pose error to grasp success.


@jax.jit
def grasp_success_probability(
    sigma: Float[ArrayLike, "..."],
    bias: Float[ArrayLike, "..."],
    margin: Float[ArrayLike, "..."],
) -> Float[Array, "..."]:
    """``P(|e| < margin)`` for a lateral pose error ``e ~ N(bias, sigma^2)``.

    A parallel-jaw grasp closes around the object when the error across the jaws stays
    inside the mechanical margin (:func:`grasp_margin`):

        ``P = (erf((margin - bias) / s) + erf((margin + bias) / s)) / 2``,  ``s = sqrt(2) sigma``

    ``sigma = 0`` gives the limit: 1 when ``|bias| < margin``, 0 outside, 1/2 on the edge; a
    negative margin gives 0. Arguments broadcast (same units, e.g. metres); gradients are
    finite everywhere. For independent errors along several axes, multiply the per-axis
    probabilities. A bias shifts the error distribution and eats the margin on one side;
    unlike noise it does not average away over repeated grasps.
    """
    sigma, bias, margin = jnp.broadcast_arrays(
        *(jnp.asarray(x, jnp.result_type(float)) for x in (sigma, bias, margin))
    )
    sigma = jnp.abs(sigma)
    zero = sigma == 0
    scale = jnp.sqrt(2.0) * jnp.where(zero, 1.0, sigma)
    spread = 0.5 * (
        jax.scipy.special.erf((margin - bias) / scale)
        + jax.scipy.special.erf((margin + bias) / scale)
    )
    exact = 0.5 * (jnp.sign(margin - bias) + jnp.sign(margin + bias))
    return jnp.where(margin > 0, jnp.clip(jnp.where(zero, exact, spread), 0.0, 1.0), 0.0)


def grasp_margin(
    opening: Float[ArrayLike, "..."],
    width: Float[ArrayLike, "..."],
    friction_allowance: Float[ArrayLike, "..."] = 0.0,
) -> Float[Array, "..."]:
    """Lateral clearance per side: ``(opening - width) / 2 - friction_allowance``.

    A 40 mm opening around a 25 mm box leaves 7.5 mm per side; the friction allowance is the
    part of it a closing jaw needs to drag the object without losing the grasp. Units as
    given (all the same); broadcasts.
    """
    opening, width, friction_allowance = (
        jnp.asarray(x, jnp.result_type(float)) for x in (opening, width, friction_allowance)
    )
    return (opening - width) / 2 - friction_allowance


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
