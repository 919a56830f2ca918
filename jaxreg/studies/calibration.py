"""Can the error bars be trusted? Render frames of a model with a sensor model, estimate each
pose, and compare the reported uncertainty with the real error.

:func:`calibration_study` reports, per object and overall, the coverage of the 50/90/95%
regions of the reported covariance (the fraction of frames whose true pose lies inside, over
the 6-dof pose and the translation alone: a calibrated covariance covers about the nominal
fraction), their sharpness (the predicted translation sigma ``sqrt(trace Sigma_t)`` over the
actual translation error: bars that are uselessly wide cover everything), and the grasp chance
predicted from the budget against the observed success rate of a parallel-jaw grasp across the
model's narrowest axis at several margins.

Errors are right perturbations of the estimate, ``truth = est @ exp(delta)`` (object axes,
``(v, w)``), with the truth moved to the estimate's symmetry branch; free axes (a continuous
symmetry's rotation) are left out of the regions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import numpy as np
from scipy.stats import chi2

from jaxreg.geometry.metrics import canonicalise
from jaxreg.pipeline import estimate_pose
from jaxreg.synth import OBJECTS, StereoSensor, surface_samples, tabletop_scene
from jaxreg.uncertainty.budget import mahalanobis
from jaxreg.uncertainty.grasp import grasp_axis, grasp_success_probability

__all__ = ["CalibrationStudy", "FrameOutcome", "calibration_study"]

LEVELS = (0.5, 0.9, 0.95)


@dataclasses.dataclass(frozen=True)
class FrameOutcome:
    """One frame of the study (host values; NaN where the pipeline made no pose claim).

    Attributes:
        object: the object's name; ``seed`` the scene's seed.
        found: whether a pose was claimed; ``failed_stage`` otherwise.
        delta: ``(6,)`` the true error, right perturbation of the estimate (object axes).
        covariance: ``(6, 6)`` the reported total.
        sigmas: ``source -> (6,)`` per-axis sigma of each budget term and ``"total"``.
        terms: ``source -> (6, 6)`` the budget's terms.
        d2, dof: squared Mahalanobis distance of ``delta`` and its degrees of freedom over
            the 6-dof pose; ``d2_translation``, ``dof_translation`` over the translation.
        predicted_sigma: ``sqrt(trace)`` of the translation block (metres).
        error: ``|delta_v|`` the translation error (metres).
        lateral_sigma: sigma (metres) along ``axis``, the grasp's jaw axis (object frame);
            ``lateral_error`` the error along it.
    """

    object: str
    seed: int
    found: bool
    failed_stage: str | None
    delta: np.ndarray
    covariance: np.ndarray
    sigmas: dict[str, np.ndarray]
    terms: dict[str, np.ndarray]
    d2: float
    dof: int
    d2_translation: float
    dof_translation: int
    predicted_sigma: float
    error: float
    axis: np.ndarray
    lateral_sigma: float
    lateral_error: float


@dataclasses.dataclass(frozen=True)
class CalibrationStudy:
    """The frames and their summary.

    Attributes:
        frames: every :class:`FrameOutcome`.
        margins: ``(G,)`` grasp margins per side (metres) of the grasp comparison.
    """

    frames: list[FrameOutcome]
    margins: np.ndarray

    def found(self, object: str | None = None) -> list[FrameOutcome]:
        """The frames with a pose (of ``object``, or all)."""
        return [f for f in self.frames if f.found and object in (None, f.object)]

    def coverage(self, level: float, object: str | None = None, translation=False) -> float:
        """Fraction of found frames whose truth lies inside the ``level`` region."""
        rows = self.found(object)
        inside = [
            (f.d2_translation if translation else f.d2)
            <= chi2.ppf(level, f.dof_translation if translation else f.dof)
            for f in rows
        ]
        return float(np.mean(inside)) if rows else float("nan")

    def sharpness(self, object: str | None = None) -> float:
        """Median predicted translation sigma over the median translation error."""
        rows = self.found(object)
        if not rows:
            return float("nan")
        return float(
            np.median([f.predicted_sigma for f in rows]) / np.median([f.error for f in rows])
        )

    def grasp(self, object: str | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(G,)`` mean predicted grasp chance and ``(G,)`` observed success rate at each
        margin: success when the error along the jaws is inside the margin."""
        rows = self.found(object)
        sigma = np.array([f.lateral_sigma for f in rows])[:, None]
        error = np.abs(np.array([f.lateral_error for f in rows]))[:, None]
        margin = self.margins[None, :]
        predicted = np.asarray(grasp_success_probability(sigma, 0.0, margin), np.float64)
        return predicted.mean(0), (error < margin).mean(0)

    def table(self) -> str:
        """A markdown table per object and overall: frames, coverage (6-dof and translation)
        at 50/90/95%, sharpness, median error and sigma, grasp predicted vs observed at the
        2 mm margin (when among the margins)."""
        names = sorted({f.object for f in self.frames}) + [None]
        head = (
            "| object | found | 6-dof 50/90/95% | translation 50/90/95% | median error mm "
            "| median sigma mm | sharpness | grasp 2 mm predicted / observed |\n"
            "|---|---|---|---|---|---|---|---|\n"
        )
        lines = []
        two = np.flatnonzero(np.isclose(self.margins, 0.002))
        for name in names:
            rows = self.found(name)
            total = [f for f in self.frames if name in (None, f.object)]
            six = "/".join(f"{self.coverage(lv, name):.0%}" for lv in LEVELS)
            tra = "/".join(f"{self.coverage(lv, name, True):.0%}" for lv in LEVELS)
            grasp = "-"
            if rows and len(two):
                p, o = self.grasp(name)
                grasp = f"{p[two[0]]:.2f} / {o[two[0]]:.2f}"
            err = np.median([f.error for f in rows]) * 1e3 if rows else np.nan
            sig = np.median([f.predicted_sigma for f in rows]) * 1e3 if rows else np.nan
            lines.append(
                f"| {name or 'all'} | {len(rows)}/{len(total)} | {six} | {tra} | {err:.2f} "
                f"| {sig:.2f} | {self.sharpness(name):.2f} | {grasp} |"
            )
        return head + "\n".join(lines)


def _outcome(name, seed, scene, estimate) -> FrameOutcome:
    axis = grasp_axis(scene.model_points)
    if estimate.pose is None:
        nan6 = np.full(6, np.nan)
        return FrameOutcome(
            name, seed, False, estimate.failed_stage, nan6, np.full((6, 6), np.nan), {}, {},
            np.nan, 0, np.nan, 0, np.nan, np.nan, axis, np.nan, np.nan,
        )  # fmt: skip
    truth = canonicalise(scene.truth, estimate.pose, scene.symmetry)
    delta = np.asarray((estimate.pose.inverse() @ truth).log(), np.float64)
    cov = np.asarray(estimate.covariance, np.float64)
    d2, dof = mahalanobis(delta, cov)
    d2t, doft = mahalanobis(delta, cov, translation_only=True)
    sigmas = {
        name: np.sqrt(np.clip(np.diag(c), 0.0, None))
        for name, c in {**estimate.budget.terms, "total": cov}.items()
    }
    block = np.where(np.isfinite(cov[:3, :3]), cov[:3, :3], np.inf)
    return FrameOutcome(
        name, seed, True, None, delta, cov, sigmas, dict(estimate.budget.terms), d2, dof, d2t,
        doft,
        float(np.sqrt(np.trace(block))), float(np.linalg.norm(delta[:3])), axis,
        estimate.budget.lateral_sigma(axis), float(delta[:3] @ axis),
    )  # fmt: skip


def calibration_study(
    objects: Sequence[str] = OBJECTS,
    seeds: Sequence[int] = range(1000, 1006),
    *,
    sensor: StereoSensor | None = None,
    margins: Sequence[float] = (0.001, 0.002, 0.003, 0.004, 0.005),
    model_samples: int = 20_000,
    scene_options: dict | None = None,
    estimate_options: dict | None = None,
    progress: Callable[[FrameOutcome], object] | None = None,
) -> CalibrationStudy:
    """Render, estimate and compare, frame by frame.

    Args:
        objects: object names (``jaxreg.synth.OBJECTS``) or ``(name, mesh, symmetry)``
            triples for a user's own model (a ``trimesh.Trimesh`` in metres, standing on its
            lowest face, with its ``Symmetry``).
        seeds: scene seeds (each object is rendered at every seed).
        sensor: the depth camera (default ``StereoSensor.d435()``); its noise model is
            passed to :func:`~jaxreg.estimate_pose` as ``depth_noise``.
        margins: grasp margins per side (metres) of the grasp comparison.
        model_samples: points sampled on each object's mesh, once, with the faces' normals:
            its model for every frame.
        scene_options: extra keyword arguments of :func:`~jaxreg.synth.tabletop_scene`.
        estimate_options: extra keyword arguments of :func:`~jaxreg.estimate_pose`.
        progress: called with each frame's outcome as it is done.

    Returns:
        :class:`CalibrationStudy`.
    """
    sensor = StereoSensor.d435() if sensor is None else sensor
    frames = []
    for spec in objects:
        name, mesh, symmetry = (spec, None, None) if isinstance(spec, str) else spec
        model_points = model_normals = None  # one model per object, as a user keeps one
        for seed in seeds:
            options = dict(scene_options or {})
            if mesh is not None:
                options.update(mesh=mesh, symmetry=symmetry)
            scene = tabletop_scene(int(seed), object=name, sensor=sensor, **options)
            if model_points is None:
                model_points, model_normals = surface_samples(scene.model, model_samples)
            noise = sensor.depth_noise(scene.frame.intrinsics)
            estimate = estimate_pose(
                scene.frame, model_points, model_normals=model_normals,
                symmetry=scene.symmetry, depth_noise=noise,
                **(estimate_options or {}),
            )  # fmt: skip
            outcome = _outcome(name, int(seed), scene, estimate)
            frames.append(outcome)
            if progress is not None:
                progress(outcome)
    return CalibrationStudy(frames, np.asarray(margins, np.float64))
