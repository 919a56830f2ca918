"""``jaxreg pose --ycbv PREFIX --object NAME_OR_INDEX``: ``jaxreg pose`` on a YCB-Video frame
(:func:`jaxreg.io.read_ycbv`). The frame's depth and colour, the object's point model and its
mask (the label image's pixels of its class; ``--no-mask`` for the table route, or ``--mask``,
``--pixel``, ``--box`` of your own) come from the dataset, and, the truth being known, the
report holds the errors against it as ``jaxreg demo``'s does: ``translation_error_mm``,
``rotation_error_deg``, ``add_mm``, ``add_s_mm`` and ``truth`` (the ``(4, 4)`` true
base_T_object; the frame's base is its camera), and ``ycbv`` says which frame, object and
segment were used.
"""

from __future__ import annotations

from pathlib import Path

from jaxreg.cli._report import (
    add_truth_errors,
    build_report,
    emit,
    pose_options,
    stage_progress,
    truth_offset,
)
from jaxreg.io.ycbv import read_ycbv
from jaxreg.pipeline.estimate import estimate_pose

__all__ = ["run_pose_ycbv"]


def _ycbv_instance(prefix: Path, wanted: str | None):
    """The YCB-Video frame at ``prefix`` (:func:`jaxreg.io.read_ycbv`) and its instance named
    by ``wanted``: a model name (``025_mug``, or ``mug``) or a class index (``14``, the
    label's value)."""
    frames = read_ycbv(prefix)
    if len(frames) != 1:
        raise ValueError(
            f"--ycbv {prefix} names {len(frames)} frames ({frames[0].name} ...); give one "
            "frame's prefix, e.g. data/0000/000001"
        )
    (ycbv,) = frames
    present = ", ".join(f"{i.model_name} ({i.class_index})" for i in ycbv.instances)
    if wanted is None:
        raise ValueError(f"--ycbv needs --object NAME_OR_INDEX: frame {ycbv.name} holds {present}")
    for instance in ycbv.instances:
        short = instance.model_name.split("_", 1)[-1]
        if wanted in (instance.model_name, short, str(instance.class_index)):
            break
    else:
        raise ValueError(f"--object {wanted!r} is not in frame {ycbv.name}: it holds {present}")
    if instance.model_points is None:
        raise ValueError(
            f"{prefix}: no models/ folder (models.txt, <name>/points.xyz) beside the dataset's "
            "data/ folder: the object's points are needed"
        )
    return ycbv, instance


def run_pose_ycbv(args) -> int:
    """``jaxreg pose --ycbv PREFIX --object NAME_OR_INDEX``: the frame, the model and the
    label's mask from the dataset, and the errors against its truth in the report."""
    unused = [f"--{name}" for name in ("model", "intrinsics", "rgb") if getattr(args, name)]
    if unused:
        raise ValueError(
            f"{', '.join(unused)} cannot be given with --ycbv: the dataset holds the model, the "
            "intrinsics and the colour image"
        )
    ycbv, instance = _ycbv_instance(args.ycbv, args.object)
    frame, model = ycbv.frame, instance.model_points
    options = pose_options(args, frame)
    if args.no_mask:
        segment = "the table route"
    elif any(option in options for option in ("mask", "pixel", "box")):
        segment = "your --mask, --pixel or --box"
    else:
        options["mask"], segment = instance.mask, "the label's mask"
    progress = stage_progress(args.json)
    estimate = estimate_pose(frame, model, progress=progress, **options)
    progress(None)
    report = build_report(
        estimate, model, args.gripper_opening, truth_offset(estimate, instance.truth)
    )
    add_truth_errors(report, estimate, instance.truth, model, options["symmetry"])
    report["scene"] = str(args.ycbv)
    report["ycbv"] = {
        "frame": ycbv.name,
        "object": instance.model_name,
        "class_index": instance.class_index,
        "segment": segment,
        "model_points": len(model),
    }
    title = f"jaxreg pose: {instance.model_name} in YCB-Video frame {ycbv.name}"
    return emit(args, report, title, frame, estimate, model, truth=instance.truth)
