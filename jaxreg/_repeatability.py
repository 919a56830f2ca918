"""Repeatability studies on synthetic scenes, and the hand-eye correction that makes camera
viewpoints agree, found by differentiating through lifting and registration.

:func:`repeatability` runs the three tiers of a pose repeatability study on scenes of
:func:`jaxreg.synth.tabletop_scene` (small images, no clutter by default):

1. **frozen**: one scene re-measured ``frozen`` times (new sensor-noise draws): the spread is
   the sensor's noise through the registration;
2. **re-placement**: the object re-placed ``replacements`` times around its nominal pose
   (uniform jitter of ``placement`` metres in x, y and ``placement_deg`` of yaw), same camera:
   the pose-dependent error joins in;
3. **viewpoint**: the object left in place and seen from ``len(viewpoints)`` camera poses
   (an arm moving an eye-in-hand camera), each re-measured ``draws_per_view`` times.

Every frame reports a hand-eye transform that is off from the true one by a planted right
perturbation, ``reported = true @ exp(hand_eye_bias)``: constant in the camera frame, as an
eye-in-hand calibration error is. It moves each estimate by a few millimetres, the same way
every time from one viewpoint, so tiers 1 and 2 cannot see it; tier 3 does (per-viewpoint
clusters, each tight, mutually offset: the groups test of
:func:`jaxreg.uncertainty.pose_statistics`). :func:`estimate_hand_eye_correction` then finds
the correction ``exp(delta)`` to the reported ``base_T_camera`` that makes the viewpoints
agree, by Gauss-Newton on the spread of the object across frames, with the Jacobian taken by
``jax.jacfwd`` through lifting (:meth:`jaxreg.RGBDFrame.points`) and ICP (implicit
differentiation at the converged fixed point).

Registration (``jaxreg.estimate_pose`` is not used: the study isolates the sensor, placement
and calibration errors from segmentation and global initialisation, the pipeline's own failure
modes): the scene's exact target mask less its one-pixel silhouette ring (where the sensor
mixes depths; dropping it halves the view-dependent registration bias); ``num_points`` of its
valid pixels drawn at random, a fixed set per frame (subsampling in pixel space keeps the lift
differentiable, where :func:`jaxreg.voxel_downsample` is a host step); lifted through the
intrinsics and the reported ``base_T_camera``; registered scene -> model (every scene point
has its match on the model, whatever part is visible) by point-to-plane ICP against the
model's surface samples and exact face normals, from the truth perturbed by ``init_sigma``.

Observability: a hand-eye correction is fixed only up to what the camera motions constrain.
With views ``B_k`` the estimate from view ``k`` moves as ``B_k X B_k^-1`` for a correction
error ``X``, so an ``X`` that commutes with every relative motion ``B_j B_k^-1`` changes no
disagreement: camera poses on one orbit (rotations about a single axis) leave the screw about
that axis (rotation about it and translation along it: 2 directions) unobservable; relative
rotations about two non-parallel axes fix all 6. Fixed is not well fixed: a camera moved by
azimuth about the object turns about the vertical through it, so a hand-eye turn about that
line shows only through changes of elevation and distance, and it is the weakest direction
(its standard error is the largest in ``covariance``). The result reports the singular values
of the disagreement's Jacobian, the projector onto the observable directions and the
correction's standard-error covariance; Gauss-Newton steps are taken in the observable
subspace only (the rest stays at zero).

Conventions: poses ``a_T_b``; tangents jaxlie's ``(vx, vy, vz, wx, wy, wz)`` (metres,
radians); the hand-eye bias and correction are right perturbations of ``base_T_camera``
(camera frame). Distances in metres, angles in degrees where the name says so.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import trimesh
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg._result import AbstractResult
from jaxreg.camera import Intrinsics, RGBDFrame
from jaxreg.icp import ICPStatus, icp
from jaxreg.lie import se3_exp, se3_from_matrix
from jaxreg.metrics import Symmetry
from jaxreg.neighbors import NeighborGrid, build_grid
from jaxreg.uncertainty import (
    ErrorBudget,
    PoseStatistics,
    error_budget,
    grasp_margin,
    grasp_success_probability,
    pose_statistics,
)

__all__ = [
    "HandEyeCorrection",
    "HandEyeStatus",
    "Repeatability",
    "estimate_hand_eye_correction",
    "repeatability",
    "stack_frames",
]

TIERS = ("frozen", "re-placement", "viewpoint")


# --------------------------------------------------------------------------------------------
# Lifting and registration of a batch of frames, differentiable in a hand-eye correction.


def stack_frames(frames: Sequence[RGBDFrame]) -> RGBDFrame:
    """One :class:`~jaxreg.camera.RGBDFrame` batch ``(K,)`` of frames of one camera (same
    intrinsics and image size): ``depth (K, H, W)``, ``base_T_camera`` batch ``(K,)``; colour
    is dropped."""
    if len(frames) == 0:
        raise ValueError("stack_frames needs at least one frame")
    shapes = {f.depth.shape for f in frames}
    if len(shapes) != 1:
        raise ValueError(f"frames must share one image size, got {sorted(shapes)}")
    first, structure = jax.tree.flatten(frames[0].intrinsics)
    for f in frames[1:]:
        leaves, other = jax.tree.flatten(f.intrinsics)
        same = other == structure and all(map(np.array_equal, first, leaves))
        if not same:
            raise ValueError("frames must share one camera's intrinsics")
    frames = [eqx.tree_at(lambda f: f.rgb, f, None, is_leaf=lambda x: x is None) for f in frames]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *frames)


def _pick_pixels(
    depth: np.ndarray, masks: np.ndarray, num_points: int, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """``(K, N)`` flat indices of ``num_points`` random valid masked pixels per frame and their
    ``(K, N)`` weights (0 pads a frame with fewer valid pixels)."""
    pixels = np.zeros((len(depth), num_points), np.int32)
    weights = np.zeros((len(depth), num_points), np.float32)
    for k, (d, m) in enumerate(zip(depth, masks, strict=True)):
        valid = np.flatnonzero(m & np.isfinite(d))
        if len(valid) < 3:
            raise ValueError(f"frame {k}: fewer than 3 masked pixels with depth")
        take = rng.choice(valid, min(num_points, len(valid)), replace=False)
        pixels[k, : len(take)] = take
        pixels[k, len(take) :] = take[0]
        weights[k, : len(take)] = 1.0
    return pixels, weights


class _Views(eqx.Module):
    """The data of a batch of ``K`` frames to register: depth, intrinsics, reported
    ``base_T_camera``, chosen pixels and weights, the model and its neighbour grid."""

    depth: Float[Array, "K H W"]
    intrinsics: Intrinsics
    base_T_camera: SE3
    pixels: Int[Array, "K N"]
    weights: Float[Array, "K N"]
    model: Float[Array, "M 3"]
    normals: Float[Array, "M 3"]
    grid: NeighborGrid
    distance: Float[Array, ""]


def _views(frames, masks, model_points, model_normals, num_points, distance, seed) -> _Views:
    depth = np.asarray(frames.depth)
    masks = np.asarray(masks, bool)
    if depth.ndim != 3 or masks.shape != depth.shape:
        raise ValueError(
            f"frames must be a batch (K,) (see stack_frames) with masks (K, H, W); got depth "
            f"{depth.shape}, masks {masks.shape}"
        )
    model = jnp.asarray(model_points, jnp.float32)
    normals = jnp.asarray(model_normals, jnp.float32)
    if model.ndim != 2 or model.shape[1] != 3 or normals.shape != model.shape:
        raise ValueError(
            f"model_points and model_normals must both be (M, 3), got {model.shape}, "
            f"{normals.shape}"
        )
    pixels, weights = _pick_pixels(depth, masks, num_points, np.random.default_rng(seed))
    return _Views(
        jnp.asarray(depth),
        jax.tree.map(lambda x: x[0] if jnp.ndim(x) else x, frames.intrinsics),  # one camera
        frames.base_T_camera,
        jnp.asarray(pixels),
        jnp.asarray(weights),
        model,
        normals,
        build_grid(model, distance),
        jnp.asarray(distance, jnp.float32),
    )


def _register(correction: Float[Array, " 6"], views: _Views, inits: SE3, iterations: int):
    """``base_T_object`` batch ``(K,)`` of every frame lifted with ``base_T_camera @
    exp(correction)``, and the ICP statuses."""
    fix = se3_exp(correction)

    def one(depth, camera, pixels, weights, init):
        frame = RGBDFrame(depth, views.intrinsics, base_T_camera=camera @ fix)
        points = frame.points().reshape(-1, 3)[pixels]
        result = icp(
            points, views.model, init.inverse(), method="point_to_plane",
            target_normals=views.normals, max_correspondence_distance=views.distance,
            max_iterations=iterations, tolerance=1e-6, source_weights=weights,
            neighbors=views.grid,
        )  # fmt: skip
        return result.pose.inverse(), result.status

    return jax.vmap(one)(views.depth, views.base_T_camera, views.pixels, views.weights, inits)


def _points_of(poses: SE3, anchors: Array) -> Array:
    """``(K, P, 3)``: the ``(P, 3)`` object-frame anchors placed by each of ``K`` poses."""
    rot = poses.rotation().as_matrix()
    return jnp.einsum("kij,pj->kpi", rot, anchors) + poses.translation()[:, None]


def _corners(model_points) -> Float[Array, "8 3"]:
    """The 8 corners of the model's bounding box (object frame)."""
    lo, hi = np.min(model_points, axis=0), np.max(model_points, axis=0)
    corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1)
    return jnp.asarray(corners.reshape(-1, 3), jnp.float32)


def _disagreement(correction, views, inits, anchors, iterations):
    """Residuals ``(K * P * 3,)``: each frame's placement of the anchors minus the mean over
    frames, with the aux ``(poses, status)``."""
    poses, status = _register(correction, views, inits, iterations)
    placed = _points_of(poses, anchors)
    residual = (placed - jnp.mean(placed, axis=0)).reshape(-1)
    return residual, (residual, poses, status)


@eqx.filter_jit
def _linearise(correction, views, inits, anchors, iterations):
    """Jacobian ``(K * P * 3, 6)``, residuals, poses and statuses at ``correction``."""
    jac, aux = jax.jacfwd(_disagreement, has_aux=True)(
        correction, views, inits, anchors, iterations
    )
    return jac, *aux


# --------------------------------------------------------------------------------------------
# The hand-eye correction.


class HandEyeStatus(eqx.Enumeration):
    """How :func:`estimate_hand_eye_correction` ended; each member's value is the message."""

    success = "the views agree: the correction converged"
    partially_observable = (
        "converged, but the views fix only some directions of the correction (see "
        "`observable`); the others are left at zero: move the camera about two non-parallel axes"
    )
    max_steps = "the Gauss-Newton steps ran out before the correction settled: raise max_steps"
    registration_failed = (
        "a frame's registration failed for want of pairs or a finite update (see "
        "`registration_status`): check its mask and start"
    )


class HandEyeCorrection(AbstractResult):
    """Result of :func:`estimate_hand_eye_correction` (``K`` frames).

    Attributes:
        pose: ``SE3`` correction ``C``: the corrected hand-eye is ``base_T_camera @ C``.
        tangent: ``(6,)`` ``log C`` (right perturbation, camera frame, ``(v, w)``).
        status: :class:`HandEyeStatus`.
        converged: the last step fell below ``tolerance`` (metres, radians).
        iterations: Gauss-Newton steps taken.
        covariance: ``(6, 6)`` standard-error covariance of ``tangent`` from the residual
            disagreement left after correction (frame-to-frame noise), restricted to the
            observable directions (0 across the others).
        singular_values: ``(6,)`` of the Jacobian of the disagreement residuals at the start,
            descending, with the rotation columns multiplied by the mean camera-object
            distance (so both kinds are metres of displacement per metre).
        observable: ``(6, 6)`` projector onto the directions of the tangent the views fix
            (singular value above ``rank_tolerance`` times the largest); it acts on tangents
            ``(v, w)`` and is orthogonal in the scaled coordinates ``(v, distance * w)``.
        rank: ``()`` number of observable directions.
        poses_before, poses_after: ``SE3`` batch ``(K,)`` ``base_T_object`` of every frame
            with the reported and with the corrected hand-eye.
        disagreement_before, disagreement_after: ``()`` RMS distance (metres) of the model's
            bounding-box corners, as each frame places them, from their mean over frames.
        before, after: :func:`jaxreg.uncertainty.pose_statistics` of those poses with the
            ``groups`` labels (``None`` without labels): the per-viewpoint bias test.
        registration_status: :class:`jaxreg.ICPStatus` batch ``(K,)`` at the correction.
    """

    pose: SE3
    tangent: Float[Array, " 6"]
    status: HandEyeStatus
    converged: Bool[Array, ""]
    iterations: Int[Array, ""]
    covariance: Float[Array, "6 6"]
    singular_values: Float[Array, " 6"]
    observable: Float[Array, "6 6"]
    rank: Int[Array, ""]
    poses_before: SE3
    poses_after: SE3
    disagreement_before: Float[Array, ""]
    disagreement_after: Float[Array, ""]
    before: PoseStatistics | None
    after: PoseStatistics | None
    registration_status: ICPStatus


def estimate_hand_eye_correction(
    frames: RGBDFrame | Sequence[RGBDFrame],
    masks: Bool[ArrayLike, "K H W"],
    model_points: Float[ArrayLike, "M 3"],
    model_normals: Float[ArrayLike, "M 3"],
    inits: SE3,
    *,
    groups: Int[ArrayLike, " K"] | None = None,
    symmetry: Symmetry | None = None,
    num_points: int = 768,
    max_correspondence_distance: float = 0.015,
    max_iterations: int = 40,
    max_steps: int = 8,
    tolerance: float = 1e-5,
    rank_tolerance: float = 1e-3,
    seed: int = 0,
) -> HandEyeCorrection:
    """The correction ``C`` to a hand-eye transform that makes frames from several camera
    poses agree on where a static object is.

    Each frame's masked pixels are lifted with ``base_T_camera @ exp(delta)`` and registered
    to the model (see the module docstring); the residuals are the model's bounding-box
    corners as each frame places them, minus their mean over frames. Gauss-Newton on
    ``delta``, its Jacobian by ``jax.jacfwd`` through the lift and ICP (implicit
    differentiation), steps by the pseudo-inverse truncated to the observable directions,
    each step's registrations warm-started from the last.

    Args:
        frames: ``K`` frames of one camera (a list, or a batch from :func:`stack_frames`)
            with the hand-eye as reported: every ``base_T_camera`` shares one calibration
            error, a right perturbation (eye-in-hand: an error in ``flange_T_camera``).
        masks: ``(K, H, W)`` the object's pixels in each frame.
        model_points: ``(M, 3)`` surface samples of the object, its own frame (metres).
        model_normals: ``(M, 3)`` their unit normals.
        inits: ``SE3`` batch ``(K,)`` starting ``base_T_object`` per frame (within ICP's
            basin of the frame's own, biased, pose).
        groups: optional ``(K,)`` viewpoint labels for the before/after bias test.
        symmetry: the object's symmetry, for those statistics.
        num_points: pixels per frame registered (static).
        max_correspondence_distance, max_iterations: ICP's (point-to-plane).
        max_steps: Gauss-Newton steps at most.
        tolerance: a step below this (metres and radians) ends the iteration.
        rank_tolerance: relative singular value below which a direction is unobservable.
        seed: the draw of each frame's pixels.

    Returns:
        :class:`HandEyeCorrection`.

    Raises:
        ValueError: mismatched shapes, or a frame with fewer than 3 usable pixels.
    """
    if isinstance(frames, (list, tuple)):
        frames = stack_frames(frames)
    views = _views(
        frames, masks, model_points, model_normals, num_points, max_correspondence_distance, seed
    )
    if not isinstance(inits, SE3) or inits.get_batch_axes() != views.depth.shape[:1]:
        raise ValueError(f"inits must be an SE3 batch ({views.depth.shape[0]},)")
    anchors = _corners(model_points)
    # Rotations scaled by the camera-object distance: every column in metres of displacement.
    reach = float(np.mean(np.linalg.norm(
        np.asarray((frames.base_T_camera.inverse() @ inits).translation()), axis=-1
    )))  # fmt: skip
    scale = np.r_[np.ones(3), np.full(3, 1.0 / reach)]

    def linearise(delta, starts):
        jac, residual, poses, status = _linearise(
            jnp.asarray(delta, jnp.float32), views, starts, anchors, max_iterations
        )
        return np.asarray(jac, float) * scale, np.asarray(residual, float), poses, status

    delta = np.zeros(6)
    jac, residual, poses, status = linearise(delta, inits)
    poses_before, residual_before = poses, residual
    _, sigma, vt = np.linalg.svd(jac, full_matrices=False)
    basis = vt[sigma > rank_tolerance * sigma[0]]  # (r, 6) observable, scaled coordinates
    converged, steps = False, 0
    while steps < max_steps and not converged:
        coef, *_ = np.linalg.lstsq(jac @ basis.T, -residual, rcond=None)
        step = basis.T @ coef
        for _ in range(4):  # halve a step that makes the views disagree more
            trial = linearise(delta + step * scale, poses)
            if np.sum(trial[1] ** 2) <= np.sum(residual**2):
                break
            step = step / 2
        else:  # no step along the model reduces the disagreement: the noise floor
            converged = True
            break
        delta = delta + step * scale
        jac, residual, poses, status = trial
        steps += 1
        converged = max(np.abs(step[:3]).max(), np.abs(step[3:]).max() / reach) < tolerance
    rank = len(basis)
    # Standard error of the correction from the residual left over (frame-to-frame noise).
    reduced = jac @ basis.T
    # Each frame's residuals come from its 6-DOF pose error; the mean over frames takes 6.
    dof = 6 * (len(residual) // anchors.size - 1) - rank
    noise = np.sum(residual**2) / max(dof, 1)
    covariance = basis.T @ np.linalg.pinv(reduced.T @ reduced) @ basis * noise
    covariance = covariance * scale[:, None] * scale[None, :]

    # A registration stopped by the iteration bound still moved to within its last step.
    usable = [ICPStatus.success._value, ICPStatus.max_iterations._value]
    failed = ~np.isin(np.asarray(status._value), usable)
    if failed.any():
        code = HandEyeStatus.registration_failed
    elif not converged:
        code = HandEyeStatus.max_steps
    elif rank < 6:
        code = HandEyeStatus.partially_observable
    else:
        code = HandEyeStatus.success

    def stats(poses):
        if groups is None:
            return None
        labels = np.asarray(groups)
        return pose_statistics(
            poses, groups=labels, symmetry=symmetry, num_groups=int(labels.max()) + 1
        )

    rms = lambda r: jnp.asarray(np.sqrt(np.mean(np.sum(r.reshape(-1, 3) ** 2, -1))))  # noqa: E731
    return HandEyeCorrection(
        pose=se3_exp(jnp.asarray(delta, jnp.float32)),
        tangent=jnp.asarray(delta, jnp.float32),
        status=code,
        converged=jnp.asarray(converged),
        iterations=jnp.asarray(steps, jnp.int32),
        covariance=jnp.asarray(covariance, jnp.float32),
        singular_values=jnp.asarray(sigma, jnp.float32),
        observable=jnp.asarray(np.diag(scale) @ basis.T @ basis @ np.diag(1 / scale), jnp.float32),
        rank=jnp.asarray(rank, jnp.int32),
        poses_before=poses_before,
        poses_after=poses,
        disagreement_before=rms(residual_before),
        disagreement_after=rms(residual),
        before=stats(poses_before),
        after=stats(poses),
        registration_status=status,
    )


# --------------------------------------------------------------------------------------------
# The three-tier study.


class Repeatability(eqx.Module):
    """Result of :func:`repeatability`: ``K`` frames over the three tiers (``TIERS``: frozen,
    re-placement, viewpoint), ``K3`` of them in the viewpoint tier.

    Statistics take each estimate referred to the nominal pose, ``est @ truth^-1 @ nominal``
    (its base-frame error carried to the nominal pose), so the re-placement tier's spread is
    the registration's error, not the placement jitter itself.

    Attributes:
        frozen, replacement: :class:`jaxreg.uncertainty.PoseStatistics` of tiers 1 and 2.
        viewpoint: the same for tier 3 with ``groups`` = viewpoint (``viewpoint.groups``: the
            per-viewpoint bias test).
        translation_bias: ``(3, 3)`` per tier, its mean position minus the nominal (base
            frame, metres): what the hand-eye error does to every estimate, which only the
            synthetic truth shows.
        rotation_bias_deg: ``(3, 3)`` per tier, ``log(R_mean R_nominal^-1)`` (degrees).
        nominal: ``SE3`` the object's nominal ``base_T_object``.
        poses: ``SE3`` batch ``(K,)`` estimated ``base_T_object`` (reported hand-eye).
        truth: ``SE3`` batch ``(K,)`` true ``base_T_object`` of each frame.
        tier: ``(K,)`` 0, 1, 2 for frozen, re-placement, viewpoint.
        view: ``(K,)`` viewpoint label (0 in tiers 1 and 2).
        status: :class:`jaxreg.ICPStatus` batch ``(K,)``.
        lateral_error: ``(K,)`` position error along ``closing_axis`` (metres).
        lateral_sigma, lateral_bias: ``(3,)`` per tier, standard deviation and mean of it.
        margin: ``()`` the gripper's clearance per side (metres).
        grasp_success: ``(3,)`` per tier :func:`grasp_success_probability` of its lateral
            sigma and bias (the bias known only because the scene is synthetic).
        budget: :class:`jaxreg.uncertainty.ErrorBudget` along the closing axis (metres):
            tier 1's sigma, and what tiers 2 and 3 add to it in quadrature
            (``sqrt(max(sigma_t^2 - sigma_1^2, 0))``).
        budget_grasp_success: ``()`` grasp success of the budget's total as a zero-mean
            sigma: what the RSS budget predicts without knowing the bias.
        hand_eye_bias: ``(6,)`` the planted error (right perturbation of ``base_T_camera``).
        frames: :class:`~jaxreg.camera.RGBDFrame` batch ``(K3,)`` of the viewpoint tier (as
            reported), with ``masks (K3, H, W)``, for :meth:`correct_hand_eye`.
        true_base_T_camera: ``SE3`` batch ``(K3,)`` the viewpoint tier's true hand-eye.
        model_points, model_normals: ``(M, 3)`` the model's surface samples and normals.
        symmetry: the object's :class:`jaxreg.metrics.Symmetry`.
    """

    frozen: PoseStatistics
    replacement: PoseStatistics
    viewpoint: PoseStatistics
    translation_bias: Float[Array, "3 3"]
    rotation_bias_deg: Float[Array, "3 3"]
    nominal: SE3
    poses: SE3
    truth: SE3
    tier: Int[Array, " K"]
    view: Int[Array, " K"]
    status: ICPStatus
    lateral_error: Float[Array, " K"]
    lateral_sigma: Float[Array, " 3"]
    lateral_bias: Float[Array, " 3"]
    margin: Float[Array, ""]
    grasp_success: Float[Array, " 3"]
    budget: ErrorBudget
    budget_grasp_success: Float[Array, ""]
    hand_eye_bias: Float[Array, " 6"]
    frames: RGBDFrame
    masks: Bool[Array, "K3 H W"]
    true_base_T_camera: SE3
    model_points: Float[Array, "M 3"]
    model_normals: Float[Array, "M 3"]
    symmetry: Symmetry

    def correct_hand_eye(self, **options) -> HandEyeCorrection:
        """:func:`estimate_hand_eye_correction` on the viewpoint tier's frames, started from
        their estimates, with the viewpoints as groups; ``options`` are its keywords."""
        third = np.asarray(self.tier) == 2
        return estimate_hand_eye_correction(
            self.frames, self.masks, self.model_points, self.model_normals,
            SE3(self.poses.wxyz_xyz[third]), groups=np.asarray(self.view)[third],
            symmetry=self.symmetry, **options,
        )  # fmt: skip


def _erode(mask: np.ndarray) -> np.ndarray:
    """``mask`` less its silhouette ring: pixels with all 8 neighbours inside (the ring is
    where a stereo sensor mixes the object's depth with the background's)."""
    padded = np.pad(mask, 1)
    h, w = mask.shape
    keep = mask.copy()
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            keep &= padded[dy : dy + h, dx : dx + w]
    return keep


def _object_view(base_T_object: np.ndarray, distance: float, azimuth_deg, elevation_deg):
    """``(4, 4)`` camera ``distance`` metres from the object's origin, at ``azimuth_deg`` about
    the vertical from the object's x axis and ``elevation_deg`` above the table, looking at
    the origin."""
    from jaxreg.synth import look_at

    centre = base_T_object[:3, 3]
    azimuth = np.arctan2(base_T_object[1, 0], base_T_object[0, 0]) + np.radians(azimuth_deg)
    elevation = np.radians(elevation_deg)
    direction = np.array(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ]
    )
    return look_at(centre + distance * direction, centre)


def repeatability(
    seed: int = 0,
    *,
    object: str = "box",
    frozen: int = 8,
    replacements: int = 6,
    viewpoints: Sequence[tuple[float, float, float]] = (
        (45.0, 35.0, 0.45),
        (135.0, 50.0, 0.6),
        (225.0, 65.0, 0.75),
    ),
    draws_per_view: int = 4,
    hand_eye_bias: Float[ArrayLike, " 6"] = (0.003, -0.002, 0.003, 0.004, -0.006, 0.004),
    placement: float = 0.005,
    placement_deg: float = 5.0,
    image_size: tuple[int, int] = (640, 360),
    distractors: int = 0,
    num_points: int = 768,
    init_sigma: tuple[float, float] = (0.005, 2.0),
    max_correspondence_distance: float = 0.015,
    max_iterations: int = 40,
    gripper_opening: float = 0.040,
    object_width: float = 0.025,
    closing_axis: Float[ArrayLike, " 3"] = (1.0, 0.0, 0.0),
) -> Repeatability:
    """The three-tier repeatability study of the module docstring on synthetic scenes.

    Args:
        seed: the scene (:func:`jaxreg.synth.tabletop_scene`): object pose, nominal camera,
            and every draw of the study (noise, placements, starts, pixels).
        object: the target, one of :data:`jaxreg.synth.OBJECTS`.
        frozen: tier 1 re-measurements.
        replacements: tier 2 re-placements (one measurement each).
        viewpoints: cameras as ``(azimuth_deg, elevation_deg, distance)``: azimuth about the
            vertical from the object's x axis, elevation above the table, distance (metres)
            from the object's origin, looking at it. The first is the camera of tiers 1 and
            2; all are tier 3's. Vary azimuth and elevation (relative rotations about two
            non-parallel axes) to make every direction of the hand-eye observable. A turn of
            the hand-eye about the vertical through the object commutes with every change of
            azimuth: only elevation and distance changes reveal it, so vary those widely. A view
            nearly square to a face of a box sees two faces, which leave a slide along their
            common edge to the silhouette's noisy pixels: millimetres of view-dependent
            registration bias, which a hand-eye correction would absorb. The defaults look
            along the box's diagonals.
        draws_per_view: tier 3 re-measurements per viewpoint.
        hand_eye_bias: ``(6,)`` planted hand-eye error, tangent ``(v, w)`` (metres,
            radians): every frame reports ``base_T_camera = true @ exp(hand_eye_bias)``.
        placement, placement_deg: tier 2's uniform jitter half-widths (x, y in metres; yaw).
        image_size: ``(width, height)`` of the D435's depth image (pixels).
        distractors: clutter objects (placed off every camera's line of sight).
        num_points: pixels registered per frame.
        init_sigma: ``(metres, degrees)`` per-axis sigma of the start's perturbation of the
            truth.
        max_correspondence_distance, max_iterations: ICP's (point-to-plane).
        gripper_opening, object_width: the grasp (metres): margin ``(opening - width) / 2``.
        closing_axis: ``(3,)`` base-frame direction along which the jaws close.

    Returns:
        :class:`Repeatability`.

    Raises:
        ValueError: fewer than 2 frames in a tier or fewer than 2 viewpoints, a bad object,
            or a frame whose mask has no depth.
    """
    from jaxreg.synth import StereoSensor, tabletop_scene

    if min(frozen, replacements, draws_per_view) < 2 or len(viewpoints) < 2:
        raise ValueError(
            "each tier needs at least 2 frames (draws_per_view >= 2) and the viewpoint tier at "
            "least 2 viewpoints"
        )
    bias = jnp.asarray(hand_eye_bias, jnp.float32)
    if bias.shape != (6,):
        raise ValueError(f"hand_eye_bias must be a (6,) tangent (v, w), got {bias.shape}")
    axis = np.asarray(closing_axis, float)
    if axis.shape != (3,) or not np.linalg.norm(axis) > 0:
        raise ValueError(f"closing_axis must be a nonzero (3,) vector, got {closing_axis}")
    axis /= np.linalg.norm(axis)
    rng = np.random.default_rng([seed, 2])
    intrinsics = StereoSensor.d435().intrinsics(*image_size)
    scene_options = dict(object=object, distractors=distractors, intrinsics=intrinsics)
    base = tabletop_scene(seed, noise=False, **scene_options)
    nominal = np.asarray(base.truth.as_matrix(), float)
    cameras_of_views = [_object_view(nominal, d, az, el) for az, el, d in viewpoints]
    camera = cameras_of_views[0]

    # (tier, view, base_T_object, base_T_camera) of every frame.
    plan = [(0, 0, nominal, camera)] * frozen
    for _ in range(replacements):
        moved = nominal.copy()
        yaw = np.radians(rng.uniform(-placement_deg, placement_deg))
        c, s = np.cos(yaw), np.sin(yaw)
        moved[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ nominal[:3, :3]
        moved[:2, 3] += rng.uniform(-placement, placement, 2)
        plan.append((1, 0, moved, camera))
    for v, view_camera in enumerate(cameras_of_views):
        plan += [(2, v, nominal, view_camera)] * draws_per_view

    fix = se3_exp(bias)
    frames, masks, truths, cameras = [], [], [], []
    for k, (_, _, pose, cam) in enumerate(plan):
        scene = tabletop_scene(
            seed, base_T_object=pose, base_T_camera=cam, noise_seed=(seed + 1) * 100_003 + k,
            **scene_options,
        )  # fmt: skip
        true_camera = scene.frame.base_T_camera
        frames.append(eqx.tree_at(lambda f: f.base_T_camera, scene.frame, true_camera @ fix))
        masks.append(_erode(scene.mask))
        truths.append(scene.truth.wxyz_xyz)
        cameras.append(true_camera.wxyz_xyz)
    tier = np.array([p[0] for p in plan], np.int32)
    view = np.array([p[1] for p in plan], np.int32)
    truth = SE3(jnp.stack(truths))
    stacked = stack_frames(frames)

    samples, faces = trimesh.sample.sample_surface(base.model, 2048, seed=seed)
    model_points = samples.astype(np.float32)
    model_normals = base.model.face_normals[faces].astype(np.float32)
    views = _views(
        stacked, np.stack(masks), model_points, model_normals, num_points,
        max_correspondence_distance, seed,
    )  # fmt: skip
    scale = np.r_[[init_sigma[0]] * 3, [np.radians(init_sigma[1])] * 3]
    inits = truth @ se3_exp(jnp.asarray(rng.normal(size=(len(plan), 6)) * scale, jnp.float32))
    # Registered in chunks of the viewpoint tier's size by the function the hand-eye
    # correction differentiates: one compilation serves the study and the correction.
    chunk, anchors = int(np.sum(tier == 2)), _corners(model_points)
    order = np.arange(-(-len(plan) // chunk) * chunk) % len(plan)  # pad by wrapping around
    poses, status = [], []
    for part in order.reshape(-1, chunk):
        sub = eqx.tree_at(
            lambda v: (v.depth, v.base_T_camera, v.pixels, v.weights), views,
            (views.depth[part], SE3(views.base_T_camera.wxyz_xyz[part]), views.pixels[part],
             views.weights[part]),
        )  # fmt: skip
        start = SE3(inits.wxyz_xyz[part])
        _, _, p, st = _linearise(jnp.zeros(6, jnp.float32), sub, start, anchors, max_iterations)
        poses.append(p.wxyz_xyz)
        status.append(st._value)
    poses = SE3(jnp.concatenate(poses)[: len(plan)])
    status = type(st)(_value=jnp.concatenate(status)[: len(plan)], _enumeration=st._enumeration)

    nominal_pose = se3_from_matrix(nominal.astype(np.float32))
    referred = poses @ truth.inverse() @ nominal_pose

    # Each tier padded to the longest (zero weights): one compilation, shared with the
    # correction's statistics when the viewpoint tier is the longest.
    length = max(np.sum(tier == t) for t in range(3))

    def stats(t):
        idx = np.flatnonzero(tier == t)
        pad = np.r_[idx, np.full(length - len(idx), idx[0])]
        result = pose_statistics(
            SE3(referred.wxyz_xyz[pad]), symmetry=base.symmetry, groups=view[pad],
            weights=np.arange(length) < len(idx), num_groups=len(viewpoints),
        )  # fmt: skip
        return result if t == 2 else eqx.tree_at(lambda r: r.groups, result, None)

    tiers = [stats(t) for t in range(3)]
    t_bias = np.stack(
        [np.asarray(s.mean.translation() - nominal_pose.translation()) for s in tiers]
    )
    r_bias = np.stack(
        [np.asarray((s.mean.rotation() @ nominal_pose.rotation().inverse()).log()) for s in tiers]
    )
    lateral = np.asarray(poses.translation() - truth.translation(), float) @ axis
    sigma = np.array([np.std(lateral[tier == t], ddof=1) for t in range(3)])
    mean = np.array([np.mean(lateral[tier == t]) for t in range(3)])
    margin = grasp_margin(gripper_opening, object_width)
    excess = np.sqrt(np.maximum(sigma**2 - sigma[0] ** 2, 0.0))
    budget = error_budget({TIERS[0]: sigma[0], TIERS[1]: excess[1], TIERS[2]: excess[2]})
    third = tier == 2
    return Repeatability(
        frozen=tiers[0],
        replacement=tiers[1],
        viewpoint=tiers[2],
        translation_bias=jnp.asarray(t_bias),
        rotation_bias_deg=jnp.asarray(np.degrees(r_bias)),
        nominal=nominal_pose,
        poses=poses,
        truth=truth,
        tier=jnp.asarray(tier),
        view=jnp.asarray(view),
        status=status,
        lateral_error=jnp.asarray(lateral),
        lateral_sigma=jnp.asarray(sigma),
        lateral_bias=jnp.asarray(mean),
        margin=margin,
        grasp_success=grasp_success_probability(sigma, mean, margin),
        budget=budget,
        budget_grasp_success=grasp_success_probability(budget.total, 0.0, margin),
        hand_eye_bias=bias,
        frames=jax.tree.map(lambda x: x[third] if jnp.ndim(x) else x, stacked),
        masks=jnp.asarray(np.stack(masks)[third]),
        true_base_T_camera=SE3(jnp.stack(cameras)[third]),
        model_points=jnp.asarray(model_points),
        model_normals=jnp.asarray(model_normals),
        symmetry=base.symmetry,
    )
