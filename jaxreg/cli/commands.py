"""Command line: ``jaxreg demo | pose | basin | bop | convert-ycbv`` (``python -m jaxreg`` is
the same).

* ``jaxreg demo [--out DIR] [--json] [--seed N] [--object NAME]`` renders a synthetic tabletop
  frame (:func:`jaxreg.synth.tabletop_scene`), estimates the object's pose
  (:func:`jaxreg.estimate_pose`), and reports each stage, the error against the known pose,
  the pose's error bars and the predicted success of a parallel-jaw grasp.
* ``jaxreg pose --scene FILE --model FILE [--intrinsics FILE] [--json] [--out DIR]`` does the
  same on your data: an organized PCD, or a 16-bit depth PNG with its intrinsics JSON
  (:func:`jaxreg.io.read_frame`), and a model as points (PCD, PLY) or a mesh (OBJ, STL, PLY),
  in metres unless ``--model-units mm|cm`` says otherwise; ``--rgb FILE`` the colour image
  registered to the depth (the pictures are drawn on it; with ``--model-color R G B``, the
  object's paint, or ``--model-colors``, the model file's own, clusters of other colours are
  no candidates). ``--mask PNG`` (nonzero = the
  object, from your own segmenter), ``--pixel U V`` or ``--box U0 V0 U1 V1`` name the object;
  ``--symmetry`` and ``--depth-noise`` describe the model and the camera (see ``--help``).
* ``jaxreg pose --ycbv PREFIX --object NAME_OR_INDEX`` does it on a YCB-Video frame, with the
  dataset's model and label mask, and reports the errors against its truth
  (:mod:`jaxreg.cli._ycbv`).

With ``--json`` stdout is one JSON object (the fields of the design's command line section);
``--out DIR`` also writes ``report.json`` and the pictures ``depth.png``,
``segmentation.png`` (the lifted segment over the image) and ``model_overlay.png`` (the model
drawn at the estimated pose) to DIR, over the colour image when the frame has one.
``--view`` then serves the scene in 3D to a browser (:mod:`jaxreg.cli._view`) at
``--view-port`` until Ctrl-C.

Exit status: 0 when a pose is found; 1 when the evidence says the object is not there (the
report, or the JSON, is still printed, with the failed stage and its reason); 2 on bad input
(a malformed or missing file, an argument out of range, a missing optional package: one line on
stderr, no traceback); 3 on an internal error (a bug in jaxreg, not the input: the traceback,
then a line saying so).

Compilation cache: the commands (never ``import jaxreg``) call
:func:`jaxreg.enable_compilation_cache`: JAX's persistent compilation cache, and the compiled
programs beside it (:mod:`jaxreg.core._program_cache`), so a second run neither traces, lowers
nor compiles them again. It lives in ``$JAXREG_CACHE_DIR`` if set, else
``$XDG_CACHE_HOME/jaxreg/jax`` (``~/.cache/jaxreg/jax``), programs in its ``programs`` folder;
set ``JAXREG_CACHE_DIR=""`` to turn both off. Deleting the folder is always safe.

Subcommands are added by functions taking the subparsers object (``_add_demo``,
``_add_pose``, ``jaxreg basin``'s ``add_basin_parser`` from :mod:`jaxreg.cli._basin` and
``jaxreg bop``'s ``add_bop_parser`` and ``jaxreg convert-ycbv``'s ``add_convert_ycbv_parser``
from :mod:`jaxreg.cli._bop`); each sets ``run`` to a
function of the parsed arguments returning the exit status.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from jaxreg.cli._basin import add_basin_parser, run_basin
from jaxreg.cli._bop import (
    add_bop_parser,
    add_convert_ycbv_parser,
    run_bop_command,
    run_convert_ycbv,
)
from jaxreg.core._program_cache import persistent_jit
from jaxreg.core.compilation import enable_compilation_cache

GRIPPER_OPENING = 0.085  # metres: a Robotiq 2F-85-class parallel-jaw gripper
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


def print_report(report: dict, stages: dict, title: str, out=sys.stdout) -> None:
    """A readable stage-by-stage report of ``report`` (:func:`build_report`) and the
    estimate's typed stage records ``stages``."""

    def line(text=""):
        print(text, file=out)

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


def write_pictures(folder: Path, frame, estimate, model_points: np.ndarray) -> list[str]:
    """depth.png (false colour), segmentation.png (the lifted segment in green) and
    model_overlay.png (every fourth model point at the estimated pose in red) in ``folder``;
    the last two are drawn on the frame's colour image when it has one, else on grey depth.
    Returns the names."""
    from PIL import Image

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
    drawn = base.copy()
    if estimate.pose is not None:
        import jax.numpy as jnp

        camera_T_object = frame.base_T_camera.inverse() @ estimate.pose
        cam = np.asarray(camera_T_object @ jnp.asarray(model_points[::4]))
        pix = np.asarray(frame.intrinsics.project(jnp.asarray(cam)))
        u, v = np.round(pix[:, 0]).astype(int), np.round(pix[:, 1]).astype(int)
        h, w = depth.shape
        keep = (cam[:, 2] > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        drawn[v[keep], u[keep]] = (255, 40, 40)
    Image.fromarray(drawn.astype(np.uint8)).save(folder / "model_overlay.png")
    return ["depth.png", "segmentation.png", "model_overlay.png"]


# --------------------------------------------------------------------------------------------
# Commands.


def _progress(quiet: bool):
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


def _emit(args, report: dict, title: str, frame, estimate, model_points, truth=None) -> int:
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        report["pictures"] = write_pictures(args.out, frame, estimate, model_points)
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
def _truth_errors(pose, truth, model_points, symmetry):
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
    t_err, r_err, add_m, add_s_m = _truth_errors(estimate.pose, truth, model_points, symmetry)
    errors = (float(t_err) * 1e3, float(np.degrees(r_err)), float(add_m) * 1e3, add_s_m * 1e3)
    report.update({key: round(float(value), 3) for key, value in zip(keys, errors, strict=True)})


def run_demo(args) -> int:
    from jaxreg.pipeline.estimate import estimate_pose
    from jaxreg.synth import OBJECTS, StereoSensor, surface_samples, tabletop_scene

    if args.object not in OBJECTS:
        raise ValueError(f"unknown object {args.object!r}: choose one of {', '.join(OBJECTS)}")
    if args.track is not None:
        from jaxreg.cli._track import run_demo_track

        return run_demo_track(args)
    progress = _progress(args.json)
    if not args.json:
        print(
            f"jaxreg demo: seed {args.seed}, a {args.object} on a table with 2 distractors, "
            "848x480 depth with a RealSense D435's noise (the first run compiles: ~1 min; "
            "later runs use the compilation cache)",
            file=sys.stderr,
        )
    progress("render")
    scene = tabletop_scene(args.seed, object=args.object)
    model, normals = surface_samples(scene.model)
    symmetry = scene.symmetry
    noise = StereoSensor.d435().depth_noise(scene.frame.intrinsics)
    estimate = estimate_pose(
        scene.frame, model, model_normals=normals, symmetry=symmetry, depth_noise=noise,
        progress=progress,
    )  # fmt: skip
    progress(None)
    report = build_report(
        estimate, model, args.gripper_opening, truth_offset(estimate, scene.truth)
    )
    add_truth_errors(report, estimate, scene.truth, scene.model_points, symmetry)
    report["scene"] = {"seed": args.seed, "object": args.object, "distractors": 2}
    title = f"jaxreg demo: a {args.object} (seed {args.seed})"
    return _emit(args, report, title, scene.frame, estimate, model, truth=scene.truth)


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


def _pose_options(args, frame) -> dict:
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


def run_pose(args) -> int:
    from jaxreg.io import load_points, read_frame
    from jaxreg.pipeline.estimate import estimate_pose

    if args.ycbv is not None:
        from jaxreg.cli._ycbv import run_pose_ycbv

        if args.model_colors:
            raise ValueError(
                "--model-colors reads the --model file's colours; YCB-Video's point models "
                "have none (give one paint with --model-color R G B)"
            )
        return run_pose_ycbv(args)
    for name in ("object", "no_mask"):
        if getattr(args, name):
            raise ValueError(f"--{name.replace('_', '-')} is for --ycbv frames")
    if args.model is None:
        raise ValueError("--scene needs --model FILE (the object's points or mesh)")
    frame = read_frame(args.scene, args.intrinsics, rgb=args.rgb)
    if args.model_colors and args.model_color is not None:
        raise ValueError("give --model-color R G B or --model-colors, not both")
    loaded = load_points(args.model, n_points=None, with_colors=args.model_colors)
    model, colors = loaded if args.model_colors else (loaded, None)
    model = np.asarray(model, np.float32) * np.float32(UNITS[args.model_units])
    if len(model) < 10:
        raise ValueError(f"{args.model}: the model has {len(model)} points; give a surface")
    options = _pose_options(args, frame)
    if colors is not None:
        options["model_colors"] = colors
    progress = _progress(args.json)
    estimate = estimate_pose(frame, model, progress=progress, **options)
    progress(None)
    report = build_report(estimate, model, args.gripper_opening)
    report["scene"] = str(args.scene)
    report["model"] = str(args.model)
    return _emit(
        args, report, f"jaxreg pose: {args.model} in {args.scene}", frame, estimate, model
    )


def _common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, help="write report.json and pictures to DIR")
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    parser.add_argument(
        "--gripper-opening", type=float, default=GRIPPER_OPENING, metavar="M",
        help=f"parallel gripper opening in metres (default {GRIPPER_OPENING})",
    )  # fmt: skip
    parser.add_argument("--view", action="store_true", help="serve a 3D view until Ctrl-C")
    parser.add_argument("--view-port", type=int, default=8080, help="its port (default 8080)")
    parser.add_argument(
        "--view-host", default="127.0.0.1", help="its address (default 127.0.0.1; 0.0.0.0: all)"
    )


def _add_demo(sub) -> None:
    demo = sub.add_parser("demo", help="estimate a pose in a synthetic scene whose truth is known")
    demo.add_argument("--seed", type=int, default=0, help="the scene (default 0)")
    demo.add_argument("--object", default="mug", help="box, mug, cylinder or container")
    demo.add_argument(
        "--track", type=int, metavar="N",
        help="N frames of the object pushed across the table: found in the first, tracked after",
    )  # fmt: skip
    _common(demo)
    demo.set_defaults(run=run_demo)


def _add_pose(sub) -> None:
    pose = sub.add_parser("pose", help="estimate a model's pose in your depth frame")
    frame = pose.add_mutually_exclusive_group(required=True)
    frame.add_argument("--scene", type=Path, help="organized PCD or depth PNG")
    frame.add_argument(
        "--ycbv", type=Path, metavar="PREFIX",
        help="a YCB-Video frame (e.g. data/0000/000001): its depth, colour, the model of "
        "--object, the label's mask, and the errors against its truth",
    )  # fmt: skip
    pose.add_argument(
        "--object", metavar="NAME_OR_INDEX",
        help="with --ycbv: the object, by model name (025_mug) or class index (14)",
    )  # fmt: skip
    pose.add_argument("--model", type=Path, help="model points or mesh (with --scene)")
    pose.add_argument(
        "--model-units", choices=tuple(UNITS), default="m",
        help="the model file's units (default m; CAD files are often mm)",
    )  # fmt: skip
    pose.add_argument("--intrinsics", type=Path, help="intrinsics JSON of a depth PNG")
    pose.add_argument(
        "--rgb", type=Path,
        help="colour image registered to the depth (same size): the pictures of --out are "
        "drawn on it",
    )  # fmt: skip
    pose.add_argument(
        "--model-colors", action="store_true",
        help="with --rgb: the model file's own colours (a PLY's or PCD's vertex colours, a "
        "mesh's vertex colours or texture) set aside clusters of other colours",
    )  # fmt: skip
    pose.add_argument(
        "--model-color", type=float, nargs=3, metavar=("R", "G", "B"),
        help="the object's paint as sRGB counts 0-255: with --rgb, clusters whose pixels show "
        "other colours are no candidates (a look-alike of another colour)",
    )  # fmt: skip
    which = pose.add_mutually_exclusive_group()
    which.add_argument("--mask", type=Path, help="PNG of the object's pixels (nonzero = object)")
    which.add_argument("--pixel", type=float, nargs=2, metavar=("U", "V"), help="a pixel on it")
    which.add_argument(
        "--box", type=float, nargs=4, metavar=("U0", "V0", "U1", "V1"), help="a box around it"
    )
    which.add_argument(
        "--no-mask", action="store_true",
        help="with --ycbv: find the object by the table route, not the label's mask",
    )  # fmt: skip
    pose.add_argument(
        "--symmetry", default="none",
        help="the model's symmetry about its own axes through its origin: none (default), box "
        "(half turns about x, y, z), cylinder (any turn about z, half turn about x), "
        "revolution (any turn about z), turns:N (N equal turns about z)",
    )  # fmt: skip
    pose.add_argument(
        "--depth-noise", type=float, nargs=3, metavar=("A", "B", "C"),
        help="the camera's depth sigma in metres, A + B z + C z^2 (default 0 0 0.0025)",
    )  # fmt: skip
    pose.add_argument(
        "--hand-eye-sigma", type=float, nargs=2, metavar=("MM", "DEG"),
        help="the hand-eye calibration's uncertainty: translation (mm) and rotation (degrees) "
        "sigma per axis, propagated into the error budget",
    )  # fmt: skip
    pose.add_argument(
        "--depth-scale-sigma", type=float, default=0.0, metavar="REL",
        help="relative sigma of the depth scale (0.01 = 1%%), propagated into the budget",
    )  # fmt: skip
    _common(pose)
    pose.set_defaults(run=run_pose)


def build_parser() -> tuple[argparse.ArgumentParser, argparse._SubParsersAction]:
    """The parser and its subparsers (a further command adds itself to the latter)."""
    parser = argparse.ArgumentParser(
        prog="jaxreg",
        description="jaxreg command line",
        epilog="The compilation cache lives in $JAXREG_CACHE_DIR (default ~/.cache/jaxreg/jax; "
        "empty to disable).",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    _add_demo(sub)
    _add_pose(sub)
    add_basin_parser(sub).set_defaults(run=run_basin)
    add_bop_parser(sub).set_defaults(run=run_bop_command)
    add_convert_ycbv_parser(sub).set_defaults(run=run_convert_ycbv)
    return parser, sub


def main(argv: list[str] | None = None) -> int:
    parser, _ = build_parser()
    args = parser.parse_args(argv)
    try:
        enable_compilation_cache()
        return args.run(args)
    except KeyboardInterrupt:
        print(f"jaxreg {args.command}: interrupted", file=sys.stderr)
        return 130
    except (ValueError, OSError, ImportError) as err:  # bad input: one clear line
        message = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        print(f"jaxreg {args.command}: {message}", file=sys.stderr)
        return 2
    except Exception as err:  # a bug: never reported as the user's mistake
        traceback.print_exc()
        print(
            f"jaxreg {args.command}: internal error ({type(err).__name__}), not a problem with "
            "the input: please report it with the traceback above",
            file=sys.stderr,
        )
        return 3
