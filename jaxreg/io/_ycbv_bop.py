"""YCB-Video frames written as a BOP dataset split, so that `jaxreg.io.read_bop` and
`jaxreg bop` read and score them. Public through `jaxreg.io.ycbv_to_bop`.

What is written (`jaxreg.io.bop`'s layout, BOP's units: millimetres)::

    OUT/camera.json                                  width, height
    OUT/models/models_info.json                      per object: diameter, min_x/y/z, size_x/y/z
    OUT/models/obj_<class:06d>.ply                   PoseCNN's points, vertices only, mm
    OUT/<split>/<sequence:06d>/scene_camera.json     {im_id: {cam_K, depth_scale}}
    OUT/<split>/<sequence:06d>/scene_gt.json         {im_id: [{obj_id, cam_R_m2c, cam_t_m2c}]}
    OUT/<split>/<sequence:06d>/depth/<im_id:06d>.png         uint16, mm = count * depth_scale
    OUT/<split>/<sequence:06d>/rgb/<im_id:06d>.png           the colour image
    OUT/<split>/<sequence:06d>/mask_visib/<im_id:06d>_<k:06d>.png   label == class of instance k

The object id is the YCB-Video class index (the line of models.txt, as in BOP's own ycbv
release), the scene id the sequence number and the image id the frame number. Converting more
frames into the same folder adds them (the JSON files are merged, an image converted again is
replaced).

What the YCB-Video files cannot give, and is therefore not written: meshes (the models are
PoseCNN's 2,620 surface points, so BOP's VSD, which renders a surface, cannot score them; MSSD
and MSPD need only vertices), the objects' symmetries (none are declared: a box turned half
a turn counts as an error), full-silhouette masks (`mask/`) and `scene_gt_info.json`'s visible
fractions (both need a rendered silhouette; `read_bop` then takes every instance as a target).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from PIL import Image

from jaxreg.geometry.metrics import diameter
from jaxreg.io.clouds import write_ply
from jaxreg.io.ycbv import YcbvFrame, read_ycbv

__all__ = ["ycbv_to_bop"]

_MM = 1000.0  # millimetres per metre
_UINT16_MAX = np.iinfo(np.uint16).max


def _model_info(points_mm: np.ndarray) -> dict:
    low, high = points_mm.min(0), points_mm.max(0)
    info = {"diameter": diameter(points_mm)}
    info |= {f"min_{axis}": float(v) for axis, v in zip("xyz", low, strict=True)}
    info |= {f"size_{axis}": float(v) for axis, v in zip("xyz", high - low, strict=True)}
    return info


def _merge_json(path: Path, entries: dict) -> None:
    """Writes `entries` into the JSON object at `path`, over what it already holds."""
    document = json.loads(path.read_text()) if path.is_file() else {}
    if not isinstance(document, dict):
        raise ValueError(f"{path}: exists and is not a JSON object; convert into an empty folder")
    document.update(entries)
    ordered = dict(sorted(document.items(), key=lambda item: int(item[0])))
    path.write_text(json.dumps(ordered, indent=2))


def _ids(frame: YcbvFrame) -> tuple[int, int]:
    sequence, image = frame.name.split("/")
    if not (sequence.isdigit() and image.isdigit()):
        raise ValueError(
            f"frame {frame.name}: BOP needs numeric scene and image ids; the sequence and frame "
            "names must be digits"
        )
    return int(sequence), int(image)


def _depth_counts(frame: YcbvFrame, depth_scale: float) -> np.ndarray:
    """The frame's depth as BOP counts (`mm = count * depth_scale`, 0 = no measurement)."""
    depth = np.asarray(frame.frame.depth, np.float64)
    counts = np.rint(np.nan_to_num(depth, nan=0.0) * _MM / depth_scale)
    if counts.max() > _UINT16_MAX:
        raise ValueError(
            f"frame {frame.name}: depth {np.nanmax(depth):.3f} m is {counts.max():.0f} counts > "
            f"65535 at depth_scale {depth_scale} mm: choose a larger depth_scale"
        )
    return counts.astype(np.uint16)


def _write_image(
    folder: Path, frame: YcbvFrame, counts: np.ndarray, depth_scale: float
) -> tuple[dict, list, dict]:
    """Writes one frame's depth `counts`, colour and masks into its scene `folder`; returns its
    scene_camera entry, its scene_gt entries and its models `{obj_id: points (M, 3) mm}`."""
    _, im_id = _ids(frame)
    for sub in ("depth", "rgb", "mask_visib"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    Image.fromarray(counts).save(folder / "depth" / f"{im_id:06d}.png")
    if frame.frame.rgb is not None:
        rgb = np.asarray(frame.frame.rgb, np.uint8)
        Image.fromarray(rgb).save(folder / "rgb" / f"{im_id:06d}.png")
    for stale in (folder / "mask_visib").glob(f"{im_id:06d}_*.png"):
        stale.unlink()  # an image converted again: its instances may differ
    K = np.asarray(frame.frame.intrinsics.K, np.float64)
    camera = {"cam_K": K.reshape(-1).tolist(), "depth_scale": depth_scale}
    gts, models = [], {}
    for k, instance in enumerate(frame.instances):
        matrix = np.asarray(instance.truth.as_matrix(), np.float64)
        gts.append({
            "cam_R_m2c": matrix[:3, :3].reshape(-1).tolist(),
            "cam_t_m2c": (matrix[:3, 3] * _MM).tolist(),
            "obj_id": instance.class_index,
        })  # fmt: skip
        mask = (255 * np.asarray(instance.mask, bool)).astype(np.uint8)
        Image.fromarray(mask).save(folder / "mask_visib" / f"{im_id:06d}_{k:06d}.png")
        models[instance.class_index] = np.asarray(instance.model_points, np.float64) * _MM
    return camera, gts, models


def ycbv_to_bop(
    path: str | Path,
    out_root: str | Path,
    split: str = "test",
    *,
    models: str | Path | None = None,
    depth_scale: float = 0.1,
) -> Path:
    """Write YCB-Video frames as a BOP dataset split (see the module docstring).

    Args:
        path: what `jaxreg.io.read_ycbv` reads: a sequence folder, one frame's prefix or the
            dataset root.
        out_root: the BOP dataset folder to write (created if needed; frames already there are
            kept, an image converted again is replaced).
        split: the split folder's name.
        models: the folder of `models.txt` and `<name>/points.xyz` (default: found beside the
            dataset's `data/`, as `read_ycbv` finds it).
        depth_scale: millimetres per depth count of the written PNGs; the default 0.1 is
            YCB-Video's own unit (factor_depth 10000), so its counts are written unchanged.

    Returns:
        The split's folder, `out_root / split`.

    Raises:
        ValueError: what `read_ycbv` raises; no models found; a depth beyond 65535 counts at
            `depth_scale`; frames of different image sizes, or of another size than the
            folder's camera.json.
    """
    if not depth_scale > 0:
        raise ValueError(f"depth_scale must be positive millimetres per count, got {depth_scale}")
    frames = read_ycbv(path, models=models)
    for frame in frames:  # everything checked before anything is written
        _ids(frame)
        for instance in frame.instances:
            if instance.model_points is None:
                raise ValueError(
                    f"{path}: no models folder found beside data/ (no points for "
                    f"{instance.model_name}); pass models= (the folder of models.txt and "
                    "<name>/points.xyz)"
                )
    counts = [_depth_counts(frame, depth_scale) for frame in frames]
    out_root = Path(out_root)
    sizes = {frame.frame.intrinsics.shape for frame in frames}
    camera_path = out_root / "camera.json"
    if camera_path.is_file():
        held = json.loads(camera_path.read_text())
        sizes.add((held.get("height"), held.get("width")))
    if len(sizes) != 1:
        raise ValueError(
            f"{out_root}: frames of different image sizes {sorted(map(str, sizes))} (height, "
            "width) cannot share one BOP camera.json; convert them into separate folders"
        )
    ((height, width),) = sizes
    (out_root / "models").mkdir(parents=True, exist_ok=True)
    camera_path.write_text(json.dumps({"width": width, "height": height}, indent=2))
    scenes: dict[int, tuple[dict, dict]] = {}
    points: dict[int, np.ndarray] = {}
    for frame, depth in zip(frames, counts, strict=True):
        scene_id, im_id = _ids(frame)
        folder = out_root / split / f"{scene_id:06d}"
        camera, gts, models_mm = _write_image(folder, frame, depth, depth_scale)
        cameras, truths = scenes.setdefault(scene_id, ({}, {}))
        cameras[str(im_id)], truths[str(im_id)] = camera, gts
        points |= models_mm
    for scene_id, (cameras, truths) in scenes.items():
        folder = out_root / split / f"{scene_id:06d}"
        _merge_json(folder / "scene_camera.json", cameras)
        _merge_json(folder / "scene_gt.json", truths)
    for obj_id, points_mm in points.items():
        write_ply(out_root / "models" / f"obj_{obj_id:06d}.ply", points_mm)
    infos = {str(obj_id): _model_info(p) for obj_id, p in sorted(points.items())}
    _merge_json(out_root / "models" / "models_info.json", infos)
    return out_root / split
