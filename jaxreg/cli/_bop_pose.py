"""``jaxreg pose --bop DATASET --scene S --image I --object O``: ``jaxreg pose`` on one image of a
BOP dataset split (:func:`jaxreg.io.read_bop`; ``--split``, default ``test``).

The image's depth and colour, the object's model (its mesh's surface samples, or a point
model's vertices, as ``jaxreg bop`` takes them), its symmetries (models_info.json) and its
visible mask (mask_visib; ``--no-mask`` for the table route, or ``--mask``, ``--pixel``,
``--box`` of your own) come from the dataset. Of several instances of the object in the image,
the most visible is the target. The truth being known, the report holds the errors against it
as ``--ycbv``'s does (``translation_error_mm``, ``rotation_error_deg``, ``add_mm``,
``add_s_mm``, ``truth``: the ``(4, 4)`` true base_T_object, the base being BOP's world frame
where the split gives ``cam_*_w2c``, else the camera), and ``bop`` says which image, object,
instance and segment were used.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxreg.cli._report import (
    add_truth_errors,
    build_report,
    emit,
    pose_options,
    stage_progress,
    truth_offset,
)
from jaxreg.geometry.lie import SE3
from jaxreg.io.bop import read_bop
from jaxreg.pipeline.estimate import estimate_pose
from jaxreg.synth import surface_points

__all__ = ["run_pose_bop"]


def _listed(ids) -> str:
    """``[1, 2, 3, 5, 7, 8]`` as ``"1-3, 5, 7-8"``."""
    runs = []
    for i in sorted(ids):
        if runs and i == runs[-1][1] + 1:
            runs[-1][1] = i
        else:
            runs.append([i, i])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def _id(value, flag: str) -> int:
    text = str(value)
    if not text.isdigit():
        raise ValueError(f"{flag} with --bop is the dataset's integer id, got {text!r}")
    return int(text)


def _bop_target(root: Path, split_name: str, scene: int, image: int, obj: int):
    """The split read for this scene and object, and the target: the most visible instance of
    object ``obj`` in image ``image`` of scene ``scene``. A missing scene, image or object is a
    ``ValueError`` naming what the split holds."""
    try:
        split = read_bop(root, split_name, scenes=[scene], objects=[obj])
    except ValueError:
        split = None
    if split is None or (scene, image) not in split.images:
        # read the scene whole to name what it holds (a missing split or scene raises here)
        whole = read_bop(root, split_name, scenes=[scene])
        images = [im for s, im in whole.images if s == scene]
        if image not in images:
            raise ValueError(
                f"--image {image} is not in scene {scene} of {root / split_name}: its images "
                f"with targets are {_listed(images)}"
            )
        present = sorted({t.obj_id for t in whole.targets(scene, image)})
        if obj not in present:
            raise ValueError(
                f"--object {obj} is not in image {image} of scene {scene}: it holds objects "
                f"{', '.join(map(str, present))}"
            )
        split = read_bop(root, split_name, scenes=[scene], objects=[obj])  # its own error
    instances = [t for t in split.targets(scene, image) if t.obj_id == obj]
    target = max(instances, key=lambda t: t.visib_fract)
    return split, target, len(instances)


def run_pose_bop(args) -> int:
    """``jaxreg pose --bop DATASET --scene S --image I --object O``: the frame, the model, its
    symmetries and the visible mask from the dataset, and the errors against its truth in the
    report."""
    unused = [
        f"--{name.replace('_', '-')}"
        for name in ("ycbv", "model", "intrinsics", "rgb", "model_colors")
        if getattr(args, name)
    ]
    if unused:
        raise ValueError(
            f"{', '.join(unused)} cannot be given with --bop: the dataset holds the frame, the "
            "model, the intrinsics and the colour image"
        )
    if args.symmetry != "none":
        raise ValueError(
            "--symmetry cannot be given with --bop: the dataset's models_info.json gives the "
            "object's symmetries"
        )
    missing = [flag for flag, value in (("--scene", args.scene), ("--image", args.image),
                                        ("--object", args.object)) if value is None]  # fmt: skip
    if missing:
        raise ValueError(f"--bop DATASET needs {', '.join(missing)} (--scene S --image I "
                         "--object O: the ids of one image and one object in it)")  # fmt: skip
    split_name = args.split or "test"
    scene, obj = _id(args.scene, "--scene"), _id(args.object, "--object")
    split, target, count = _bop_target(args.bop, split_name, scene, args.image, obj)
    model = split.models[obj]
    points = (
        model.points.astype(np.float32) if model.mesh is None else surface_points(model.mesh)
    )
    frame = split.frame(scene, args.image)
    options = pose_options(args, frame)
    options["symmetry"] = model.symmetry
    if args.no_mask:
        segment = "the table route"
    elif any(option in options for option in ("mask", "pixel", "box")):
        segment = "your --mask, --pixel or --box"
    else:
        mask = split.mask(target)
        if mask is None:
            segment = "the table route (the split has no mask_visib)"
        elif not mask.any():
            raise ValueError(
                f"object {obj}'s mask_visib in image {args.image} of scene {scene} is empty: "
                "nothing of it is visible (give --no-mask, --pixel or --box to look anyway)"
            )
        else:
            options["mask"], segment = mask, "mask_visib"
    base_T_camera = np.asarray(frame.base_T_camera.as_matrix(), np.float64)
    truth = SE3.from_matrix(base_T_camera @ target.camera_T_object)
    progress = stage_progress(args.json)
    estimate = estimate_pose(frame, points, progress=progress, **options)
    progress(None)
    report = build_report(estimate, points, args.gripper_opening, truth_offset(estimate, truth))
    add_truth_errors(report, estimate, truth, points, model.symmetry)
    report["scene"] = str(args.bop / split_name)
    report["bop"] = {
        "dataset": str(args.bop),
        "split": split_name,
        "scene_id": scene,
        "im_id": args.image,
        "obj_id": obj,
        "gt_index": target.gt_index,
        "instances": count,
        "visib_fract": target.visib_fract,
        "segment": segment,
        "model_points": len(points),
    }
    title = f"jaxreg pose: object {obj} in BOP image {scene}/{args.image} of {args.bop}"
    return emit(args, report, title, frame, estimate, points, truth=truth)
