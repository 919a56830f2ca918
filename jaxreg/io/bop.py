"""BOP datasets (the Benchmark for 6D Object Pose Estimation) in, pose estimates out.

Public through `jaxreg.io.read_bop`, `BopSplit`, `BopModel`, `BopTarget`, `BopResult`,
`write_bop_results` and `read_bop_results`. Host side; everything returned is in metres (BOP's
files are in millimetres) and a malformed or missing file raises `ValueError` naming it.

The scenewise layout read here::

    ROOT/camera.json                      optional: width, height (pixels)
    ROOT/test_targets_bop19.json          optional: [{scene_id, im_id, obj_id, inst_count}]
    ROOT/models/models_info.json          diameter and symmetries (see _bop_models)
    ROOT/models/obj_<obj_id:06d>.ply      meshes, millimetres
    ROOT/<split>/<scene_id:06d>/scene_camera.json   {im_id: {cam_K, depth_scale,
                                                      cam_R_w2c?, cam_t_w2c?}}
    ROOT/<split>/<scene_id:06d>/scene_gt.json       {im_id: [{obj_id, cam_R_m2c, cam_t_m2c}]}
    ROOT/<split>/<scene_id:06d>/scene_gt_info.json  optional: {im_id: [{visib_fract, ...}]}
    ROOT/<split>/<scene_id:06d>/depth/<im_id:06d>.png             16-bit, mm = count * scale
    ROOT/<split>/<scene_id:06d>/mask_visib/<im_id:06d>_<k:06d>.png  optional, k = gt index
    ROOT/<split>/<scene_id:06d>/rgb/<im_id:06d>.png (or .jpg)     optional

`cam_K` is row-major 3x3 with OpenCV's pixel convention (the library's); `cam_R_*` are
row-major 3x3, `cam_t_*` millimetres; `*_m2c` maps model to camera, `*_w2c` world to camera.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from jaxreg.camera.model import Intrinsics, RGBDFrame
from jaxreg.io._bop_files import load_json, numbers
from jaxreg.io._bop_models import MM, BopModel, read_models
from jaxreg.io._bop_results import BopResult, read_bop_results, write_bop_results
from jaxreg.io.images import read_depth_counts, read_image_size, read_mask, read_rgb

__all__ = [
    "BopModel",
    "BopResult",
    "BopSplit",
    "BopTarget",
    "read_bop",
    "read_bop_results",
    "write_bop_results",
]


@dataclasses.dataclass(frozen=True, eq=False)
class BopTarget:
    """One annotated object instance in one image.

    Attributes:
        scene_id, im_id, obj_id: the dataset's ids.
        gt_index: index of the instance in `scene_gt[im_id]` (the second number of its
            mask_visib file).
        camera_T_object: `(4, 4)` float64 the true pose, model -> camera, metres.
        visib_fract: visible fraction of the object's silhouette (1.0 without scene_gt_info).
    """

    scene_id: int
    im_id: int
    obj_id: int
    gt_index: int
    camera_T_object: np.ndarray
    visib_fract: float


@dataclasses.dataclass(frozen=True)
class _Camera:
    K: np.ndarray  # (3, 3) pixels
    depth_scale: float | None  # millimetres per depth count
    camera_T_world: np.ndarray | None  # (4, 4) metres


def _int_keys(path: Path, document, what: str) -> dict:
    if not isinstance(document, dict):
        raise ValueError(f"{path}: expected an object keyed by image id (the {what})")
    try:
        return {int(key): value for key, value in document.items()}
    except ValueError:
        raise ValueError(f"{path}: keys must be image ids (integers)") from None


def _pose(path: Path, label: str, rotation, translation) -> np.ndarray:
    """`(4, 4)` metres from a row-major rotation list and a translation list in mm."""
    matrix = np.eye(4)
    matrix[:3, :3] = numbers(path, f"{label} rotation", rotation, 9).reshape(3, 3)
    matrix[:3, 3] = numbers(path, f"{label} translation", translation, 3) * MM
    rot = matrix[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-4 or np.linalg.det(rot) < 0:
        raise ValueError(f"{path}: {label}: the rotation is not orthonormal with determinant +1")
    return matrix


def _cameras(path: Path) -> dict[int, _Camera]:
    cameras = {}
    for im_id, entry in _int_keys(path, load_json(path, "scene's cameras"), "cameras").items():
        where = f"image {im_id}"
        if not isinstance(entry, dict) or "cam_K" not in entry:
            raise ValueError(
                f"{path}: {where} has no cam_K (only pinhole intrinsics are read; BOP24's "
                "cam_model is not)"
            )
        scale = entry.get("depth_scale")
        if scale is not None and (isinstance(scale, bool) or not isinstance(scale, int | float)):
            raise ValueError(f"{path}: {where}: depth_scale must be a number, got {scale!r}")
        if scale is not None and not scale > 0:
            raise ValueError(f"{path}: {where}: depth_scale must be positive mm per count")
        world = None
        if "cam_R_w2c" in entry or "cam_t_w2c" in entry:
            world = _pose(
                path, f"{where}: cam_*_w2c", entry.get("cam_R_w2c"), entry.get("cam_t_w2c")
            )
        K = numbers(path, f"{where}: cam_K", entry["cam_K"], 9).reshape(3, 3)
        cameras[im_id] = _Camera(K, None if scale is None else float(scale), world)
    return cameras


def _ground_truth(path: Path, info_path: Path):
    """`{im_id: [(obj_id, camera_T_object, visib_fract)]}` from scene_gt (+ scene_gt_info)."""
    gts = _int_keys(path, load_json(path, "scene's ground-truth poses"), "poses")
    infos = {}
    if info_path.is_file():
        infos = _int_keys(info_path, load_json(info_path, "visibility"), "visibility")
    truth = {}
    for im_id, instances in gts.items():
        if not isinstance(instances, list):
            raise ValueError(f"{path}: image {im_id}: expected a list of object instances")
        info = infos.get(im_id, [{}] * len(instances))
        if not isinstance(info, list) or len(info) != len(instances):
            listed = len(info) if isinstance(info, list) else "no list of"
            raise ValueError(
                f"{info_path}: image {im_id} lists {listed} instances, scene_gt.json "
                f"{len(instances)}: the two files must describe the same instances"
            )
        rows = []
        for k, (gt, extra) in enumerate(zip(instances, info, strict=True)):
            where = f"image {im_id} instance {k}"
            obj_id = gt.get("obj_id") if isinstance(gt, dict) else None
            if not isinstance(obj_id, int) or isinstance(obj_id, bool):
                raise ValueError(f"{path}: {where} has no integer obj_id")
            pose = _pose(path, f"{where}: cam_*_m2c", gt.get("cam_R_m2c"), gt.get("cam_t_m2c"))
            visib = extra.get("visib_fract", 1.0) if isinstance(extra, dict) else 1.0
            if isinstance(visib, bool) or not isinstance(visib, int | float) or not 0 <= visib <= 1:
                raise ValueError(f"{info_path}: {where}: visib_fract must be a number in [0, 1]")
            rows.append((obj_id, pose, float(visib)))
        truth[im_id] = rows
    return truth


@dataclasses.dataclass(frozen=True, eq=False)
class BopSplit:
    """One split of a BOP dataset, as returned by `read_bop`; images are read on request.

    Attributes:
        root: the dataset's folder.
        split: the split's name (`"test"`, `"val"`, ...).
        models: `{obj_id: BopModel}` of every object with a target (or of `objects`).
        images: sorted `(scene_id, im_id)` of every image with at least one target.
    """

    root: Path
    split: str
    models: dict[int, BopModel]
    images: list[tuple[int, int]]
    _targets: dict[tuple[int, int], list[BopTarget]] = dataclasses.field(repr=False)
    _cameras: dict[int, dict[int, _Camera]] = dataclasses.field(repr=False)
    _size: tuple[int, int] | None = dataclasses.field(repr=False)  # (height, width)

    def _folder(self, scene_id: int) -> Path:
        return self.root / self.split / f"{scene_id:06d}"

    def _camera(self, scene_id: int, im_id: int) -> _Camera:
        try:
            return self._cameras[scene_id][im_id]
        except KeyError:
            raise ValueError(
                f"image ({scene_id}, {im_id}) is not in this split's scene_camera.json files "
                "(or its scene was not read: see read_bop's scenes)"
            ) from None

    def targets(self, scene_id: int | None = None, im_id: int | None = None) -> list[BopTarget]:
        """The targets of one image, of one scene (`im_id` None) or of the split (both None):
        test_targets_bop19.json's when the dataset has it, else every annotated instance."""
        return [
            target
            for key in self.images
            if (scene_id is None or key[0] == scene_id) and (im_id is None or key[1] == im_id)
            for target in self._targets[key]
        ]

    def intrinsics(self, scene_id: int, im_id: int) -> Intrinsics:
        """The image's pinhole `Intrinsics` (size from camera.json, else the depth PNG)."""
        K = self._camera(scene_id, im_id).K
        depth = self._depth_path(scene_id, im_id)
        height, width = self._size or read_image_size(depth, "depth image")
        return Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)

    def _depth_path(self, scene_id: int, im_id: int) -> Path:
        return self._folder(scene_id) / "depth" / f"{im_id:06d}.png"

    def depth(self, scene_id: int, im_id: int) -> np.ndarray:
        """`(H, W)` float64 depth in metres, 0 where the sensor has no measurement."""
        camera = self._camera(scene_id, im_id)
        path = self._depth_path(scene_id, im_id)
        if camera.depth_scale is None:
            raise ValueError(
                f"{self._folder(scene_id) / 'scene_camera.json'}: image {im_id} has no "
                "depth_scale (millimetres per depth count)"
            )
        counts = read_depth_counts(path, "BOP depth image")
        if self._size is not None and counts.shape != self._size:
            raise ValueError(
                f"{path}: the image is {counts.shape} (height, width) but camera.json says "
                f"{self._size}"
            )
        return counts * (camera.depth_scale * MM)

    def frame(self, scene_id: int, im_id: int) -> RGBDFrame:
        """The image as an `RGBDFrame`: float32 depth in metres (NaN holes), colour when the
        split has it, and `base_T_camera` from cam_*_w2c when given (the base is BOP's world
        frame), else the identity (the base is the camera)."""
        depth = self.depth(scene_id, im_id)
        intrinsics = self.intrinsics(scene_id, im_id)
        if depth.shape != intrinsics.shape:
            raise ValueError(f"{self._depth_path(scene_id, im_id)}: size differs from camera.json")
        rgb = None
        for suffix in (".png", ".jpg"):
            path = self._folder(scene_id) / "rgb" / f"{im_id:06d}{suffix}"
            if path.is_file():
                rgb = read_rgb(path)
                if rgb.shape[:2] != depth.shape:
                    raise ValueError(f"{path}: {rgb.shape[:2]} pixels, the depth {depth.shape}")
                break
        world = self._camera(scene_id, im_id).camera_T_world
        base_T_camera = None if world is None else np.linalg.inv(world)
        return RGBDFrame(depth.astype(np.float32), intrinsics, rgb=rgb, base_T_camera=base_T_camera)

    def mask(self, target: BopTarget) -> np.ndarray | None:
        """`(H, W)` bool visible mask of `target` (mask_visib), or None when the split has none."""
        name = f"{target.im_id:06d}_{target.gt_index:06d}.png"
        path = self._folder(target.scene_id) / "mask_visib" / name
        if not path.is_file():
            return None
        mask = read_mask(path)
        expected = self._size or read_image_size(
            self._depth_path(target.scene_id, target.im_id), "depth image"
        )
        if mask.shape != tuple(expected):
            raise ValueError(f"{path}: {mask.shape} pixels, the depth image {tuple(expected)}")
        return mask


def _scene_folders(split_dir: Path, scenes) -> dict[int, Path]:
    found = {int(p.name): p for p in split_dir.iterdir() if p.is_dir() and p.name.isdigit()}
    if scenes is None:
        chosen = sorted(found)
    else:
        chosen = sorted(int(s) for s in scenes)
        missing = [s for s in chosen if s not in found]
        if missing:
            raise ValueError(
                f"{split_dir}: no scene folders for {missing} (it has {sorted(found)})"
            )
    if not chosen:
        raise ValueError(f"{split_dir}: no scene folders (<scene_id:06d>/)")
    return {s: found[s] for s in chosen}


def _chosen_targets(root: Path, truth: dict, objects) -> dict[tuple[int, int], list[BopTarget]]:
    """Per image, the BOP19 targets (when test_targets_bop19.json exists) or every instance."""

    def target(scene_id, im_id, k):
        obj_id, pose, visib = truth[scene_id][im_id][k]
        return BopTarget(scene_id, im_id, obj_id, k, pose, visib)

    chosen: dict[tuple[int, int], list[BopTarget]] = {}
    path = root / "test_targets_bop19.json"
    if not path.is_file():
        for scene_id, images in truth.items():
            for im_id, rows in images.items():
                picked = [target(scene_id, im_id, k) for k in range(len(rows))]
                chosen[(scene_id, im_id)] = [
                    t for t in picked if objects is None or t.obj_id in objects
                ]
        return {key: value for key, value in chosen.items() if value}
    entries = load_json(path, "BOP19 target list")
    if not isinstance(entries, list):
        raise ValueError(f"{path}: expected a list of {{scene_id, im_id, obj_id, inst_count}}")
    for n, entry in enumerate(entries):
        keys = ("scene_id", "im_id", "obj_id", "inst_count")
        if not isinstance(entry, dict) or not all(isinstance(entry.get(k), int) for k in keys):
            raise ValueError(f"{path}: entry {n} needs integer {', '.join(keys)}")
        scene_id, im_id, obj_id, count = (entry[k] for k in keys)
        if scene_id not in truth or (objects is not None and obj_id not in objects):
            continue
        if im_id not in truth[scene_id]:
            raise ValueError(
                f"{path}: entry {n}: scene {scene_id} has no image {im_id} in scene_gt"
            )
        rows = truth[scene_id][im_id]
        # the inst_count most visible instances of the object (BOP counts an instance as
        # a target when at least 10% of it is visible)
        candidates = sorted(
            (k for k, row in enumerate(rows) if row[0] == obj_id), key=lambda k: -rows[k][2]
        )
        if len(candidates) < count:
            raise ValueError(
                f"{path}: entry {n} asks for {count} instances of object {obj_id} in image "
                f"({scene_id}, {im_id}); scene_gt.json has {len(candidates)}"
            )
        picked = [target(scene_id, im_id, k) for k in sorted(candidates[:count])]
        chosen.setdefault((scene_id, im_id), []).extend(picked)
    return chosen


def read_bop(
    root: str | Path,
    split: str = "test",
    *,
    objects: Iterable[int] | None = None,
    scenes: Iterable[int] | None = None,
) -> BopSplit:
    """Read a BOP dataset split in the scenewise layout (see the module docstring).

    Args:
        root: the dataset's folder (holding `models/` and the split folders).
        split: the split folder's name.
        objects: keep only the targets of these object ids (default all).
        scenes: read only these scene ids (default every scene folder).

    Returns:
        A `BopSplit`: its models are read now (metres), its images on request.

    Raises:
        ValueError: a missing folder or file, malformed JSON, a wrong-length or non-rotation
            pose, an object without a model, or a target list that disagrees with scene_gt.
    """
    root = Path(root)
    split_dir = root / split
    if not split_dir.is_dir():
        have = sorted(p.name for p in root.iterdir() if p.is_dir()) if root.is_dir() else []
        raise ValueError(
            f"{split_dir}: no such split folder (the dataset root {root} has {have}); pass the "
            "dataset's root and one of its splits"
        )
    objects = None if objects is None else {int(o) for o in objects}
    folders = _scene_folders(split_dir, scenes)
    cameras, truth = {}, {}
    for scene_id, folder in folders.items():
        cameras[scene_id] = _cameras(folder / "scene_camera.json")
        truth[scene_id] = _ground_truth(folder / "scene_gt.json", folder / "scene_gt_info.json")
        missing = sorted(set(truth[scene_id]) - set(cameras[scene_id]))
        if missing:
            raise ValueError(
                f"{folder / 'scene_camera.json'}: no camera for images {missing[:5]} of "
                "scene_gt.json"
            )
    targets = _chosen_targets(root, truth, objects)
    if not targets:
        raise ValueError(
            f"{split_dir}: no targets in scenes {sorted(folders)}"
            + ("" if objects is None else f" for objects {sorted(objects)}")
        )
    for scene_id, im_id in targets:
        depth = folders[scene_id] / "depth" / f"{im_id:06d}.png"
        if not depth.is_file():
            raise ValueError(f"{depth}: no such file (the depth image of a target)")
    size = None
    if (root / "camera.json").is_file():
        camera = load_json(root / "camera.json", "camera's image size")
        if not isinstance(camera, dict):
            raise ValueError(f"{root / 'camera.json'}: expected an object with width and height")
        width, height = numbers(
            root / "camera.json", "width, height", [camera.get("width"), camera.get("height")], 2
        ).astype(int)
        size = (int(height), int(width))
    obj_ids = {t.obj_id for rows in targets.values() for t in rows} | (objects or set())
    return BopSplit(
        root=root,
        split=split,
        models=read_models(root / "models", obj_ids),
        images=sorted(targets),
        _targets=targets,
        _cameras=cameras,
        _size=size,
    )
