"""The hand-eye correction that makes camera viewpoints agree on where a static object is,
found by differentiating through lifting and registration.

:func:`estimate_hand_eye_correction` takes frames of one object seen from several camera poses,
each with the hand-eye as reported (``base_T_camera``, sharing one calibration error, a right
perturbation: eye-in-hand, an error in ``flange_T_camera``). It finds the correction
``exp(delta)`` to the reported ``base_T_camera`` that makes the frames agree, by Gauss-Newton on
the spread of the object across frames, with the Jacobian taken by ``jax.jacfwd`` through lifting
(:meth:`jaxreg.RGBDFrame.points`) and ICP (implicit differentiation at the converged fixed
point).

Registration: ``num_points`` of each mask's valid pixels drawn at random, a fixed set per frame
(subsampling in pixel space keeps the lift differentiable, where :func:`jaxreg.voxel_downsample`
is a host step); lifted through the intrinsics and the corrected ``base_T_camera``; registered
scene -> model (every scene point has its match on the model, whatever part is visible) by
point-to-plane ICP against the model's surface samples and their normals.

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

What a correction cannot remove: the registration's own view-dependent bias. The sensor's
depth noise (1-3 mm per pixel at 0.45-0.75 m on a D435 at 640x360) meets the object's edges
differently from each view, so with no hand-eye error at all the viewpoints of the synthetic
box study differ by up to 0.2 mm and 0.5 degrees, tight clusters that the per-viewpoint test
(p < 0.01, offset over pooled within-view sigma > 1, 4 draws per view) flags on 2 of 4 seeds.
It is not a rigid change of the camera: part of it stays in the offsets after the correction,
part is absorbed into the correction as an error of a millimetre or two (within its standard
error). ``bias_left`` therefore calls a bias left only above ``resolution``.

Conventions: poses ``a_T_b``; tangents jaxlie's ``(vx, vy, vz, wx, wy, wz)`` (metres,
radians); the correction is a right perturbation of ``base_T_camera`` (camera frame).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.camera.model import Intrinsics, RGBDFrame
from jaxreg.core._result import AbstractResult
from jaxreg.geometry.lie import se3_exp
from jaxreg.geometry.metrics import Symmetry, canonicalise
from jaxreg.registration.icp import ICPStatus, icp
from jaxreg.search.neighbors import NeighborGrid, build_grid
from jaxreg.uncertainty import PoseStatistics, pose_statistics

__all__ = ["HandEyeCorrection", "HandEyeStatus", "estimate_hand_eye_correction", "stack_frames"]

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
    no_improvement = (
        "no step reduced the views' disagreement (the first Gauss-Newton step, halved 4 "
        "times, made it worse): the correction is left at zero. The views may already agree "
        "to within the registrations' noise, or their registrations do not follow the "
        "correction smoothly (a start in another basin): check the starts and masks"
    )
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
        converged: the last step fell below ``tolerance`` (metres, radians), or, after
            steps that reduced the disagreement, no further step reduced it (the noise
            floor); False when the first step could not reduce it (``no_improvement``).
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
        bias_left: ``()`` after the correction, the per-viewpoint test still fires
            (``after.groups.bias_detected``) on an offset larger than ``resolution``; False
            without ``groups``. The test alone (p < 0.01 and offset over pooled within-view
            sigma > 1) also flags offsets of a tenth of a millimetre, the registration's own
            view-dependent bias (see the module docstring), which no hand-eye correction can
            remove.
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
    bias_left: Bool[Array, ""]
    registration_status: ICPStatus


def _bias_beyond(stats: PoseStatistics, resolution: tuple[float, float]) -> bool:
    """The per-viewpoint test fires and some viewpoint's offset exceeds ``resolution``
    (metres, degrees) on some axis."""
    groups = stats.groups
    offset = np.abs(np.asarray(groups.translation_offset)).max() > resolution[0]
    turn = np.abs(np.asarray(groups.rotation_offset_deg)).max() > resolution[1]
    return bool(groups.bias_detected) and bool(offset or turn)


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
    resolution: tuple[float, float] = (0.5e-3, 0.5),
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
        symmetry: the object's symmetry: every start is moved to the first one's branch (the
            frames are compared through the model's corners), and the statistics use it.
        num_points: pixels per frame registered (static).
        max_correspondence_distance, max_iterations: ICP's (point-to-plane).
        max_steps: Gauss-Newton steps at most.
        tolerance: a step below this (metres and radians) ends the iteration.
        rank_tolerance: relative singular value below which a direction is unobservable.
        resolution: ``(metres, degrees)``: a viewpoint offset (group mean minus overall mean)
            at most this large on every axis is not called a bias left (``bias_left``). The
            default sits above the registration's own view-dependent offsets on the synthetic
            D435 scenes (up to 0.2 mm and 0.5 degrees with no hand-eye error) and far below a
            calibration error that matters against a grasp margin of millimetres.
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
    if symmetry is not None:  # one branch for all: the anchors are compared frame to frame
        inits = canonicalise(inits, SE3(inits.wxyz_xyz[0]), symmetry)
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
    converged, stalled, steps = False, False, 0
    while steps < max_steps and not converged:
        coef, *_ = np.linalg.lstsq(jac @ basis.T, -residual, rcond=None)
        step = basis.T @ coef
        for _ in range(4):  # halve a step that makes the views disagree more
            trial = linearise(delta + step * scale, poses)
            if np.sum(trial[1] ** 2) <= np.sum(residual**2):
                break
            step = step / 2
        else:  # no step reduces the disagreement: the noise floor, once a step has improved
            converged, stalled = steps > 0, steps == 0
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
    elif stalled:
        code = HandEyeStatus.no_improvement
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
    before, after = stats(poses_before), stats(poses)
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
        before=before,
        after=after,
        bias_left=jnp.asarray(after is not None and _bias_beyond(after, resolution)),
        registration_status=status,
    )
