"""The three tiers of a pose repeatability study on synthetic scenes, with a planted hand-eye
error.

:func:`repeatability` runs them on scenes of :func:`jaxreg.synth.tabletop_scene` (small images,
no clutter by default):

1. **frozen**: one scene re-measured ``frozen`` times (new sensor-noise draws): the spread is
   the sensor's noise through the estimator;
2. **re-placement**: the object re-placed ``replacements`` times around its nominal pose
   (uniform jitter of ``placement`` metres in x, y and ``placement_deg`` of yaw), same camera:
   the pose-dependent error (what the segment holds, which faces are seen, where the voxels
   fall) joins in;
3. **viewpoint**: the object left in place and seen from ``len(viewpoints)`` camera poses
   (an arm moving an eye-in-hand camera), each re-measured ``draws_per_view`` times.

Every frame reports a hand-eye transform that is off from the true one by a planted right
perturbation, ``reported = true @ exp(hand_eye_bias)``: constant in the camera frame, as an
eye-in-hand calibration error is. It moves each estimate by a few millimetres, the same way
every time from one viewpoint, so tiers 1 and 2 cannot see it; tier 3 does (per-viewpoint
clusters, each tight, mutually offset: the groups test of
:func:`jaxreg.uncertainty.pose_statistics`). :meth:`Repeatability.correct_hand_eye` then
finds the correction that makes the viewpoints agree
(:func:`jaxreg.studies.estimate_hand_eye_correction`).

Two estimators (``registration``):

* ``"pipeline"`` (default): :func:`jaxreg.estimate_pose` on every frame, segmentation and
  global initialisation included: what a user of the library gets. A frame where it fails is
  counted (``found``) and left out of the statistics. The hand-eye correction registers the
  viewpoint frames' pipeline segments (the pixels their poses explain), started from the
  pipeline's poses.
* ``"mask"``: the scene's exact target mask, and point-to-plane ICP from the truth perturbed by
  ``init_sigma`` (the correction's own registration, see :mod:`jaxreg.studies.basin`): isolates the
  sensor, placement and calibration errors from segmentation and initialisation, at a
  fraction of the cost.

The exact masks lose their one-pixel silhouette ring (where the sensor mixes depths; dropping
it halves the view-dependent registration bias); the pipeline removes flying pixels itself.

Conventions: poses ``a_T_b``; tangents jaxlie's ``(vx, vy, vz, wx, wy, wz)`` (metres,
radians); the hand-eye bias is a right perturbation of ``base_T_camera`` (camera frame).
Distances in metres, angles in degrees where the name says so.
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

from jaxreg.camera.model import RGBDFrame
from jaxreg.geometry.lie import se3_exp, se3_from_matrix
from jaxreg.geometry.metrics import Symmetry, canonicalise
from jaxreg.registration.icp import ICPStatus
from jaxreg.studies._hand_eye import (
    HandEyeCorrection,
    _corners,
    _linearise,
    _views,
    estimate_hand_eye_correction,
    stack_frames,
)
from jaxreg.uncertainty import (
    ErrorBudget,
    PoseStatistics,
    error_budget,
    grasp_margin,
    grasp_success_probability,
    pose_statistics,
)

__all__ = ["Repeatability", "repeatability"]

TIERS = ("frozen", "re-placement", "viewpoint")
REGISTRATIONS = ("pipeline", "mask")


class Repeatability(eqx.Module):
    """Result of :func:`repeatability`: ``K`` frames over the three tiers (``TIERS``: frozen,
    re-placement, viewpoint), ``K3`` of them in the viewpoint tier with a pose (``found``).

    Statistics take each estimate (on the symmetry branch nearest its truth) referred to the
    nominal pose, ``est @ truth^-1 @ nominal`` (its base-frame error carried to the nominal
    pose), so the re-placement tier's spread is the estimator's error, not the placement
    jitter itself. Frames without a pose are left out.

    Attributes:
        frozen, replacement: :class:`jaxreg.uncertainty.PoseStatistics` of tiers 1 and 2.
        viewpoint: the same for tier 3 with ``groups`` = viewpoint (``viewpoint.groups``: the
            per-viewpoint bias test).
        translation_bias: ``(3, 3)`` per tier, its mean position minus the nominal (base
            frame, metres): what the hand-eye error does to every estimate, which only the
            synthetic truth shows.
        rotation_bias_deg: ``(3, 3)`` per tier, ``log(R_mean R_nominal^-1)`` (degrees).
        nominal: ``SE3`` the object's nominal ``base_T_object``.
        poses: ``SE3`` batch ``(K,)`` estimated ``base_T_object`` (reported hand-eye), on
            the symmetry branch nearest the truth; NaN where ``found`` is False (no pose).
        truth: ``SE3`` batch ``(K,)`` true ``base_T_object`` of each frame.
        found: ``(K,)`` the estimator gave a pose: the pipeline succeeded, or (``"mask"``)
            ICP ended converged or at its iteration bound (``status``).
        reasons: ``K`` strings: why each frame has a pose or not: the pipeline's one-line
            reason, or (``"mask"``) the ICP status's message.
        tier: ``(K,)`` 0, 1, 2 for frozen, re-placement, viewpoint.
        view: ``(K,)`` viewpoint label (0 in tiers 1 and 2).
        status: :class:`jaxreg.ICPStatus` batch ``(K,)`` with ``"mask"``; ``None`` with
            ``"pipeline"`` (see ``found`` and ``reasons``).
        lateral_error: ``(K,)`` position error along ``closing_axis`` (metres; NaN without a
            pose).
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
        frames: :class:`~jaxreg.camera.RGBDFrame` batch ``(K3,)`` of the viewpoint tier's
            frames with a pose (as reported), with ``masks (K3, H, W)`` (eroded) and
            ``view_poses`` (their estimates), for :meth:`correct_hand_eye`.
        true_base_T_camera: ``SE3`` batch ``(K3,)`` those frames' true hand-eye.
        model_points, model_normals: ``(M, 3)`` the model's surface samples and normals.
        symmetry: the object's :class:`jaxreg.Symmetry`.
        registration: the estimator, one of ``REGISTRATIONS``.
    """

    frozen: PoseStatistics
    replacement: PoseStatistics
    viewpoint: PoseStatistics
    translation_bias: Float[Array, "3 3"]
    rotation_bias_deg: Float[Array, "3 3"]
    nominal: SE3
    poses: SE3
    truth: SE3
    found: Bool[Array, " K"]
    reasons: tuple[str, ...] = eqx.field(static=True)
    tier: Int[Array, " K"]
    view: Int[Array, " K"]
    status: ICPStatus | None
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
    view_poses: SE3
    view_labels: Int[Array, " K3"]
    true_base_T_camera: SE3
    model_points: Float[Array, "M 3"]
    model_normals: Float[Array, "M 3"]
    symmetry: Symmetry
    registration: str = eqx.field(static=True)

    def correct_hand_eye(self, **options) -> HandEyeCorrection:
        """:func:`estimate_hand_eye_correction` on the viewpoint tier's frames, started from
        their estimates, with the viewpoints as groups; ``options`` are its keywords."""
        return estimate_hand_eye_correction(
            self.frames, self.masks, self.model_points, self.model_normals, self.view_poses,
            groups=np.asarray(self.view_labels), symmetry=self.symmetry, **options,
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
    from jaxreg.synth.scenes import look_at

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


def _register_masks(stacked, masks, model_points, model_normals, truth, tier, options, rng):
    """``"mask"`` registration of every frame: poses ``(K,)`` and ICP statuses, in chunks of
    the viewpoint tier's size by the function the hand-eye correction differentiates (one
    compilation serves the study and the correction)."""
    num_points, distance, iterations, init_sigma, seed = options
    views = _views(stacked, masks, model_points, model_normals, num_points, distance, seed)
    k = len(tier)
    scale = np.r_[[init_sigma[0]] * 3, [np.radians(init_sigma[1])] * 3]
    inits = truth @ se3_exp(jnp.asarray(rng.normal(size=(k, 6)) * scale, jnp.float32))
    chunk, anchors = int(np.sum(tier == 2)), _corners(model_points)
    order = np.arange(-(-k // chunk) * chunk) % k  # pad by wrapping around
    poses, status = [], []
    for part in order.reshape(-1, chunk):
        sub = eqx.tree_at(
            lambda v: (v.depth, v.base_T_camera, v.pixels, v.weights), views,
            (views.depth[part], SE3(views.base_T_camera.wxyz_xyz[part]), views.pixels[part],
             views.weights[part]),
        )  # fmt: skip
        start = SE3(inits.wxyz_xyz[part])
        _, _, p, st = _linearise(jnp.zeros(6, jnp.float32), sub, start, anchors, iterations)
        poses.append(p.wxyz_xyz)
        status.append(st._value)
    poses = SE3(jnp.concatenate(poses)[:k])
    status = type(st)(_value=jnp.concatenate(status)[:k], _enumeration=st._enumeration)
    return poses, status


def _messages(status: ICPStatus) -> np.ndarray:
    """The messages of a batch of ICP statuses."""
    table = np.asarray(status._enumeration._index_to_message, dtype=object)
    return table[np.asarray(status._value)]


def _explained(frame: RGBDFrame, mask: np.ndarray, pose: SE3, tree, distance: float):
    """``mask`` less the pixels whose lifted point lies farther than ``distance`` from the
    model placed at ``pose`` (table and background that a segment holds)."""
    points = np.asarray(frame.points(mask))[mask]
    near, _ = tree.query(np.asarray(pose.inverse() @ points), distance_upper_bound=distance)
    keep = mask.copy()
    keep[mask] = np.isfinite(near)
    return keep


def _register_pipeline(frames, model_points, model_normals, symmetry, truth, inlier_distance):
    """:func:`jaxreg.estimate_pose` on every frame: poses ``(K,)`` (a placeholder, the truth,
    where it failed: the caller keeps those out of every statistic and reports NaN), found
    ``(K,)``, masks ``(K, H, W)`` (the segment less the pixels its pose does not put within
    ``inlier_distance`` of the model) and reasons."""
    from scipy.spatial import cKDTree

    from jaxreg.pipeline.estimate import estimate_pose

    tree = cKDTree(model_points)
    poses, found, masks, reasons = [], [], [], []
    for k, frame in enumerate(frames):
        est = estimate_pose(frame, model_points, model_normals=model_normals, symmetry=symmetry)
        found.append(est.success)
        poses.append(est.pose.wxyz_xyz if est.success else truth.wxyz_xyz[k])
        # The pipeline has removed flying pixels already; eroding its holed segment as well
        # would leave a few hundred pixels of a far view.
        mask = est.mask
        masks.append(
            _explained(frame, mask, est.pose, tree, inlier_distance) if est.success else mask
        )
        reasons.append(est.reason)
    return SE3(jnp.stack(poses).astype(jnp.float32)), np.array(found), np.stack(masks), reasons


def repeatability(
    seed: int = 0,
    *,
    object: str = "box",
    registration: str = "pipeline",
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
    model_samples: int = 2048,
    init_sigma: tuple[float, float] = (0.005, 2.0),
    max_correspondence_distance: float = 0.015,
    max_iterations: int = 40,
    inlier_distance: float = 0.004,
    gripper_opening: float = 0.040,
    object_width: float = 0.025,
    closing_axis: Float[ArrayLike, " 3"] = (1.0, 0.0, 0.0),
) -> Repeatability:
    """The three-tier repeatability study of the module docstring on synthetic scenes.

    Args:
        seed: the scene (:func:`jaxreg.synth.tabletop_scene`): object pose, nominal camera,
            and every draw of the study (noise, placements, starts, pixels).
        object: the target, one of :data:`jaxreg.synth.OBJECTS`.
        registration: ``"pipeline"`` (:func:`jaxreg.estimate_pose`, what a user gets) or
            ``"mask"`` (exact masks and ICP from near the truth; see the module docstring).
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
        num_points: pixels registered per frame by the ``"mask"`` registration and the
            hand-eye correction.
        model_samples: surface samples of the model (its normals are the faces').
        init_sigma: ``(metres, degrees)`` per-axis sigma of the ``"mask"`` registration's
            start, a perturbation of the truth.
        max_correspondence_distance, max_iterations: the ``"mask"`` registration's ICP
            (point-to-plane).
        inlier_distance: with ``"pipeline"``, the hand-eye correction registers only the
            segment pixels that the pipeline's pose puts within this distance (metres) of the
            model: a segment also holds table and background pixels, which have no match on
            the model and would drag a scene-to-model registration differently from each view.
        gripper_opening, object_width: the grasp (metres): margin ``(opening - width) / 2``.
        closing_axis: ``(3,)`` base-frame direction along which the jaws close.

    Returns:
        :class:`Repeatability`.

    Raises:
        ValueError: fewer than 2 frames in a tier or fewer than 2 viewpoints, a bad object or
            registration, a frame whose mask has no depth, or (pipeline) fewer than 2 poses
            found in a tier.
    """
    from jaxreg.synth.scenes import StereoSensor, tabletop_scene

    if registration not in REGISTRATIONS:
        raise ValueError(f"registration must be one of {REGISTRATIONS}, got {registration!r}")
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

    samples, faces = trimesh.sample.sample_surface(base.model, model_samples, seed=seed)
    model_points = samples.astype(np.float32)
    model_normals = base.model.face_normals[faces].astype(np.float32)
    masks = np.stack(masks)
    if registration == "mask":
        options = (num_points, max_correspondence_distance, max_iterations, init_sigma, seed)
        poses, status = _register_masks(
            stacked, masks, model_points, model_normals, truth, tier, options, rng
        )
        codes = np.asarray(status._value)
        found = (codes == ICPStatus.success._value) | (codes == ICPStatus.max_iterations._value)
        reasons = tuple(str(m) for m in np.atleast_1d(_messages(status)))
    else:
        poses, found, masks, reasons = _register_pipeline(
            frames, model_points, model_normals, base.symmetry, truth, inlier_distance
        )
        status, reasons = None, tuple(reasons)
    for t in range(3):
        if np.sum(found[tier == t]) < 2:
            raise ValueError(
                f"the {registration} registration found the object in fewer than 2 frames of "
                f"the {TIERS[t]} tier: {sorted(set(np.asarray(reasons)[(tier == t) & ~found]))}"
            )
    poses = canonicalise(poses, truth, base.symmetry)

    nominal_pose = se3_from_matrix(nominal.astype(np.float32))
    referred = poses @ truth.inverse() @ nominal_pose

    # Each tier padded to the longest (zero weights): one compilation, shared with the
    # correction's statistics when the viewpoint tier is the longest.
    length = max(np.sum(tier == t) for t in range(3))

    def stats(t):
        idx = np.flatnonzero(tier == t)
        pad = np.r_[idx, np.full(length - len(idx), idx[0])]
        weights = (np.arange(length) < len(idx)) & found[pad]
        result = pose_statistics(
            SE3(referred.wxyz_xyz[pad]), symmetry=base.symmetry, groups=view[pad],
            weights=weights, num_groups=len(viewpoints),
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
    lateral = np.where(found, lateral, np.nan)
    sigma = np.array([np.nanstd(lateral[tier == t], ddof=1) for t in range(3)])
    mean = np.array([np.nanmean(lateral[tier == t]) for t in range(3)])
    margin = grasp_margin(gripper_opening, object_width)
    excess = np.sqrt(np.maximum(sigma**2 - sigma[0] ** 2, 0.0))
    budget = error_budget({TIERS[0]: sigma[0], TIERS[1]: excess[1], TIERS[2]: excess[2]})
    third = (tier == 2) & found
    return Repeatability(
        frozen=tiers[0],
        replacement=tiers[1],
        viewpoint=tiers[2],
        translation_bias=jnp.asarray(t_bias),
        rotation_bias_deg=jnp.asarray(np.degrees(r_bias)),
        nominal=nominal_pose,
        poses=SE3(jnp.where(jnp.asarray(found)[:, None], poses.wxyz_xyz, jnp.nan)),
        truth=truth,
        found=jnp.asarray(found),
        reasons=reasons,
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
        masks=jnp.asarray(masks[third]),
        view_poses=SE3(poses.wxyz_xyz[third]),
        view_labels=jnp.asarray(view[third]),
        true_base_T_camera=SE3(jnp.stack(cameras)[third]),
        model_points=jnp.asarray(model_points),
        model_normals=jnp.asarray(model_normals),
        symmetry=base.symmetry,
        registration=registration,
    )
