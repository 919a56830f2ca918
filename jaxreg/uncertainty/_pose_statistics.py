"""Repeatability statistics of a set of pose estimates: `pose_statistics`.

Public through :mod:`jaxreg.uncertainty.noise` (and ``jaxreg``), beside the noise models and the
grasp-success arithmetic its results feed. It holds the Karcher mean and per-axis spread of
``K`` poses, their bias against a reference, symmetry canonicalisation and the per-group
(per-viewpoint) ANOVA that reveals a hand-eye bias.

Conventions: poses are ``SE3`` batches ``(K,)`` mapping object into base (target)
coordinates. Per-axis sigmas, biases and group offsets are in the base frame's axes:
positions in metres and rotation vectors ``log(R_k R_mean^-1)`` (a left perturbation) in
degrees. ``PoseStatistics.covariance`` follows jaxreg's convention instead (right
perturbation, object frame, jaxlie order ``(v, w)``, metres and radians) so it can be set
beside :func:`jaxreg.icp_covariance`. Weights are normalised to sum to 1; a pose with weight 0
is padding and may hold NaN.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.geometry.lie import geodesic_angle
from jaxreg.geometry.means import karcher_mean
from jaxreg.geometry.metrics import Symmetry

__all__ = ["GroupStatistics", "PoseStatistics", "pose_statistics"]


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
       its axis: a :class:`jaxreg.Symmetry`, the description the metrics and the
       synthetic scenes use, or an ``SE3`` batch for transforms about an axis off the object
       origin; the identity is always included), each pose ``T_k`` is replaced by the
       equivalent ``T_k @ S`` whose rotation is closest to an anchor: first ``reference``
       (or the first pose), then twice the Karcher mean of the canonical set. Without this,
       estimates that hop between equally good branches average to an invalid pose and
       their sigma is fiction.
    2. **Mean and spread.** ``mean`` is the Karcher mean on SE(3)
       (:func:`jaxreg.geometry.karcher_mean`). Per-axis statistics are taken in the base frame:
       positions ``t_k`` (about their weighted mean) and rotation vectors ``log(R_k R_mean^-1)``
       (the log map, never differenced Euler angles, which wrap and couple axes); sigmas use the
       unbiased ``1 / (1 - sum w^2)`` correction (``1 / (K - 1)`` for equal weights).
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
        symmetry: optional :class:`jaxreg.Symmetry`, or an ``SE3`` batch ``(S,)`` of
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
                "symmetry must be a jaxreg.Symmetry or a jaxlie.SE3 batch of shape (S,)"
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
