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
  (:mod:`jaxreg.cli._ycbv`); ``jaxreg pose --bop DATASET --scene S --image I --object O`` on
  one image of a BOP dataset split (``--split``, default test), with the object's model,
  symmetries and visible mask (:mod:`jaxreg.cli._bop_pose`).

With ``--json`` stdout is one JSON object (the fields of the design's command line section);
``--out DIR`` also writes ``report.json`` and the pictures ``depth.png``,
``segmentation.png`` (the lifted segment over the image) and ``model_overlay.png`` (the
model's visible surface at the estimate, outlined, with its axes, and at the truth where it is
known; a refused estimate's best hypothesis in grey with its reason: :mod:`jaxreg.cli._overlay`)
to DIR, over the colour image when the frame has one.
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
function of the parsed arguments returning the exit status. What the pose commands share (the
report, its pictures, the errors against a truth, ``estimate_pose``'s options) is
:mod:`jaxreg.cli._report`, which imports none of the commands' modules.
"""

from __future__ import annotations

import argparse
import sys
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
from jaxreg.cli._report import (
    UNITS,
    add_truth_errors,
    build_report,
    emit,
    pose_options,
    stage_progress,
    truth_offset,
)
from jaxreg.core.compilation import enable_compilation_cache

GRIPPER_OPENING = 0.085  # metres: a Robotiq 2F-85-class parallel-jaw gripper


# --------------------------------------------------------------------------------------------
# Commands.


def run_demo(args) -> int:
    from jaxreg.pipeline.estimate import estimate_pose
    from jaxreg.synth import OBJECTS, StereoSensor, surface_samples, tabletop_scene

    if args.object not in OBJECTS:
        raise ValueError(f"unknown object {args.object!r}: choose one of {', '.join(OBJECTS)}")
    if args.track is not None:
        from jaxreg.cli._track import run_demo_track

        return run_demo_track(args)
    progress = stage_progress(args.json)
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
    return emit(args, report, title, scene.frame, estimate, model, truth=scene.truth)


def run_pose(args) -> int:
    from jaxreg.io import load_points, read_frame
    from jaxreg.pipeline.estimate import estimate_pose

    if args.bop is not None:
        from jaxreg.cli._bop_pose import run_pose_bop

        return run_pose_bop(args)
    for name in ("image", "split"):
        if getattr(args, name) is not None:
            raise ValueError(f"--{name} is for --bop datasets")
    if args.scene is None and args.ycbv is None:
        raise ValueError(
            "give --scene FILE, --ycbv PREFIX or --bop DATASET --scene S --image I --object O"
        )
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
            raise ValueError(f"--{name.replace('_', '-')} is for --ycbv and --bop frames")
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
    options = pose_options(args, frame)
    if colors is not None:
        options["model_colors"] = colors
    progress = stage_progress(args.json)
    estimate = estimate_pose(frame, model, progress=progress, **options)
    progress(None)
    report = build_report(estimate, model, args.gripper_opening)
    report["scene"] = str(args.scene)
    report["model"] = str(args.model)
    return emit(
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
    frame = pose.add_mutually_exclusive_group()
    frame.add_argument(
        "--scene", type=Path, help="organized PCD or depth PNG; with --bop, the scene id"
    )
    frame.add_argument(
        "--ycbv", type=Path, metavar="PREFIX",
        help="a YCB-Video frame (e.g. data/0000/000001): its depth, colour, the model of "
        "--object, the label's mask, and the errors against its truth",
    )  # fmt: skip
    pose.add_argument(
        "--object", metavar="NAME_OR_INDEX",
        help="with --ycbv: the object, by model name (025_mug) or class index (14); with "
        "--bop: its object id",
    )  # fmt: skip
    pose.add_argument(
        "--bop", type=Path, metavar="DATASET",
        help="a BOP dataset's folder: with --scene S --image I --object O, one image of it, "
        "the object's model and visible mask, and the errors against its truth",
    )  # fmt: skip
    pose.add_argument("--image", type=int, metavar="I", help="with --bop: the image id")
    pose.add_argument("--split", help="with --bop: the split folder (default test)")
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
        help="with --ycbv or --bop: find the object by the table route, not the dataset's mask",
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
