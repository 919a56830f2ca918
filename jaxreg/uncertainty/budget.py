"""A pose's error budget: one covariance per source of error, their total, the directions a
symmetry leaves free, and what they say about a grasp.

Every covariance here is of the right perturbation of ``base_T_object``:
``T_true = T_est @ exp(delta)``, ``delta ~ N(0, Sigma)``, tangent ``(vx, vy, vz, wx, wy, wz)``
in the object's axes (metres, radians). The sources are independent, so the total is their sum.

A free direction (a rotation about a continuous symmetry axis, a motion the data cannot
observe) has no finite variance: it is reported as ``inf`` on the diagonal of the tangent
axes it spans, ``0`` off the diagonal in their rows and columns, never NaN; statistics over
the region (coverage, Mahalanobis distances) use the other axes.

Host numpy throughout: the budget is a report, computed once per estimate.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = [
    "SOURCES", "PoseBudget", "lateral_sigma", "mahalanobis", "region_contains",
]

# The sources, in the order reports list them.
SOURCES = ("depth", "fit", "mismatch", "segmentation", "calibration", "ambiguity")

_TRANSLATION = np.array([True, True, True, False, False, False])


def free_axes(free: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """``covariance`` ``(6, 6)`` with the tangent axes ``free`` ``(6,)`` bool made free:
    ``inf`` on their diagonal, ``0`` elsewhere in their rows and columns."""
    covariance = np.array(covariance, dtype=np.float64)
    covariance[free, :] = 0.0
    covariance[:, free] = 0.0
    covariance[free, free] = np.inf
    return covariance


def _psd(matrix: np.ndarray) -> np.ndarray:
    """The positive semi-definite part of a symmetric matrix (negative eigenvalues dropped)."""
    matrix = 0.5 * (matrix + matrix.T)
    values, vectors = np.linalg.eigh(matrix)
    return (vectors * np.clip(values, 0.0, None)) @ vectors.T


def lateral_sigma(covariance: np.ndarray, axis: np.ndarray) -> float:
    """Standard deviation (metres) of the translation error along the unit ``axis`` ``(3,)``
    (object frame, e.g. across a gripper's jaws) under ``covariance`` ``(6, 6)`` (free axes
    ``inf``): ``inf`` if a free axis enters."""
    axis = np.asarray(axis, np.float64)
    block = np.asarray(covariance, np.float64)[:3, :3]
    if np.any(~np.isfinite(np.diag(block)) & (np.abs(axis) > 1e-9)):
        return float("inf")
    return float(np.sqrt(max(axis @ np.where(np.isfinite(block), block, 0.0) @ axis, 0.0)))


def mahalanobis(delta: np.ndarray, covariance: np.ndarray, translation_only: bool = False):
    """Squared Mahalanobis distance of an error ``delta`` ``(6,)`` (right perturbation,
    object axes) under ``covariance`` ``(6, 6)``, over the finite axes (the translation axes
    alone with ``translation_only``), and the number of axes used (its chi-square degrees of
    freedom)."""
    use = np.isfinite(np.diag(covariance))
    if translation_only:
        use &= _TRANSLATION
    block = covariance[np.ix_(use, use)]
    d = np.asarray(delta, np.float64)[use]
    return float(d @ np.linalg.pinv(block, rcond=1e-12, hermitian=True) @ d), int(use.sum())


def region_contains(
    delta: np.ndarray, covariance: np.ndarray, level: float, translation_only: bool = False
) -> bool:
    """Whether ``delta`` lies inside the ``level`` (e.g. 0.95) region of ``N(0, covariance)``
    over the finite axes (chi-square quantile of their count)."""
    from scipy.stats import chi2  # scipy.stats takes ~0.5 s to import: loaded when used

    d2, dof = mahalanobis(delta, covariance, translation_only)
    return bool(dof > 0 and d2 <= chi2.ppf(level, dof))


@dataclasses.dataclass(frozen=True)
class PoseBudget:
    """The error budget of one pose estimate.

    Attributes:
        terms: ``source -> (6, 6)`` covariance of the right perturbation of ``base_T_object``
            (object axes, ``(v, w)``, metres and radians) for each of :data:`SOURCES`: the
            depth noise, the fit (residuals beyond the depth noise, correlated between
            neighbouring points), the mismatch (model and sensor disagreeing over a patch in
            a way the residuals do not show), the segmentation (how the pose moves when the
            segment's membership changes), the calibration (hand-eye, intrinsics, depth scale as
            stated by the user; zero when none is stated) and the ambiguity (equally good
            starts that disagree). Free axes are ``inf`` in every term.
        free: ``(6,)`` bool tangent axes left free (no finite variance).
        free_reason: why they are free (the symmetry's axis, or directions the data cannot
            observe), or ``None``.
        bias: ``(6,)`` known systematic offset of the estimate (object axes) that the
            pipeline could not remove; zero when none is known.
        unknown: ``source -> why`` for each term that could not be computed (a non-finite
            value, no usable re-registration): such a term is ``inf`` on every axis, and so
            is the total: a budget with an unknown term bounds nothing.
    """

    terms: dict[str, np.ndarray]
    free: np.ndarray
    free_reason: str | None
    bias: np.ndarray
    unknown: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def total(self) -> np.ndarray:
        """``(6, 6)`` sum of the terms (they are independent), free axes ``inf``; ``inf`` on
        every axis when a term is :attr:`unknown`."""
        if self.unknown:
            return free_axes(np.ones(6, bool), np.zeros((6, 6)))
        finite = sum(np.where(np.isfinite(c), c, 0.0) for c in self.terms.values())
        return free_axes(self.free, finite)

    def sigmas(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """``source -> (translation sigma (3,) metres, rotation sigma (3,) radians)`` along
        the object's axes, with ``"total"`` last; ``inf`` along free axes."""
        rows = {**self.terms, "total": self.total}
        return {
            name: (np.sqrt(np.diag(c)[:3]), np.sqrt(np.diag(c)[3:]))
            for name, c in ((n, np.clip(c, 0.0, None)) for n, c in rows.items())
        }

    def lateral_sigma(self, axis: np.ndarray) -> float:
        """Standard deviation (metres) of the translation error along the object-frame unit
        ``axis`` ``(3,)`` (e.g. across a gripper's jaws): ``inf`` if a free axis enters."""
        return lateral_sigma(self.total, axis)


def combine(
    terms: dict[str, np.ndarray], free: np.ndarray, free_reason: str | None, bias=None,
    unknown: dict[str, str] | None = None,
) -> PoseBudget:  # fmt: skip
    """A :class:`PoseBudget` from ``(6, 6)`` terms (each made symmetric PSD, free axes set),
    in :data:`SOURCES` order. A term with a non-finite value off the free axes, or named in
    ``unknown`` (``source -> why``) by its caller, is unknown: ``inf`` on every axis, and
    named in the budget's ``unknown`` with the reason."""
    missing = set(SOURCES) - set(terms)
    if missing:
        raise ValueError(f"the budget lacks the terms {sorted(missing)}")
    free = np.asarray(free, bool)
    unknown = dict(unknown or {})
    clean = {}
    for name in SOURCES:
        c = np.asarray(terms[name], np.float64)
        kept = np.ix_(~free, ~free)
        if name not in unknown and not np.all(np.isfinite(c[kept])):
            unknown[name] = "non-finite values"
        if name in unknown:
            clean[name] = free_axes(np.ones(6, bool), np.zeros((6, 6)))
        else:
            clean[name] = free_axes(free, _psd(np.where(np.isfinite(c), c, 0.0)))
    bias = np.zeros(6) if bias is None else np.asarray(bias, np.float64)
    return PoseBudget(clean, free, free_reason, bias, unknown)
