"""``jaxreg demo --track N``: a synthetic target pushed across the table over ``N`` frames
(:func:`jaxreg.synth.tracking_sequence`: 1-5 cm and 2-10 degrees between frames), found by
``estimate_pose`` in the first frame and followed by ``track`` in the others, re-detected by
``estimate_pose`` where ``track`` says it is lost. Prints a row per frame: the step, the
function that answered, the error against the truth, the reported sigma and the time."""

from __future__ import annotations

import json
import sys
import time

import numpy as np

from jaxreg.cli._report import truth_errors


def run_demo_track(args) -> int:
    """Runs the sequence; exit 0 when every frame was answered, else 1."""
    from jaxreg.pipeline.estimate import estimate_pose
    from jaxreg.pipeline.track import track
    from jaxreg.synth import StereoSensor, surface_samples, tracking_sequence

    if args.track < 2:
        raise ValueError(f"--track needs at least 2 frames, got {args.track}")
    if not args.json:
        print(
            f"jaxreg demo --track {args.track}: seed {args.seed}, a {args.object} pushed across "
            "the table (1-5 cm, 2-10 deg a frame) in front of a RealSense D435 (the first "
            "estimate_pose and the first track compile)",
            file=sys.stderr,
        )
    sequence = tracking_sequence(args.seed, object=args.object, frames=args.track)
    first = sequence.scenes[0]
    model, normals = surface_samples(first.model)
    options = {
        "model_normals": normals,
        "symmetry": first.symmetry,
        "depth_noise": StereoSensor.d435().depth_noise(first.frame.intrinsics),
    }
    rows, previous = [], None
    for k, scene in enumerate(sequence.scenes):
        start = time.perf_counter()
        method = "estimate_pose"
        if previous is not None and previous.pose is not None:
            method = "track"
            estimate = track(scene.frame, model, previous, **options)
            if estimate.pose is None:
                method = "estimate_pose (lost)"
        if method != "track":
            estimate = estimate_pose(scene.frame, model, **options)
        ms = (time.perf_counter() - start) * 1e3
        row = {
            "frame": k,
            "step_mm": None if k == 0 else round(float(sequence.steps[k - 1, 0]) * 1e3, 1),
            "step_deg": None if k == 0 else round(float(sequence.steps[k - 1, 1]), 1),
            "method": method,
            "found": estimate.pose is not None,
            "add_s_mm": None,
            "sigma_mm": None,
            "ms": round(ms, 1),
            "reason": estimate.reason,
            "view_terms": None,
        }
        if estimate.pose is not None:
            add_s = truth_errors(estimate.pose, scene.truth, scene.model_points, first.symmetry)[3]
            row["add_s_mm"] = round(float(add_s) * 1e3, 2)
            sigma = np.sqrt(np.trace(np.asarray(estimate.covariance)[:3, :3]))
            row["sigma_mm"] = round(float(sigma) * 1e3, 2)
            carried = estimate.stages["register"].view_carried_deg is not None
            row["view_terms"] = "carried" if carried else "measured"
        rows.append(row)
        previous = estimate
    if args.json:
        print(json.dumps({"seed": args.seed, "object": args.object, "frames": rows}))
    else:
        _print_rows(rows)
    return 0 if all(row["found"] for row in rows) else 1


def _print_rows(rows: list[dict]) -> None:
    """The per-frame table on stdout."""
    print("frame  step          answered by            ADD-S     sigma     time  view terms")
    for row in rows:
        step = (
            "" if row["step_mm"] is None else f"{row['step_mm']:.0f} mm {row['step_deg']:.0f} deg"
        )
        if row["found"]:
            error = f"{row['add_s_mm']:6.2f} mm {row['sigma_mm']:6.2f} mm"
        else:
            error = f"refused: {row['reason'][:60]}"
        print(
            f"{row['frame']:5d}  {step:12s}  {row['method']:21s}  {error}  {row['ms']:7.0f} ms"
            f"  {row['view_terms'] or ''}"
        )
