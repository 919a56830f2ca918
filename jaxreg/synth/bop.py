"""Synthetic tabletop scenes written as a BOP dataset split, so the BOP route (reader, runner,
metrics) runs without downloading anything.

`write_bop_split` writes the scenewise layout `jaxreg.io.read_bop` reads (see `jaxreg.io.bop`):
models in millimetres with their diameters and symmetries in models_info.json, 16-bit depth
PNGs (`DEPTH_SCALE` millimetres per count), colour PNGs, the target's visible and full masks,
scene_gt / scene_gt_info / scene_camera, camera.json and test_targets_bop19.json. Object ids
follow `OBJECTS`: 1 box, 2 mug, 3 cylinder, 4 container.

Each image is its own `tabletop_scene` with one target object (the distractors are clutter,
not BOP objects); BOP's world frame is the scene's base frame (`cam_R_w2c`, `cam_t_w2c` from
its `base_T_camera`), so `read_bop(...).frame(...)` gives back the base frame the pipeline
expects (z up, table top at z = 0).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh
from PIL import Image

from jaxreg.geometry.metrics import Symmetry
from jaxreg.synth._meshes import OBJECTS, object_mesh
from jaxreg.synth.render import render
from jaxreg.synth.scenes import TabletopScene, tabletop_scene

__all__ = ["DEPTH_SCALE", "image_scene", "obj_id", "write_bop_split"]

DEPTH_SCALE = 0.1  # millimetres per depth count: 0.1 mm steps, 6.5 m range
_MM_PER_M = 1000.0


def obj_id(name: str) -> int:
    """The BOP object id of one of `OBJECTS` (1-based, in `OBJECTS`' order)."""
    if name not in OBJECTS:
        raise ValueError(f"unknown object {name!r}: choose from {', '.join(OBJECTS)}")
    return OBJECTS.index(name) + 1


def image_scene(
    seed: int, k: int, objects: Sequence[str] = OBJECTS, noise: bool = True
) -> TabletopScene:
    """The `tabletop_scene` that `write_bop_split(..., objects=objects, seed=seed,
    noise=noise)` writes as its `k`-th image (counted over scenes, scene by scene)."""
    scene_seed = np.random.default_rng([seed, 26]).integers(0, 2**31, k + 1)[k]
    return tabletop_scene(int(scene_seed), object=objects[k % len(objects)], noise=noise)


def _write_json(path: Path, content: dict | list) -> None:
    """JSON with one top-level entry per line, as the BOP datasets' files are laid out."""
    if isinstance(content, dict):
        items = [
            f"{json.dumps(key)}: {json.dumps(value, sort_keys=True)}"
            for key, value in content.items()
        ]
        text = "{\n  " + ",\n  ".join(items) + "\n}\n"
    else:
        text = "[\n  " + ",\n  ".join(json.dumps(v, sort_keys=True) for v in content) + "\n]\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def _model_info(mesh: trimesh.Trimesh, symmetry: Symmetry) -> dict:
    """models_info.json's entry (millimetres): diameter, bounding box, symmetries."""
    vertices = np.asarray(mesh.vertices) * _MM_PER_M
    hull = np.asarray(mesh.convex_hull.vertices) * _MM_PER_M  # the farthest pair lies on it
    gaps = np.linalg.norm(hull[:, None] - hull[None], axis=-1)
    low, size = vertices.min(axis=0), np.ptp(vertices, axis=0)
    info = {"diameter": float(gaps.max())}
    info |= {f"min_{a}": float(v) for a, v in zip("xyz", low, strict=True)}
    info |= {f"size_{a}": float(v) for a, v in zip("xyz", size, strict=True)}
    rotations = np.asarray(symmetry.rotations, dtype=np.float64)[1:]
    if len(rotations):
        transforms = np.tile(np.eye(4), (len(rotations), 1, 1))
        transforms[:, :3, :3] = rotations
        info["symmetries_discrete"] = transforms.reshape(-1, 16).tolist()
    if symmetry.axis is not None:
        axis = np.asarray(symmetry.axis, dtype=np.float64).tolist()
        info["symmetries_continuous"] = [{"axis": axis, "offset": [0.0, 0.0, 0.0]}]
    return info


def _bbox(mask: np.ndarray) -> list[int]:
    """BOP's `[x, y, width, height]` of a mask's pixels, `[-1, -1, 0, 0]` when empty."""
    rows, cols = np.nonzero(mask)
    if len(rows) == 0:
        return [-1, -1, 0, 0]
    return [int(cols.min()), int(rows.min()), int(np.ptp(cols)) + 1, int(np.ptp(rows)) + 1]


def _flat_pose(rotation: np.ndarray, translation_m: np.ndarray) -> tuple[list, list]:
    return rotation.reshape(-1).tolist(), (translation_m * _MM_PER_M).tolist()


def _save_png(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)


def _write_image(folder: Path, im_id: int, scene: TabletopScene, object_id: int):
    """The image's depth, colour and masks as PNGs in `folder`; returns its scene_camera,
    scene_gt and scene_gt_info entries (millimetres)."""
    intrinsics = scene.frame.intrinsics
    base_T_camera = np.asarray(scene.frame.base_T_camera.as_matrix(), np.float64)
    base_T_object = np.asarray(scene.truth.as_matrix(), np.float64)
    camera_T_base = np.linalg.inv(base_T_camera)
    camera_T_object = camera_T_base @ base_T_object
    # the object alone: its full silhouette (BOP's mask/ and px_count_all)
    alone = render([scene.model.copy().apply_transform(base_T_object)], intrinsics, base_T_camera)
    full = alone.labels == 0
    depth = np.nan_to_num(np.asarray(scene.frame.depth, np.float64), nan=0.0)
    counts = np.rint(depth * _MM_PER_M / DEPTH_SCALE).astype(np.uint16)
    stem = f"{im_id:06d}"
    _save_png(folder / "depth" / f"{stem}.png", counts)
    _save_png(folder / "rgb" / f"{stem}.png", np.asarray(scene.frame.rgb, np.uint8))
    _save_png(folder / "mask_visib" / f"{stem}_000000.png", scene.mask.astype(np.uint8) * 255)
    _save_png(folder / "mask" / f"{stem}_000000.png", full.astype(np.uint8) * 255)

    K = np.array(
        [[intrinsics.fx, 0, intrinsics.cx], [0, intrinsics.fy, intrinsics.cy], [0, 0, 1]],
        dtype=np.float64,
    )
    R_w2c, t_w2c = _flat_pose(camera_T_base[:3, :3], camera_T_base[:3, 3])
    camera = {
        "cam_K": K.reshape(-1).tolist(),
        "depth_scale": DEPTH_SCALE,
        "cam_R_w2c": R_w2c,
        "cam_t_w2c": t_w2c,
    }
    R_m2c, t_m2c = _flat_pose(camera_T_object[:3, :3], camera_T_object[:3, 3])
    gt = [{"obj_id": object_id, "cam_R_m2c": R_m2c, "cam_t_m2c": t_m2c}]
    visible = int(scene.mask.sum())
    info = [
        {
            "bbox_obj": _bbox(full),
            "bbox_visib": _bbox(scene.mask),
            "px_count_all": int(full.sum()),
            "px_count_valid": int((scene.mask & (counts > 0)).sum()),
            "px_count_visib": visible,
            "visib_fract": visible / max(int(full.sum()), 1),
        }
    ]
    return camera, gt, info


def write_bop_split(
    root: str | Path,
    *,
    split: str = "test",
    objects: Sequence[str] = OBJECTS,
    scenes: int = 2,
    images_per_scene: int = 2,
    seed: int = 0,
    noise: bool = True,
) -> Path:
    """Write `scenes` x `images_per_scene` tabletop images as the BOP split `root/split`.

    Args:
        root: the dataset folder (created; existing files of the same names are replaced).
        split: the split folder's name.
        objects: names from `OBJECTS`; image `k` (counted over scenes) shows
            `objects[k % len(objects)]`.
        scenes: scene folders, ids 1..scenes; image ids start at 0 in each.
        images_per_scene: images per scene.
        seed: the draw of every image's scene (geometry and noise).
        noise: the depth camera's noise (`tabletop_scene`'s); False writes the exact depth.

    Returns:
        `root` as a `Path`.
    """
    if not objects or any(name not in OBJECTS for name in objects):
        raise ValueError(f"objects must be names from {', '.join(OBJECTS)}, got {objects!r}")
    if scenes < 1 or images_per_scene < 1:
        raise ValueError("scenes and images_per_scene must be at least 1")
    root = Path(root)
    infos = {}
    for name in dict.fromkeys(objects):
        mesh, symmetry = object_mesh(name)
        path = root / "models" / f"obj_{obj_id(name):06d}.ply"
        path.parent.mkdir(parents=True, exist_ok=True)
        mesh.copy().apply_scale(_MM_PER_M).export(path)
        infos[str(obj_id(name))] = _model_info(mesh, symmetry)
    _write_json(root / "models" / "models_info.json", infos)

    targets = []
    intrinsics = None
    for s in range(scenes):
        scene_id, folder = s + 1, root / split / f"{s + 1:06d}"
        cameras, gts, gt_infos = {}, {}, {}
        for im_id in range(images_per_scene):
            name = objects[(s * images_per_scene + im_id) % len(objects)]
            scene = image_scene(seed, s * images_per_scene + im_id, objects, noise)
            intrinsics = scene.frame.intrinsics
            cameras[str(im_id)], gts[str(im_id)], gt_infos[str(im_id)] = _write_image(
                folder, im_id, scene, obj_id(name)
            )
            targets.append(
                {"im_id": im_id, "inst_count": 1, "obj_id": obj_id(name), "scene_id": scene_id}
            )
        _write_json(folder / "scene_camera.json", cameras)
        _write_json(folder / "scene_gt.json", gts)
        _write_json(folder / "scene_gt_info.json", gt_infos)
    camera = {key: float(getattr(intrinsics, key)) for key in ("fx", "fy", "cx", "cy")}
    camera |= {"width": intrinsics.width, "height": intrinsics.height, "depth_scale": DEPTH_SCALE}
    _write_json(root / "camera.json", camera)
    _write_json(root / "test_targets_bop19.json", targets)
    return root
