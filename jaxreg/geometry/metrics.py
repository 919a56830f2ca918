"""Pose error metrics that respect object symmetry: rotation error, ADD and ADD-S.

A symmetric object has several poses that explain the data equally well: a cylinder turned
about its axis, a box flipped end over end, a square tray turned by a quarter. Scoring an
estimate against the one annotated pose then punishes a correct answer, and averaging
estimates that landed on different branches gives a pose that fits nothing. This module
describes such symmetries once (:class:`Symmetry`) and measures pose error with them:

* :func:`pose_error`: translation error and geodesic rotation error, the rotation error
  minimised over the symmetry when one is given;
* :func:`canonicalise`: the equivalent pose ``pose @ S`` whose rotation is nearest a
  reference (one symmetry branch), exact for a continuous axis;
* :func:`add`: ADD, the mean distance between model points moved by the estimate and by the
  truth (forgives nothing unless a symmetry is given);
* :func:`add_s`: ADD-S, the mean distance from each model point moved by the estimate to the
  nearest model point moved by the truth (forgives any pose that puts the surface in place);
* :func:`diameter`: the model's largest extent, the scale those errors are judged against
  (ADD(-S) within 10% of it, BOP's thresholds as fractions of it).

Conventions: poses are ``jaxlie.SE3`` mapping object (model) coordinates into the scene
(``base_T_object`` or ``camera_T_object``); a symmetry ``S`` rotates the object frame about
its origin, so ``truth @ S`` is as right as ``truth``. This needs the object origin on every
symmetry axis (its centre), as the meshes of :mod:`jaxreg.synth.scenes` have. The batch axes of
``est`` and ``truth`` broadcast against each other.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3, SO3
from jaxtyping import Array, ArrayLike, Float

from jaxreg.core._brute import knn
from jaxreg.geometry.lie import rotation_angle, so3_from_matrix

__all__ = [
    "Symmetry", "add", "add_s", "canonicalise", "diameter", "pose_error", "rotation_error",
]  # fmt: skip

_TOLERANCE = 1e-6  # on orthonormality, the leading identity and the axis norm
_DIAMETER_BLOCK = 512  # rows of pairwise distances computed at once by diameter


class Symmetry(eqx.Module):
    """The rotations of an object's frame that map its surface onto itself.

    An estimate ``T`` of an object whose true pose is ``truth`` is as right as ``truth @ S``
    for every ``S`` in the set ``{rotations[k] @ Rot(axis, theta)}``: the discrete
    ``rotations``, each composed, when ``axis`` is set, with any turn ``theta`` about
    ``axis`` through the origin (a cylinder's or a bottle's). Without ``axis`` the set is
    ``rotations`` alone. The object origin must lie on every symmetry axis.

    Examples: a box with distinct sides has the identity and the half turns about x, y and
    z; a closed cylinder along z has ``axis = (0, 0, 1)`` and rotations ``{I, half turn
    about x}``; a square tray has the quarter turns about its axis; an asymmetric object
    has ``rotations = eye(3)[None]``.

    Attributes:
        rotations: ``(K, 3, 3)`` object-frame rotation matrices, the identity first.
        axis: ``(3,)`` unit axis of a continuous rotational symmetry in the object frame,
            or ``None``.
    """

    rotations: Float[ArrayLike, "K 3 3"]
    axis: Float[ArrayLike, " 3"] | None = None

    def __check_init__(self):
        r = self.rotations
        if np.ndim(r) != 3 or np.shape(r)[1:] != (3, 3) or np.shape(r)[0] < 1:
            raise ValueError(f"rotations must be (K, 3, 3) with K >= 1, got {np.shape(r)}")
        if self.axis is not None and np.shape(self.axis) != (3,):
            raise ValueError(f"axis must be (3,) or None, got {np.shape(self.axis)}")
        if isinstance(r, jax.core.Tracer) or isinstance(self.axis, jax.core.Tracer):
            return
        r = np.asarray(r, np.float64)
        if np.abs(r[0] - np.eye(3)).max() > _TOLERANCE:
            raise ValueError("rotations[0] must be the identity (the pose itself)")
        gram = np.einsum("kji,kjl->kil", r, r)
        if np.abs(gram - np.eye(3)).max() > _TOLERANCE or np.any(np.linalg.det(r) < 0):
            raise ValueError("rotations must be proper rotation matrices (orthonormal, det +1)")
        if self.axis is not None and abs(np.linalg.norm(self.axis) - 1) > _TOLERANCE:
            raise ValueError("axis must be a unit vector")

    @property
    def is_symmetric(self) -> bool:
        """True when some pose other than the truth fits the object equally."""
        return self.axis is not None or np.shape(self.rotations)[0] > 1

    def discretised(self, steps: int) -> Symmetry:
        """The same symmetry with the continuous axis replaced by ``steps`` equal turns.

        Returns a :class:`Symmetry` without ``axis`` whose ``K * steps`` rotations are
        ``rotations[k] @ Rot(axis, 2 pi j / steps)`` (``k`` outer, ``j`` inner; the identity
        stays first). Without an axis, returns ``self``. Use it where a finite set is needed
        (:func:`jaxreg.pose_statistics`); :func:`canonicalise` and :func:`pose_error` treat
        the axis exactly.

        Raises:
            ValueError: ``steps < 1``.
        """
        if steps < 1:
            raise ValueError(f"steps must be a positive number of turns, got {steps}")
        if self.axis is None:
            return self
        angles = 2 * np.pi * np.arange(steps) / steps
        turns = _axis_rotation(np.asarray(self.axis, np.float64), angles, np)
        rotations = np.asarray(self.rotations, np.float64)
        return Symmetry(np.einsum("kij,sjl->ksil", rotations, turns).reshape(-1, 3, 3))

    def transforms(self, *, steps: int | None = None) -> SE3:
        """The symmetry as an ``SE3`` batch ``(S,)`` of pure rotations, the identity first.

        :func:`jaxreg.pose_statistics` calls it with its ``symmetry_steps``. A continuous
        axis is discretised into ``steps`` turns (:meth:`discretised`).

        Raises:
            ValueError: the symmetry has a continuous axis and ``steps`` is not given.
        """
        sym = self
        if self.axis is not None:
            if steps is None:
                raise ValueError(
                    "a continuous symmetry axis has infinitely many transforms: pass steps= "
                    "(e.g. 360 for 1-degree turns), or use canonicalise(), which is exact"
                )
            sym = self.discretised(steps)
        rotations = SO3.from_matrix(jnp.asarray(sym.rotations))
        return SE3.from_rotation(rotations)


def _axis_rotation(axis, angle, xp=jnp):
    """Rodrigues' rotation matrices ``(..., 3, 3)`` by ``angle (...)`` about the unit ``axis``
    (computed with ``xp``: ``jax.numpy``, or ``numpy`` on the host in float64)."""
    c, s = xp.cos(angle)[..., None, None], xp.sin(angle)[..., None, None]
    return c * xp.eye(3, dtype=axis.dtype) + s * _skew(axis, xp) + (1 - c) * xp.outer(axis, axis)


def _skew(v, xp=jnp):
    """The cross-product matrix ``[v]x`` of ``v (3,)``: ``[v]x u = v x u``."""
    zero = xp.zeros((), v.dtype)
    return xp.stack(
        [
            xp.stack([zero, -v[2], v[1]]),
            xp.stack([v[2], zero, -v[0]]),
            xp.stack([-v[1], v[0], zero]),
        ]
    )


def _best_symmetry(relative: Array, symmetry: Symmetry) -> Float[Array, "... 3 3"]:
    """The symmetry rotation ``S (..., 3, 3)`` maximising ``tr(relative @ S)``.

    ``relative (..., 3, 3)`` is ``R_ref^T R``; the maximal trace is the smallest geodesic
    angle between ``R @ S`` and ``R_ref``. Over a continuous axis ``a`` the trace of
    ``M @ Rot(a, theta)`` is ``a^T M a + A cos(theta) + B sin(theta)`` with
    ``A = tr M - a^T M a`` and ``B = tr(M [a]x)``, maximised at ``theta = atan2(B, A)``.
    """
    rotations = jnp.asarray(symmetry.rotations, relative.dtype)
    m = relative[..., None, :, :] @ rotations  # (..., K, 3, 3)
    trace = jnp.trace(m, axis1=-2, axis2=-1)
    if symmetry.axis is None:
        return jnp.take(rotations, jnp.argmax(trace, axis=-1), axis=0)
    axis = jnp.asarray(symmetry.axis, relative.dtype)
    along = jnp.einsum("...ij,i,j->...", m, axis, axis)
    a = trace - along
    b = jnp.sum(m * _skew(axis).T, axis=(-2, -1))
    # double where: atan2 and hypot have no derivative at A = B = 0 (every turn ties there)
    live = a * a + b * b > jnp.finfo(relative.dtype).tiny
    a_safe, b_safe = jnp.where(live, a, 1.0), jnp.where(live, b, 0.0)
    theta = jnp.where(live, jnp.arctan2(b_safe, a_safe), 0.0)
    score = along + jnp.where(live, jnp.hypot(a_safe, b_safe), 0.0)
    best = jnp.argmax(score, axis=-1)
    angle = jnp.take_along_axis(theta, best[..., None], axis=-1)[..., 0]
    return jnp.take(rotations, best, axis=0) @ _axis_rotation(axis, angle)


def _broadcast(est: SE3, truth: SE3) -> tuple[SE3, SE3]:
    if not isinstance(est, SE3) or not isinstance(truth, SE3):
        raise ValueError("est and truth must be jaxlie.SE3 poses (batches broadcast)")
    dtype = jnp.result_type(est.wxyz_xyz.dtype, truth.wxyz_xyz.dtype)
    shape = jnp.broadcast_shapes(est.get_batch_axes(), truth.get_batch_axes())
    return (
        SE3(jnp.broadcast_to(est.wxyz_xyz.astype(dtype), (*shape, 7))),
        SE3(jnp.broadcast_to(truth.wxyz_xyz.astype(dtype), (*shape, 7))),
    )


def canonicalise(pose: SE3, reference: SE3, symmetry: Symmetry) -> SE3:
    """The pose's symmetric equivalent on the branch of ``reference``.

    Returns ``pose @ S`` with ``S`` in ``symmetry`` chosen so that its rotation is nearest
    (in geodesic angle) to ``reference``'s; the translation is unchanged. A continuous axis
    is handled in closed form, not by sampling. Batches ``(...)`` of ``pose`` and
    ``reference`` broadcast.
    """
    pose, reference = _broadcast(pose, reference)
    relative = (reference.rotation().inverse() @ pose.rotation()).as_matrix()
    s = so3_from_matrix(_best_symmetry(relative, symmetry))
    return SE3.from_rotation_and_translation(pose.rotation() @ s, pose.translation())


def rotation_error(est: SE3, truth: SE3, symmetry: Symmetry | None = None) -> Float[Array, "..."]:
    """Geodesic angle in radians, in ``[0, pi]``, between ``est`` and the nearest symmetric
    equivalent of ``truth`` (``truth`` itself without ``symmetry``); batch ``(...)``."""
    est, truth = _broadcast(est, truth)
    if symmetry is not None:
        est = canonicalise(est, truth, symmetry)
    return rotation_angle(truth.rotation().inverse() @ est.rotation())


def pose_error(
    est: SE3, truth: SE3, *, symmetry: Symmetry | None = None
) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """Translation error (the units of the poses) and rotation error in radians.

    The translation error is ``|t_est - t_truth|``: the object origin lies on every
    symmetry axis, so no symmetry moves it. The rotation error is :func:`rotation_error`,
    the smallest over ``symmetry`` when given. Batches ``(...)`` broadcast.
    """
    est, truth = _broadcast(est, truth)
    offset = est.translation() - truth.translation()
    return _norm(offset), rotation_error(est, truth, symmetry)


def _sqrt(sq: Array) -> Array:
    """``sqrt(sq)`` with a zero (not NaN) gradient at 0."""
    live = sq > 0
    return jnp.where(live, jnp.sqrt(jnp.where(live, sq, 1.0)), 0.0)


def _norm(v: Float[Array, "... 3"]) -> Float[Array, "..."]:
    """``|v|`` with a zero (not NaN) gradient at ``v = 0``."""
    return _sqrt(jnp.sum(v * v, axis=-1))


def _relative_points(model_points: ArrayLike, est: SE3, truth: SE3) -> tuple[Array, Array]:
    """Model points ``(N, 3)`` and their images ``(..., N, 3)`` under ``truth^-1 @ est``.

    Distances between ``est``- and ``truth``-moved points equal those between these (a rigid
    motion preserves them), so both metrics work in the object frame.
    """
    points = jnp.asarray(model_points)
    if points.ndim != 2 or points.shape[-1] != 3 or points.shape[0] < 1:
        raise ValueError(f"model_points must be (N, 3) with N >= 1, got {points.shape}")
    delta = truth.inverse() @ est
    points = points.astype(delta.wxyz_xyz.dtype)
    return points, SE3(delta.wxyz_xyz[..., None, :]).apply(points)


def add(
    model_points: Float[ArrayLike, "N 3"],
    est: SE3,
    truth: SE3,
    *,
    symmetry: Symmetry | None = None,
) -> Float[Array, "..."]:
    """ADD: mean over model points of ``|est p - truth p|`` (the units of the points).

    Without ``symmetry`` any rotation of a symmetric object away from the annotated pose
    counts as error; with it, ``est`` is first moved to the branch of ``truth``
    (:func:`canonicalise`), so only error the symmetry cannot explain remains.

    Args:
        model_points: ``(N, 3)`` points on the model, object frame.
        est, truth: ``SE3`` object-to-scene poses, batches ``(...)`` that broadcast.
        symmetry: optional :class:`Symmetry` of the object.

    Returns:
        ``(...)`` mean distances.
    """
    est, truth = _broadcast(est, truth)
    if symmetry is not None:
        est = canonicalise(est, truth, symmetry)
    points, moved = _relative_points(model_points, est, truth)
    return jnp.mean(_norm(moved - points), axis=-1)


def add_s(model_points: Float[ArrayLike, "N 3"], est: SE3, truth: SE3) -> Float[Array, "..."]:
    """ADD-S: mean over model points of the distance from ``est p`` to the nearest
    ``truth q`` (``q`` over all model points).

    Any pose that lays the model surface onto itself scores near zero, whatever symmetry
    causes it, so no :class:`Symmetry` is needed; the price is that it also forgives some
    wrong poses of objects whose parts resemble each other. The distance is to the nearest
    sampled point, so it does not fall below about half the sample spacing for
    rotations that move points between samples.

    Args:
        model_points: ``(N, 3)`` points on the model, object frame; the nearest-point search
            is exact brute force, ``O(N^2)``, in blocks.
        est, truth: ``SE3`` object-to-scene poses, batches ``(...)`` that broadcast.

    Returns:
        ``(...)`` mean distances.
    """
    est, truth = _broadcast(est, truth)
    points, moved = _relative_points(model_points, est, truth)
    flat = moved.reshape(-1, *points.shape)
    sq = jax.vmap(lambda q: knn(q, points, 1)[1][:, 0])(flat)
    return jnp.mean(_sqrt(sq), axis=-1).reshape(moved.shape[:-2])


def diameter(points: Float[ArrayLike, "N 3"]) -> float:
    """The largest distance between two of ``points`` ``(N, 3)`` (in their unit), exact: over
    the vertices of their convex hull, or over every point, in blocks of rows, when the hull
    is flat or degenerate. 0 for fewer than two points. Host numpy (float64), not under
    ``jit``: a model's size, measured once."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) > 8:
        from scipy.spatial import ConvexHull, QhullError  # loaded when first used

        try:
            points = points[ConvexHull(points).vertices]
        except QhullError:  # flat or degenerate: every point is a candidate
            pass
    largest = 0.0
    for start in range(0, len(points), _DIAMETER_BLOCK):
        gaps = points[start : start + _DIAMETER_BLOCK, None] - points[None]
        largest = max(largest, float(np.einsum("ijk,ijk->ij", gaps, gaps).max()))
    return float(np.sqrt(largest))
