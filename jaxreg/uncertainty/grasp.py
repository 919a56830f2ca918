"""A parallel-jaw grasp and its chance of success under a pose's error.

The jaws close across the model's narrowest principal axis (:func:`grasp_axis`). The grasp
holds when the pose error across the jaws stays inside the mechanical margin per side
(:func:`grasp_margin`); with that error Gaussian, :func:`grasp_success_probability` gives the
chance. :func:`grasp_prediction` puts the three together for one estimate: the axis, the
model's width along it, the margin, the lateral sigma that a covariance (or a whole
:class:`~jaxreg.uncertainty.budget.PoseBudget`) gives along the axis, and the predicted success;
:meth:`GraspPrediction.probability_with_error` adds a known error as a bias.

Lengths in metres unless a function says "units as given"; the object frame is the model's
own; covariances are of the right perturbation ``T_true = T_est @ exp(delta)``, tangent
``(vx, vy, vz, wx, wy, wz)`` in the object's axes.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxreg.core._program_cache import persistent_jit
from jaxreg.uncertainty.budget import PoseBudget, lateral_sigma

__all__ = [
    "GraspPrediction",
    "grasp_axis",
    "grasp_margin",
    "grasp_prediction",
    "grasp_success_probability",
]


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


def grasp_axis(model_points: Float[ArrayLike, "N 3"]) -> np.ndarray:
    """``(3,)`` unit vector, the model's narrowest principal axis (object frame): where a
    parallel-jaw gripper closes. Its sign is the eigensolver's (either is the same grasp).
    Host numpy (float64)."""
    points = np.asarray(model_points, np.float64)
    _, vectors = np.linalg.eigh(np.cov((points - points.mean(0)).T))
    return vectors[:, 0]


@persistent_jit
def _margin_and_probability(opening, width, friction_allowance, sigma, bias):
    """:func:`grasp_margin` and :func:`grasp_success_probability` as one stored program."""
    margin = grasp_margin(opening, width, friction_allowance)
    return margin, grasp_success_probability(sigma, bias, margin)


def _chance(opening, width, friction_allowance, sigma, bias) -> tuple[float, float]:
    """The margin and the probability of :func:`_margin_and_probability` in float32 (host
    floats); the probability is NaN when ``sigma`` is ``inf``."""
    numbers = np.float32([opening, width, friction_allowance, sigma, bias])
    margin, probability = _margin_and_probability(*numbers)
    return float(margin), float(probability) if np.isfinite(sigma) else float("nan")


@dataclasses.dataclass(frozen=True)
class GraspPrediction:
    """A parallel-jaw grasp across a model's narrowest principal axis, and its predicted
    success (:func:`grasp_prediction`). Host values, metres.

    Attributes:
        axis: ``(3,)`` unit jaw axis in the object frame (:func:`grasp_axis`).
        opening: the gripper's opening.
        friction_allowance: the part of the margin a closing jaw needs (:func:`grasp_margin`).
        width: the model's extent along ``axis``.
        margin: clearance per side, ``(opening - width) / 2 - friction_allowance`` (float32
            arithmetic); negative when the model does not fit between the jaws.
        lateral_sigma: standard deviation of the translation error along ``axis``; ``inf``
            when a free (unobservable) axis enters.
        probability: :func:`grasp_success_probability` with ``lateral_sigma`` and no bias
            (float32 arithmetic), times ``turn_share``; NaN when ``lateral_sigma`` is ``inf``
            (unknown).
        turn_share: the share of the weight of the pose and its equivalent turns (poses that
            fit as well) under which the jaws still close across the same axis: a turn that
            maps the axis onto itself (or its reverse) leaves the grasp as it is, any other
            puts the jaws across another extent of the object. 1 without turns.
    """

    axis: np.ndarray
    opening: float
    friction_allowance: float
    width: float
    margin: float
    lateral_sigma: float
    probability: float
    turn_share: float = 1.0

    def lateral_error(self, offset: Float[ArrayLike, " 3"]) -> float:
        """``|axis . offset|``: the part across the jaws of a known translation error
        ``offset`` ``(3,)`` (metres, object frame, e.g. the true object origin in the
        estimated object frame)."""
        offset = np.asarray(offset, np.float64)
        if offset.shape != (3,):
            raise ValueError(f"offset must have shape (3,), got {offset.shape}")
        return abs(float(self.axis @ offset))

    def probability_with_error(self, offset: Float[ArrayLike, " 3"]) -> float:
        """The chance of the grasp if its known error ``offset`` ``(3,)`` (metres, object
        frame) were added as a bias (:meth:`lateral_error`) to the same ``lateral_sigma``;
        NaN when ``lateral_sigma`` is ``inf``."""
        bias = self.lateral_error(offset)
        numbers = self.opening, self.width, self.friction_allowance, self.lateral_sigma, bias
        return _chance(*numbers)[1] * self.turn_share


def grasp_prediction(
    model_points: Float[ArrayLike, "N 3"],
    covariance: PoseBudget | Float[ArrayLike, "6 6"],
    opening: float,
    friction_allowance: float = 0.0,
    turns: Float[ArrayLike, "K 3 3"] | None = None,
    turn_weights: Float[ArrayLike, " K"] | None = None,
) -> GraspPrediction:
    """A parallel-jaw grasp across the model's narrowest principal axis and its predicted
    success under a pose's error (host-side, once per estimate).

    Args:
        model_points: ``(N, 3)`` the model in its own frame (metres), ``N >= 3``.
        covariance: ``(6, 6)`` covariance of the pose's right perturbation (object axes,
            ``(v, w)``, metres and radians; free axes ``inf``), or a
            :class:`~jaxreg.uncertainty.budget.PoseBudget`, whose total is used.
        opening: the gripper's opening (metres), > 0.
        friction_allowance: the part of the margin per side a closing jaw needs (metres).
        turns: ``(K, 3, 3)`` rotations (object frame, relative to the pose: ``R_pose^T
            R_turned``) of poses that fit as well as this one (``PoseEstimate.
            equivalent_poses``), and ``turn_weights`` ``(K,)`` their weights against the
            pose's 1 (default 1 each): the grasp holds under a turn that keeps the jaw axis
            (within 10 degrees, either sign), fails under any other.

    Returns:
        A :class:`GraspPrediction`: the jaw axis, the model's width along it, the margin per
        side, the lateral sigma along the axis (the translation block of the covariance) and
        the probability that the error across the jaws stays inside the margin.

    Raises:
        ValueError: ``model_points`` not ``(N, 3)`` with ``N >= 3`` finite rows, a covariance
            not ``(6, 6)``, or an opening that is not a positive number.
    """
    points = np.asarray(model_points)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 3:
        raise ValueError(f"model_points must have shape (N, 3), N >= 3, got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("model_points holds non-finite values")
    total = covariance.total if isinstance(covariance, PoseBudget) else covariance
    total = np.asarray(total, np.float64)
    if total.shape != (6, 6):
        raise ValueError(f"covariance must have shape (6, 6), got {total.shape}")
    if not (np.isfinite(opening) and opening > 0):
        raise ValueError(f"opening must be a positive length in metres, got {opening}")
    axis = grasp_axis(points)
    along = (points - points.mean(0)) @ axis
    width = float(along.max() - along.min())
    sigma = lateral_sigma(total, axis)
    opening, friction_allowance = float(opening), float(friction_allowance)
    margin, probability = _chance(opening, width, friction_allowance, sigma, 0.0)
    share = _turn_share(axis, turns, turn_weights)
    return GraspPrediction(
        axis, opening, friction_allowance, width, margin, sigma, probability * share, share
    )


def _turn_share(axis: np.ndarray, turns, weights) -> float:
    """The weight share (the pose's own 1 included) of ``turns`` ``(K, 3, 3)`` that keep
    ``axis`` ``(3,)`` within 10 degrees, either sign (see :func:`grasp_prediction`)."""
    if turns is None or len(turns) == 0:
        return 1.0
    turns = np.asarray(turns, np.float64).reshape(-1, 3, 3)
    weights = np.ones(len(turns)) if weights is None else np.asarray(weights, np.float64)
    if weights.shape != (len(turns),) or np.any(~np.isfinite(weights)) or np.any(weights < 0):
        raise ValueError(
            f"turn_weights must be {len(turns)} non-negative weights, got {np.shape(weights)}"
        )
    kept = np.abs((turns @ axis) @ axis) >= np.cos(np.radians(10.0))
    return float((1.0 + weights[kept].sum()) / (1.0 + weights.sum()))
