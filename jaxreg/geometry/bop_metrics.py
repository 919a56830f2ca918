"""The BOP benchmark's pose errors and its Average Recall (Hodan et al., ECCV 2018 and the
BOP Challenge 2019 onwards), as its toolkit defines them.

* :func:`mssd`: Maximum Symmetry-aware Surface Distance, ``min_S max_p |est p - truth S p|``
  over the model's vertices ``p`` and the object's symmetry transforms ``S`` (the units of
  the points);
* :func:`mspd`: Maximum Symmetry-aware Projection Distance, the same with the points'
  projections (pixels);
* :func:`vsd`: Visible Surface Discrepancy on depth maps already rendered: the fraction of
  the visible surface (in the estimated or the true pose) where the two renderings disagree
  by ``tau`` or more, or where only one of them is visible;
* :func:`bop_symmetry_transforms`: the toolkit's finite set of symmetry transforms of a
  model (its continuous symmetries cut into equal turns);
* :func:`correct` and :func:`average_recall`: the errors against BOP's threshold sets
  (``VSD_TAUS``, ``VSD_THRESHOLDS``, ``MSSD_THRESHOLDS``, ``MSPD_THRESHOLDS``) and the
  Average Recall, the mean of the three metrics' mean recalls.

Conventions: poses map model coordinates into the camera frame (``camera_T_object``) and are
given as ``SE3`` or as ``(..., 4, 4)`` matrices; a symmetry transform ``S (4, 4)`` maps model
coordinates to model coordinates, so ``truth @ S`` is as right as ``truth``. Units are the
caller's (jaxreg uses metres), the same for points, poses, depth, ``delta`` and ``diameter``.
Every function is pure JAX: ``jax.jit`` compiles it and ``jax.vmap`` batches it over targets.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Bool, Float

__all__ = [
    "MSPD_THRESHOLDS",
    "MSSD_THRESHOLDS",
    "VSD_DELTA",
    "VSD_TAUS",
    "VSD_THRESHOLDS",
    "BopRecall",
    "average_recall",
    "bop_symmetry_transforms",
    "correct",
    "mspd",
    "mssd",
    "vsd",
]

# BOP 2019's settings (the toolkit's eval_bop19_pose.py), built as it builds them so that the
# floating-point thresholds are the same numbers.
VSD_DELTA = 0.015  # metres: the visibility test's tolerance (15 mm; ITODD uses 5 mm)
VSD_TAUS = np.arange(0.05, 0.51, 0.05)  # misalignment tolerances, fractions of the diameter
VSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # a VSD error below one is correct
MSSD_THRESHOLDS = np.arange(0.05, 0.51, 0.05)  # fractions of the object diameter
MSPD_THRESHOLDS = np.arange(5, 51, 5).astype(np.float64)  # pixels of a 640-pixel-wide image
MSPD_REFERENCE_WIDTH = 640.0  # MSPD is scaled by this / the image width before thresholding
MAX_SYM_DISC_STEP = 0.01  # fraction of the diameter a continuous symmetry's turns may move


def bop_symmetry_transforms(
    discrete: Float[ArrayLike, "K 4 4"] | None = None,
    continuous: Sequence[tuple[ArrayLike, ArrayLike]] = (),
    *,
    max_sym_disc_step: float = MAX_SYM_DISC_STEP,
) -> np.ndarray:
    """The finite set of symmetry transforms BOP scores with, identity first. Host numpy.

    Each continuous symmetry (an axis through ``offset``) is cut into
    ``ceil(pi / max_sym_disc_step)`` equal turns, so that the model point farthest from the
    axis moves at most ``max_sym_disc_step`` diameters between neighbouring turns (315 turns
    for BOP's 0.01). The set is every discrete transform (the identity and ``discrete``)
    followed by every turn: ``C @ D`` for ``D`` over the discrete set (outer) and ``C`` over
    the turns of every continuous symmetry (inner), the toolkit's order.

    Args:
        discrete: ``(K, 4, 4)`` model-frame transforms (models_info's
            ``symmetries_discrete``, in the caller's units), without the identity; or None.
        continuous: ``(axis (3,), offset (3,))`` pairs (models_info's
            ``symmetries_continuous``): the axis direction (any length) and a point on it.
        max_sym_disc_step: BOP's 0.01 unless the evaluation says otherwise.

    Returns:
        ``(S, 4, 4)`` float64 transforms.

    Raises:
        ValueError: a transform that is not ``(4, 4)``, a zero axis, a non-positive step.
    """
    if not max_sym_disc_step > 0:
        raise ValueError(f"max_sym_disc_step must be positive, got {max_sym_disc_step}")
    identity = np.eye(4)[None]
    if discrete is None or np.size(discrete) == 0:
        fixed = identity
    else:
        discrete = np.asarray(discrete, np.float64)
        if discrete.ndim != 3 or discrete.shape[1:] != (4, 4):
            raise ValueError(f"discrete symmetries must be (K, 4, 4), got {discrete.shape}")
        fixed = np.concatenate([identity, discrete])
    turns = []
    steps = int(np.ceil(np.pi / max_sym_disc_step))
    for axis, offset in continuous:
        axis, offset = np.asarray(axis, np.float64), np.asarray(offset, np.float64)
        if axis.shape != (3,) or offset.shape != (3,) or not np.linalg.norm(axis) > 0:
            raise ValueError(
                f"a continuous symmetry needs a non-zero axis (3,) and an offset (3,), got "
                f"{axis.tolist()} and {offset.tolist()}"
            )
        axis = axis / np.linalg.norm(axis)
        for angle in 2 * np.pi * np.arange(steps) / steps:
            turn = np.eye(4)
            turn[:3, :3] = _rodrigues(axis, angle)
            turn[:3, 3] = offset - turn[:3, :3] @ offset  # about the axis through offset
            turns.append(turn)
    if not turns:
        return fixed
    return np.einsum("cij,djk->dcik", np.stack(turns), fixed).reshape(-1, 4, 4)


def _rodrigues(axis: np.ndarray, angle: float) -> np.ndarray:
    """The rotation ``(3, 3)`` by ``angle`` about the unit ``axis``."""
    c, s = np.cos(angle), np.sin(angle)
    cross = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return c * np.eye(3) + (1.0 - c) * np.outer(axis, axis) + s * cross


def _matrix(pose: SE3 | ArrayLike, name: str) -> Array:
    """``(..., 4, 4)`` of an ``SE3`` or a matrix; ``ValueError`` for anything else."""
    matrix = pose.as_matrix() if isinstance(pose, SE3) else jnp.asarray(pose)
    if matrix.ndim < 2 or matrix.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must be an SE3 or (..., 4, 4) matrices, got {matrix.shape}")
    return matrix


def _inputs(points, est, truth, symmetry_transforms):
    """Common dtype of the inputs: the points, the two poses and the transforms."""
    est, truth = _matrix(est, "est"), _matrix(truth, "truth")
    points, syms = jnp.asarray(points), jnp.asarray(symmetry_transforms)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 1:
        raise ValueError(f"points must be (N, 3) with N >= 1, got {points.shape}")
    if syms.ndim != 3 or syms.shape[1:] != (4, 4) or syms.shape[0] < 1:
        raise ValueError(
            f"symmetry_transforms must be (S, 4, 4) with the identity first, got {syms.shape}: "
            "pass np.eye(4)[None] for an object without symmetry"
        )
    dtype = jnp.result_type(points.dtype, est.dtype, truth.dtype, syms.dtype, jnp.float32)
    return points.astype(dtype), est.astype(dtype), truth.astype(dtype), syms.astype(dtype)


def _apply(transform: Array, points: Array) -> Array:
    """``transform (..., 4, 4)`` applied to ``points (N, 3)``: ``(..., N, 3)``."""
    return points @ jnp.swapaxes(transform[..., :3, :3], -1, -2) + transform[..., None, :3, 3]


def _max_min(distances: Array) -> Array:
    """``min`` over symmetries of the ``max`` over points of ``distances (..., S, N)``."""
    return jnp.min(jnp.max(distances, axis=-1), axis=-1)


def mssd(
    points: Float[ArrayLike, "N 3"],
    est: SE3 | Float[ArrayLike, "*batch 4 4"],
    truth: SE3 | Float[ArrayLike, "*batch 4 4"],
    symmetry_transforms: Float[ArrayLike, "S 4 4"],
) -> Float[Array, "*batch"]:
    """MSSD: ``min over S of max over p of |est p - truth S p|`` (the units of the points).

    Computed in the model frame (``truth^-1 est p - S p``: a rigid motion keeps distances),
    so float32 keeps the precision of the small differences, not of the camera distance.

    Args:
        points: ``(N, 3)`` model vertices, model frame (BOP uses the mesh's vertices).
        est, truth: ``camera_T_object`` poses, ``SE3`` or ``(..., 4, 4)``; batches broadcast.
        symmetry_transforms: ``(S, 4, 4)`` (:func:`bop_symmetry_transforms`).

    Returns:
        ``(...)`` errors.
    """
    points, est, truth, syms = _inputs(points, est, truth, symmetry_transforms)
    rotation_t = jnp.swapaxes(truth[..., :3, :3], -1, -2)
    relative_r = rotation_t @ est[..., :3, :3]
    relative_t = (rotation_t @ (est[..., :3, 3] - truth[..., :3, 3])[..., None])[..., 0]
    moved = points @ jnp.swapaxes(relative_r, -1, -2) + relative_t[..., None, :]  # (..., N, 3)
    offsets = moved[..., None, :, :] - _apply(syms, points)  # (..., S, N, 3)
    return _max_min(jnp.linalg.norm(offsets, axis=-1))


def _project(K: Array, camera_points: Array) -> Array:
    """Pixels ``(..., 2)`` of camera-frame points ``(..., 3)`` through ``K (3, 3)``."""
    image = camera_points @ K.T
    return image[..., :2] / image[..., 2:]


def mspd(
    points: Float[ArrayLike, "N 3"],
    est: SE3 | Float[ArrayLike, "*batch 4 4"],
    truth: SE3 | Float[ArrayLike, "*batch 4 4"],
    symmetry_transforms: Float[ArrayLike, "S 4 4"],
    K: Float[ArrayLike, "3 3"],
) -> Float[Array, "*batch"]:
    """MSPD: ``min over S of max over p of |pi(est p) - pi(truth S p)|`` in pixels.

    ``pi`` is the pinhole projection through ``K`` without distortion, as BOP projects. The
    benchmark compares it with thresholds scaled to a 640-pixel-wide image
    (:func:`correct`, ``image_width``).

    Args:
        points: ``(N, 3)`` model vertices, model frame.
        est, truth: ``camera_T_object`` poses, ``SE3`` or ``(..., 4, 4)``; batches broadcast.
        symmetry_transforms: ``(S, 4, 4)`` (:func:`bop_symmetry_transforms`).
        K: ``(3, 3)`` camera matrix.

    Returns:
        ``(...)`` errors in pixels.
    """
    points, est, truth, syms = _inputs(points, est, truth, symmetry_transforms)
    K = jnp.asarray(K, points.dtype)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    seen = _project(K, _apply(est, points))  # (..., N, 2)
    truths = truth[..., None, :, :] @ syms  # (..., S, 4, 4)
    offsets = seen[..., None, :, :] - _project(K, _apply(truths, points))
    return _max_min(jnp.linalg.norm(offsets, axis=-1))


def _distance_image(depth: Array, K: Array) -> Array:
    """Distance from the camera centre ``(H, W)`` of a z-depth image; 0 where no depth.

    Pixel ``(u, v)`` (column, row) is the ray through ``((u - cx) / fx, (v - cy) / fy, 1)``:
    pixel centres at integer coordinates, as BOP's toolkit and :class:`jaxreg.Intrinsics`.
    """
    height, width = depth.shape[-2:]
    x = (jnp.arange(width, dtype=depth.dtype) - K[0, 2]) / K[0, 0]
    y = (jnp.arange(height, dtype=depth.dtype) - K[1, 2]) / K[1, 1]
    stretch = jnp.sqrt(x[None, :] ** 2 + y[:, None] ** 2 + 1.0)
    return depth * stretch


def _measured(depth: ArrayLike, dtype) -> Array:
    """Depth with every missing value (0, negative, NaN) as 0, BOP's 'no measurement'."""
    depth = jnp.asarray(depth, dtype)
    return jnp.where(jnp.isfinite(depth) & (depth > 0), depth, 0.0)


def vsd(
    depth_est: Float[ArrayLike, "H W"],
    depth_gt: Float[ArrayLike, "H W"],
    depth_test: Float[ArrayLike, "H W"],
    K: Float[ArrayLike, "3 3"],
    *,
    delta: float | Float[ArrayLike, ""] = VSD_DELTA,
    taus: Float[ArrayLike, " T"] = VSD_TAUS,
    diameter: float | Float[ArrayLike, ""],
    normalized_by_diameter: bool = True,
) -> Float[Array, " T"]:
    """VSD of one estimate against one true pose, per misalignment tolerance ``tau``.

    The depth maps are z-depth with 0 (or NaN) where there is nothing: the model rendered at
    the estimated and at the true pose, and the test image. They are turned into distances
    from the camera centre. The model at the true pose is visible where it is rendered and
    not more than ``delta`` behind the test image's surface, or where the test image has no
    measurement (BOP 2019's visibility); at the estimated pose, the same, or where it is
    rendered and the true pose's surface is visible. With ``inter`` and ``union`` of the two
    visible surfaces and ``d`` the distance between the renderings (over the diameter when
    ``normalized_by_diameter``), the error is
    ``(#{inter: d >= tau} + #union - #inter) / #union``, and 1 for an empty union.

    Args:
        depth_est, depth_gt, depth_test: ``(H, W)`` z-depth maps in the units of ``delta``.
        K: ``(3, 3)`` camera matrix of the three maps.
        delta: visibility tolerance (BOP: 15 mm, ``VSD_DELTA`` in metres).
        taus: ``(T,)`` misalignment tolerances (fractions of the diameter when normalised).
        diameter: the object's diameter (largest distance between its vertices).
        normalized_by_diameter: divide the distances by ``diameter`` (BOP does).

    Returns:
        ``(T,)`` errors in ``[0, 1]``, one per ``tau``.
    """
    dtype = jnp.result_type(jnp.asarray(depth_gt).dtype, jnp.float32)
    est, gt, test = (_measured(d, dtype) for d in (depth_est, depth_gt, depth_test))
    if not est.shape == gt.shape == test.shape or est.ndim != 2:
        raise ValueError(
            f"the depth maps must be three (H, W) of one shape, got {est.shape}, {gt.shape} "
            f"and {test.shape}"
        )
    K = jnp.asarray(K, dtype)
    if K.shape != (3, 3):
        raise ValueError(f"K must be (3, 3), got {K.shape}")
    est, gt, test = (_distance_image(d, K) for d in (est, gt, test))
    visible_gt = _visible(gt, test, delta)
    visible_est = _visible(est, test, delta) | (visible_gt & (est > 0))
    inter, union = visible_gt & visible_est, visible_gt | visible_est
    distance = jnp.abs(gt - est)
    if normalized_by_diameter:
        distance = distance / jnp.asarray(diameter, dtype)
    taus = jnp.asarray(taus, dtype)
    far = jnp.sum(inter & (distance >= taus[:, None, None]), axis=(-2, -1))
    union_count, inter_count = jnp.sum(union), jnp.sum(inter)
    error = (far + union_count - inter_count) / jnp.maximum(union_count, 1).astype(dtype)
    return jnp.where(union_count > 0, error, 1.0)


def _visible(model: Array, test: Array, delta) -> Bool[Array, "H W"]:
    """Where the rendered model (distances) is visible in the test image: rendered, and not
    more than ``delta`` behind the test surface or where the test image has no depth."""
    return (model > 0) & ((model - test <= delta) | (test == 0))


def correct(
    errors: Float[ArrayLike, "..."], thresholds: Float[ArrayLike, " T"]
) -> Bool[Array, "... T"]:
    """``errors[..., None] < thresholds``: BOP's correctness (strictly below), per threshold.

    A missing estimate has an infinite error (VSD: 1), which no threshold accepts. Normalise
    first: MSSD by the diameter, MSPD by ``640 / image width`` (:func:`average_recall` does).
    """
    errors = jnp.asarray(errors)
    return errors[..., None] < jnp.asarray(thresholds, errors.dtype)


class BopRecall(eqx.Module):
    """Recall per threshold and BOP's Average Recall of a set of targets.

    Attributes:
        ar: ``()`` the mean of ``ar_vsd``, ``ar_mssd`` and ``ar_mspd``.
        ar_vsd, ar_mssd, ar_mspd: ``()`` each metric's mean recall over its thresholds.
        recall_vsd: ``(T, C)`` recall per ``tau`` (rows) and correctness threshold.
        recall_mssd, recall_mspd: ``(C,)`` recall per threshold.
    """

    ar: Float[Array, ""]
    ar_vsd: Float[Array, ""]
    ar_mssd: Float[Array, ""]
    ar_mspd: Float[Array, ""]
    recall_vsd: Float[Array, "T C"]
    recall_mssd: Float[Array, " C"]
    recall_mspd: Float[Array, " C"]

    @classmethod
    def from_hits(
        cls,
        vsd_hits: Bool[ArrayLike, "M T C"],
        mssd_hits: Bool[ArrayLike, "M C"],
        mspd_hits: Bool[ArrayLike, "M C"],
    ) -> BopRecall:
        """The recalls of ``M`` targets from whether each was found correctly at each
        threshold (:func:`correct`, or a matching of several estimates to several instances).
        No targets give a recall of 0, as the toolkit's."""
        recall_vsd, recall_mssd, recall_mspd = (
            _recall(h) for h in (vsd_hits, mssd_hits, mspd_hits)
        )
        means = [jnp.mean(r) for r in (recall_vsd, recall_mssd, recall_mspd)]
        return cls(
            ar=(means[0] + means[1] + means[2]) / 3,
            ar_vsd=means[0],
            ar_mssd=means[1],
            ar_mspd=means[2],
            recall_vsd=recall_vsd,
            recall_mssd=recall_mssd,
            recall_mspd=recall_mspd,
        )


def _recall(hits: Bool[ArrayLike, "M ..."]) -> Float[Array, "..."]:
    """The fraction of the ``M`` targets hit, per threshold; 0 without targets."""
    hits = jnp.asarray(hits, bool)
    return jnp.sum(hits, axis=0) / max(hits.shape[0], 1)


def average_recall(
    vsd_errors: Float[ArrayLike, "M T"],
    mssd_errors: Float[ArrayLike, " M"],
    mspd_errors: Float[ArrayLike, " M"],
    *,
    diameter: Float[ArrayLike, " M"],
    image_width: Float[ArrayLike, " M"],
) -> BopRecall:
    """BOP's Average Recall of ``M`` targets, each with the errors of its one estimate.

    MSSD is divided by the object's ``diameter`` and MSPD scaled by ``640 / image_width``
    before the thresholds (``MSSD_THRESHOLDS``, ``MSPD_THRESHOLDS``, ``VSD_THRESHOLDS`` for
    each of the ``T`` taus). A target without an estimate has errors ``inf`` (VSD: 1).

    Args:
        vsd_errors: ``(M, T)`` VSD per tau (:func:`vsd` with ``VSD_TAUS``).
        mssd_errors: ``(M,)`` MSSD in the units of ``diameter``.
        mspd_errors: ``(M,)`` MSPD in pixels.
        diameter: ``(M,)`` (or scalar) object diameters.
        image_width: ``(M,)`` (or scalar) widths in pixels of the targets' images.
    """
    mssd_errors = jnp.asarray(mssd_errors) / jnp.asarray(diameter)
    mspd_errors = jnp.asarray(mspd_errors) * (MSPD_REFERENCE_WIDTH / jnp.asarray(image_width))
    return BopRecall.from_hits(
        correct(vsd_errors, VSD_THRESHOLDS),
        correct(mssd_errors, MSSD_THRESHOLDS),
        correct(mspd_errors, MSPD_THRESHOLDS),
    )
