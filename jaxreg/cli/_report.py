"""What the pose commands share (``jaxreg demo``, ``jaxreg pose`` on files, on a YCB-Video
frame and on a BOP image, ``jaxreg demo --track``): the estimate's report (JSON, and printed
stage by stage), its pictures, the errors against a known truth, ``estimate_pose``'s options
read from the command line, and writing it all out (:func:`emit`).

Imported by :mod:`jaxreg.cli.commands` and the modules of its subcommands; imports none of
them.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from jaxreg.core._program_cache import persistent_jit

__all__ = [
    "UNITS", "add_truth_errors", "build_report", "emit", "pose_options", "print_report",
    "stage_progress", "truth_errors", "truth_offset", "write_pictures",
]  # fmt: skip

_TANGENT_AXES = ("vx", "vy", "vz", "wx", "wy", "wz")


# --------------------------------------------------------------------------------------------
# The report.


def _clean(value):
    """JSON-safe: NaN and inf become null, numpy scalars and arrays plain Python."""
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _grasp(prediction, offset=None) -> dict:
    """The report's grasp: a :class:`jaxreg.uncertainty.grasp.GraspPrediction` in mm, and
    with a known error ``offset`` (the true object origin in the estimated object frame,
    ``(3,)`` metres) the chance this frame would have if its error were known."""
    grasp = {
        "gripper_opening_mm": round(prediction.opening * 1e3, 1),
        "object_width_mm": round(prediction.width * 1e3, 1),
        "margin_per_side_mm": round(prediction.margin * 1e3, 2),
        "lateral_sigma_mm": round(prediction.lateral_sigma * 1e3, 3),
        "probability": prediction.probability,
        "axis": prediction.axis.tolist(),
        "equivalent_turns_keeping_the_axis": round(prediction.turn_share, 3),
    }
    if offset is not None and math.isfinite(prediction.probability):
        grasp["measured_lateral_error_mm"] = round(prediction.lateral_error(offset) * 1e3, 3)
        grasp["probability_with_measured_error"] = prediction.probability_with_error(offset)
    return grasp


@persistent_jit
def _pose_matrix(pose):
    """``(4, 4)`` matrix of ``pose``, as one stored program (each eager operation would be a
    program of its own to load)."""
    return pose.as_matrix()


def build_report(estimate, model_points: np.ndarray, opening: float, offset=None) -> dict:
    """The JSON report of a :class:`jaxreg.pipeline.PoseEstimate` whose model is
    ``model_points`` ``(N, 3)``, with the grasp of a parallel gripper of this ``opening``
    (metres; :func:`jaxreg.grasp_prediction`) and, where the true pose is known, the grasp's
    chance with this frame's error ``offset`` (the true object origin in the estimated object
    frame, ``(3,)`` metres) as a bias."""
    from jaxreg.uncertainty.grasp import grasp_prediction

    found = estimate.pose is not None
    report = {
        "pose": None,
        "failed_stage": estimate.failed_stage,
        "reason": estimate.reason,
        "stages": {name: record.as_dict() for name, record in estimate.stages.items()},
        "inlier_rmse_mm": round(estimate.inlier_rmse * 1e3, 3),
        "inlier_fraction": round(estimate.inlier_fraction, 4),
        "predicted_grasp_success": None,
    }
    if found:
        report["pose"] = np.asarray(_pose_matrix(estimate.pose)).tolist()
        sources = {
            name: {
                "translation_sigma_mm": (translation * 1e3).round(4).tolist(),
                "rotation_sigma_deg": np.degrees(rotation).round(4).tolist(),
            }
            for name, (translation, rotation) in estimate.budget.sigmas().items()
        }
        report["error_bars"] = {
            **sources["total"],
            "frame": "object axes (right perturbation of base_T_object), 1 sigma, every source",
        }
        report["error_budget"] = {
            "sources": sources,
            "free_axes": [
                name for name, free in zip(_TANGENT_AXES, estimate.budget.free, strict=True)
                if free
            ],
            "free_reason": estimate.budget.free_reason,
        }
        report["equivalent_poses"] = [turn.as_dict() for turn in estimate.equivalent_poses]
        rotation = np.asarray(estimate.pose.rotation().as_matrix(), np.float64)
        turns = [
            rotation.T @ np.asarray(turn.pose.rotation().as_matrix(), np.float64)
            for turn in estimate.equivalent_poses
        ]
        weights = [turn.weight for turn in estimate.equivalent_poses]
        prediction = grasp_prediction(
            model_points, estimate.budget, opening, turns=turns, turn_weights=weights
        )
        grasp = _grasp(prediction, offset)
        report["grasp"] = grasp
        report["predicted_grasp_success"] = grasp["probability"]
    return _clean(report)


def print_report(report: dict, stages: dict, title: str, out=None) -> None:
    """A readable stage-by-stage report of ``report`` (:func:`build_report`) and the
    estimate's typed stage records ``stages``, to ``out`` (default: ``sys.stdout`` at the
    call, so a redirected stdout receives it)."""

    def line(text=""):
        print(text, file=sys.stdout if out is None else out)

    line(title)
    seg = stages.get("segment")
    if seg is not None and seg.mask_pixels is not None:
        table = (
            "no table under it"
            if seg.plane_inliers is None
            else f"table plane: {seg.plane_inliers} grid points ({seg.plane_inlier_fraction:.0%})"
        )
        line(
            f"  segment  {seg.ms:8.1f} ms  your mask: {seg.mask_pixels} pixels, "
            f"{seg.mask_grid_points} grid points with depth; {table}"
        )
    elif seg is not None:
        line(
            f"  segment  {seg.ms:8.1f} ms  table plane: {seg.plane_inliers} grid points "
            f"({seg.plane_inlier_fraction:.0%}); {len(seg.cluster_sizes)} clusters above it "
            f"(sizes {seg.cluster_sizes})"
        )
    reg = stages.get("register")
    for c in (reg.candidates if reg is not None else None) or []:
        line(
            f"           candidate {c.clusters or 'mask'}: score {c.score:.2f} (model explains "
            f"{c.explained:.0%}, image contradicts {c.contradicted:.0%})"
        )
    lift = stages.get("lift")
    if lift is not None:
        text = f"  lift     {lift.ms:8.1f} ms  {lift.valid_depth_fraction:.0%} valid depth"
        if lift.points is not None:
            text += (
                f", {lift.flying_pixels_removed} flying pixels and "
                f"{lift.isolated_points_removed} isolated points removed -> "
                f"{lift.points} points"
            )
        line(text)
    if reg is not None and reg.refined_starts is not None:
        residual = "none" if reg.inlier_rmse_mm is None else f"{reg.inlier_rmse_mm:.2f} mm"
        line(
            f"  register {reg.ms:8.1f} ms  {reg.starts} starts, best {reg.refined_starts} "
            f"refined: {reg.inlier_fraction:.0%} inliers, residual {residual}; "
            f"{reg.equally_good_starts} equally good starts agree within "
            f"{reg.start_agreement_mm:.1f} mm / {reg.start_agreement_deg:.1f} deg; "
            + (
                "the image judges none of the visible model"
                if reg.model_confirmed is None
                else f"image confirms {reg.model_confirmed:.0%} of the visible model"
            )
        )
    if report["failed_stage"]:
        line(f"  FAILED at {report['failed_stage']}: {report['reason']} (no pose claimed)")
        return
    line(f"  {report['reason']}")
    line("  pose (base_T_object):")
    for row in report["pose"]:
        line("    " + " ".join(f"{v:+.4f}" for v in row))
    if report.get("add_s_mm") is not None:
        line(
            f"  error vs truth: translation {report['translation_error_mm']:.2f} mm, rotation "
            f"{report['rotation_error_deg']:.2f} deg, ADD {report['add_mm']:.2f} mm, ADD-S "
            f"{report['add_s_mm']:.2f} mm"
        )
    budget = report["error_budget"]
    line("  error budget (1 sigma along the object's x y z): translation mm | rotation deg")

    def cells(values):
        return " ".join("  free" if v is None else f"{v:6.2f}" for v in values)

    for name, row in budget["sources"].items():
        line(
            f"    {name:13s}{cells(row['translation_sigma_mm'])} | "
            f"{cells(row['rotation_sigma_deg'])}"
        )
    if budget["free_axes"]:
        line(f"    free ({', '.join(budget['free_axes'])}): {budget['free_reason']}")
    turns = report.get("equivalent_poses") or []
    if turns:
        line(
            f"  depth cannot decide between this pose and {len(turns)} turn(s) of the model "
            "that fit as well (in the ambiguity term):"
        )
        for turn in turns:
            line(
                f"    {turn['angle_deg']:+.0f} deg about {turn['axis']}: weight "
                f"{turn['weight']:.2f}, residual {turn['inlier_rmse_mm']:.2f} mm"
            )
    g = report["grasp"]
    if g["probability"] is not None:
        line(
            f"  grasp: a {g['gripper_opening_mm']:.0f} mm parallel gripper across the "
            f"{g['object_width_mm']:.0f} mm width leaves {g['margin_per_side_mm']:.1f} mm per "
            f"side; lateral sigma {g['lateral_sigma_mm']:.2f} mm (the whole budget) -> "
            f"predicted success {g['probability']:.1%}"
            + (
                f" ({g['equivalent_turns_keeping_the_axis']:.0%} of the equally good turns "
                "keep the jaws' axis)"
                if turns else ""
            )
        )
    if g.get("probability_with_measured_error") is not None:
        line(
            f"  with this frame's measured error along the jaws as a bias "
            f"({g['measured_lateral_error_mm']:.2f} mm) -> "
            f"{g['probability_with_measured_error']:.1%}"
        )


# --------------------------------------------------------------------------------------------
# Pictures.


def _colormap(values: np.ndarray) -> np.ndarray:
    """``(..., 3)`` uint8 colours of values in [0, 1] (dark blue -> teal -> yellow)."""
    anchors = np.array([[48, 18, 59], [33, 145, 140], [94, 201, 98], [253, 231, 37]], float)
    x = np.clip(np.nan_to_num(values), 0, 1) * (len(anchors) - 1)
    i = np.minimum(x.astype(int), len(anchors) - 2)
    t = (x - i)[..., None]
    return ((1 - t) * anchors[i] + t * anchors[i + 1]).astype(np.uint8)


def write_pictures(
    folder: Path, frame, estimate, model_points: np.ndarray, truth=None, report=None
) -> list[str]:
    """depth.png (false colour), segmentation.png (the lifted segment in green) and
    model_overlay.png (:func:`jaxreg.cli._overlay.model_overlay`: the model's visible surface
    at the estimate, or a refused estimate's hypothesis in grey with its reason, and at the
    ``truth`` where it is known) in ``folder``; the last two are drawn on the frame's colour
    image when it has one, else on grey depth. Returns the names."""
    from PIL import Image

    from jaxreg.cli._overlay import model_overlay

    depth = np.asarray(frame.depth)
    valid = np.isfinite(depth)
    lo, hi = np.percentile(depth[valid], (1, 99)) if valid.any() else (0.0, 1.0)
    picture = _colormap(1 - (depth - lo) / max(hi - lo, 1e-6))
    picture[~valid] = 0
    Image.fromarray(picture).save(folder / "depth.png")
    if frame.rgb is not None:
        base = np.asarray(frame.rgb).astype(float)
    else:
        base = np.repeat((0.3 + 0.5 * picture.mean(-1, keepdims=True) / 255) * 255, 3, -1)
    overlay = base.copy()
    overlay[estimate.mask] = 0.45 * overlay[estimate.mask] + 0.55 * np.array([40, 220, 60])
    Image.fromarray(overlay.astype(np.uint8)).save(folder / "segmentation.png")
    drawn = model_overlay(base, frame, estimate, model_points, truth=truth, report=report)
    Image.fromarray(drawn.image).save(folder / "model_overlay.png")
    return ["depth.png", "segmentation.png", "model_overlay.png"]


# --------------------------------------------------------------------------------------------
# Running a pose command.


def stage_progress(quiet: bool):
    """Stage-start callback printing to stderr, with the time since the previous stage."""
    state = {"stage": None, "start": time.perf_counter()}

    def report(stage: str | None) -> None:
        now = time.perf_counter()
        if not quiet and state["stage"] is not None:
            print(f"{now - state['start']:.1f} s", file=sys.stderr, flush=True)
        if not quiet and stage is not None:
            print(f"  {stage} ... ", end="", file=sys.stderr, flush=True)
        state.update(stage=stage, start=now)

    return report


def emit(args, report: dict, title: str, frame, estimate, model_points, truth=None) -> int:
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        report["pictures"] = write_pictures(
            args.out, frame, estimate, model_points, truth=truth, report=report
        )
        (args.out / "report.json").write_text(json.dumps(report, indent=2))
    if args.json:
        print(json.dumps(report))
    else:
        print_report(report, estimate.stages, title)
        if args.out is not None:
            print(f"  wrote report.json and {', '.join(report['pictures'])} to {args.out}")
    if args.view:
        from jaxreg.cli import _view

        sys.stdout.flush()
        scene = _view.view_scene(frame, estimate, model_points, report, truth=truth)
        _view.serve(scene, host=args.view_host, port=args.view_port)
    return 0 if estimate.pose is not None else 1


@persistent_jit
def truth_errors(pose, truth, model_points, symmetry):
    """Translation (m), rotation (rad), ADD and ADD-S (m) errors of ``pose`` against
    ``truth``. ADD counts a turn that ``symmetry`` declares as no error; without one, every
    turn is error."""
    from jaxreg.geometry.metrics import add, add_s, pose_error

    translation, rotation = pose_error(pose, truth, symmetry=symmetry)
    errors = add(model_points, pose, truth, symmetry=symmetry), add_s(model_points, pose, truth)
    return translation, rotation, *errors


def truth_offset(estimate, truth) -> np.ndarray | None:
    """The true object origin in the estimated object frame ``(3,)`` (metres): the error a
    grasp planned on the estimate meets (:func:`build_report`'s ``offset``); ``None``
    without a pose."""
    if estimate.pose is None:
        return None
    return np.asarray((estimate.pose.inverse() @ truth).translation(), np.float64)


def add_truth_errors(report: dict, estimate, truth, model_points, symmetry) -> None:
    """Adds the errors of ``estimate`` against the known ``truth`` (``SE3`` base_T_object) to
    ``report`` (:func:`build_report`): ``translation_error_mm``, ``rotation_error_deg``,
    ``add_mm``, ``add_s_mm`` (None without a pose) and ``truth`` (the ``(4, 4)`` pose)."""
    keys = ("translation_error_mm", "rotation_error_deg", "add_mm", "add_s_mm")
    report.update(dict.fromkeys(keys))
    report["truth"] = np.asarray(truth.as_matrix(), np.float64).tolist()
    if estimate.pose is None:
        return
    t_err, r_err, add_m, add_s_m = truth_errors(estimate.pose, truth, model_points, symmetry)
    errors = (float(t_err) * 1e3, float(np.degrees(r_err)), float(add_m) * 1e3, add_s_m * 1e3)
    report.update({key: round(float(value), 3) for key, value in zip(keys, errors, strict=True)})


UNITS = {"m": 1.0, "cm": 0.01, "mm": 0.001}  # metres per model unit


def _symmetry(spec: str | None):
    """The :class:`jaxreg.Symmetry` named by ``--symmetry`` (axes of the model's own frame,
    through its origin), or ``None``."""
    from jaxreg.geometry.metrics import Symmetry

    if spec is None or spec == "none":
        return None
    half = {a: np.diag([1.0 if i == a else -1.0 for i in range(3)]) for a in range(3)}
    z = np.array([0.0, 0.0, 1.0])
    if spec == "box":
        return Symmetry(np.stack([np.eye(3), half[0], half[1], half[2]]))
    if spec == "cylinder":
        return Symmetry(np.stack([np.eye(3), half[0]]), axis=z)
    if spec == "revolution":
        return Symmetry(np.eye(3)[None], axis=z)
    if spec.startswith("turns:") and spec[6:].isdigit() and int(spec[6:]) >= 1:
        angles = 2 * np.pi * np.arange(int(spec[6:])) / int(spec[6:])
        c, s = np.cos(angles), np.sin(angles)
        zero, one = np.zeros_like(c), np.ones_like(c)
        turns = np.stack([c, -s, zero, s, c, zero, zero, zero, one], -1).reshape(-1, 3, 3)
        return Symmetry(turns)
    raise ValueError(
        f"unknown --symmetry {spec!r}: choose none, box, cylinder, revolution or turns:N"
    )


def pose_options(args, frame) -> dict:
    """``estimate_pose``'s options from ``jaxreg pose``'s arguments."""
    from jaxreg.io import read_mask
    from jaxreg.uncertainty import DepthNoise

    options = {"symmetry": _symmetry(args.symmetry)}
    if args.depth_noise is not None:
        options["depth_noise"] = DepthNoise(tuple(args.depth_noise), frame.base_T_camera)
    if args.mask is not None:
        options["mask"] = read_mask(args.mask)
    if args.pixel is not None:
        options["pixel"] = tuple(args.pixel)
    if args.box is not None:
        options["box"] = tuple(args.box)
    if args.model_color is not None:
        if not all(0 <= c <= 255 for c in args.model_color):
            raise ValueError(f"--model-color takes sRGB counts 0-255, got {args.model_color}")
        options["model_colors"] = np.asarray(args.model_color) / 255.0
    if args.hand_eye_sigma is not None:
        metres, degrees = args.hand_eye_sigma[0] * 1e-3, np.radians(args.hand_eye_sigma[1])
        options["hand_eye_covariance"] = np.diag([metres**2] * 3 + [degrees**2] * 3)
    options["depth_scale_sigma"] = args.depth_scale_sigma
    return options
