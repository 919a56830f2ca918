"""YCB-Video frames (real RGB-D captures with annotated object poses) and PoseCNN's point models.

Public through `jaxreg.io.read_ycbv`, `jaxreg.io.read_ycbv_models`, `YcbvFrame` and
`YcbvInstance`. Host side; everything returned is in metres and a missing or malformed file
raises `ValueError` naming it and what is wrong.

The layout read here (the dataset's own)::

    ROOT/data/<sequence>/<frame>-color.png   8-bit RGB
    ROOT/data/<sequence>/<frame>-depth.png   16-bit counts registered to the colour image;
                                             metres = count / factor_depth, 0 = no return
    ROOT/data/<sequence>/<frame>-label.png   8-bit class index per pixel (0 = none)
    ROOT/data/<sequence>/<frame>-meta.mat    MATLAB v5: intrinsic_matrix (3, 3) pixels,
                                             factor_depth (counts per metre), cls_indexes
                                             (N, 1), poses (3, 4, N) [R | t] model -> camera
    ROOT/data/<sequence>/<frame>-box.txt     optional: "<model name> x1 y1 x2 y2" per line, each
                                             object's 2D box (pixels, x = column, y = row)
    ROOT/models/models.txt                   one line per class (line c = class index c), the
                                             model's folder name as the path's parent folder
    ROOT/models/<name>/points.xyz            surface points "x y z" per line, metres

`<frame>` is the frame id (digits, ``000001``). The instances of a frame are those of its
``cls_indexes``; an instance's mask is ``label == class_index``: the annotation's mask, which
like any segmenter's holds a few background and occluder pixels at its edges. An instance's
box is its model's line of the box file: the annotation's box, which holds the whole mask and,
where an occluder hides part of the object, may reach past it.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np

from jaxreg.camera.model import Intrinsics, RGBDFrame
from jaxreg.geometry.lie import SE3
from jaxreg.io.images import _open, read_depth_counts, read_rgb

__all__ = ["YcbvFrame", "YcbvInstance", "read_ycbv", "read_ycbv_models"]

# The dataset's 21 classes in the order of its models.txt (class index = position + 1): the
# names when no models folder is found.
CLASS_NAMES = (
    "002_master_chef_can", "003_cracker_box", "004_sugar_box", "005_tomato_soup_can",
    "006_mustard_bottle", "007_tuna_fish_can", "008_pudding_box", "009_gelatin_box",
    "010_potted_meat_can", "011_banana", "019_pitcher_base", "021_bleach_cleanser", "024_bowl",
    "025_mug", "035_power_drill", "036_wood_block", "037_scissors", "040_large_marker",
    "051_large_clamp", "052_extra_large_clamp", "061_foam_brick",
)  # fmt: skip
_FILE = re.compile(r"(\d+)-(color|depth|label|meta)\.(png|mat)")
_META_KEYS = ("intrinsic_matrix", "factor_depth", "cls_indexes", "poses")
# Largest |R^T R - I| entry of an annotated rotation (the files store float64 rotations).
_ROTATION_TOLERANCE = 1e-4


@dataclasses.dataclass(frozen=True, eq=False)
class YcbvInstance:
    """One annotated object in one frame.

    Attributes:
        class_index: the object's class, 1-21: its line in ``models.txt``.
        model_name: the model's folder name, e.g. ``"025_mug"``.
        mask: ``(H, W)`` bool, ``label == class_index``.
        truth: ``SE3`` ``camera_T_object`` (= ``base_T_object``: the frame's base is its
            camera), model frame -> camera frame, metres.
        model_points: ``(M, 3)`` float32 model surface points (metres, object frame), or
            ``None`` when no models folder was found.
        box: ``(u0, v0, u1, v1)`` the object's 2D box from the frame's ``-box.txt`` (pixels:
            ``u`` columns, ``v`` rows, ``u0 <= u1``, ``v0 <= v1``), or ``None`` when the frame
            has no box file or the file does not list the object.
    """

    class_index: int
    model_name: str
    mask: np.ndarray
    truth: SE3
    model_points: np.ndarray | None
    box: tuple[float, float, float, float] | None


@dataclasses.dataclass(frozen=True, eq=False)
class YcbvFrame:
    """One YCB-Video frame with its annotated instances.

    Attributes:
        name: ``"<sequence>/<frame id>"``, e.g. ``"0000/000001"``.
        frame: the ``RGBDFrame``: depth in metres (NaN where the sensor had no return), the
            meta file's pinhole intrinsics without distortion, ``rgb`` ``(H, W, 3)`` uint8 and
            the identity ``base_T_camera``.
        label: ``(H, W)`` uint8 class index per pixel (0 = none).
        instances: the annotated objects, in the order of the meta file's ``cls_indexes``.
    """

    name: str
    frame: RGBDFrame
    label: np.ndarray
    instances: tuple[YcbvInstance, ...]


def read_ycbv_models(folder: str | Path) -> dict[str, np.ndarray]:
    """PoseCNN's point models: ``{name: (M, 3) float32 points}`` in ``models.txt``'s order.

    Args:
        folder: the folder holding ``models.txt`` and ``<name>/points.xyz`` (metres).

    Raises:
        ValueError: ``models.txt`` or a ``points.xyz`` is missing, or a points file is not
            rows of three finite numbers.
    """
    folder = Path(folder)
    listing = folder / "models.txt"
    try:
        lines = [line.strip() for line in listing.read_text().splitlines() if line.strip()]
    except FileNotFoundError:
        raise ValueError(
            f"{listing}: no such file (the YCB-Video models' list); pass the models folder "
            "holding models.txt and <name>/points.xyz"
        ) from None
    if not lines:
        raise ValueError(f"{listing}: empty; it lists one model per line")
    models = {}
    for line in lines:
        # A line is a model file's path (data/LOV/models/<name>/textured_simple.obj) or a name.
        name = Path(line).parent.name if "/" in line else line
        models[name] = _read_points(folder / name / "points.xyz")
    return models


def _read_points(path: Path) -> np.ndarray:
    try:
        points = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file (a model's points, listed in models.txt)") from None
    except ValueError as error:
        raise ValueError(f"{path}: not rows of 'x y z' numbers ({error})") from None
    if points.shape[1:] != (3,) or len(points) == 0 or not np.isfinite(points).all():
        raise ValueError(
            f"{path}: expected rows of three finite numbers (x y z, metres), got an array of "
            f"shape {points.shape}"
        )
    return points.astype(np.float32)


def _read_label(path: Path) -> np.ndarray:
    """``(H, W)`` uint8 class indices of a label PNG (one 8-bit channel)."""
    with _open(path, "label image") as image:
        if image.mode != "L":
            raise ValueError(
                f"{path}: a label image must be one 8-bit channel of class indices (Pillow "
                f"mode L), got mode {image.mode!r}"
            )
        return np.asarray(image, dtype=np.uint8)


def _read_boxes(path: Path) -> dict[str, tuple[float, float, float, float]]:
    """``{model name: (u0, v0, u1, v1)}`` (pixels) of a box file, ``{}`` when there is none."""
    if not path.is_file():
        return {}
    boxes = {}
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        name, *corners = line.split()
        try:
            u0, v0, u1, v1 = (float(value) for value in corners)
        except ValueError:
            raise ValueError(
                f"{path}: line {number} is not '<model name> x1 y1 x2 y2' (pixels): {line!r}"
            ) from None
        if not (np.isfinite([u0, v0, u1, v1]).all() and u0 <= u1 and v0 <= v1):
            raise ValueError(f"{path}: line {number}'s box is not finite corners with x1 <= x2 "
                             f"and y1 <= y2: {line!r}")  # fmt: skip
        boxes[name] = (u0, v0, u1, v1)
    return boxes


def _meta_array(path: Path, meta: dict, key: str, shape: tuple | None) -> np.ndarray:
    if key not in meta:
        raise ValueError(f"{path}: no {key!r} (a YCB-Video meta file holds "
                         f"{', '.join(_META_KEYS)})")  # fmt: skip
    value = np.asarray(meta[key])
    if not np.issubdtype(value.dtype, np.number) or (shape is not None and value.shape != shape):
        raise ValueError(f"{path}: {key} must be a numeric array of shape {shape}, got "
                         f"{value.dtype} {value.shape}")  # fmt: skip
    if not np.isfinite(value).all():
        raise ValueError(f"{path}: {key} holds non-finite values")
    return value


def _read_meta(path: Path):
    """``(K (3, 3), factor_depth, class indices (N,), camera_T_object (N, 4, 4))``."""
    from scipy.io import loadmat  # loaded on first use: scipy.io takes a while to import

    if not path.is_file():
        raise ValueError(f"{path}: no such file (the frame's meta file)")
    try:
        meta = loadmat(path, variable_names=list(_META_KEYS))
    except Exception as error:  # scipy raises ValueError, TypeError, OSError... on bad files
        raise ValueError(f"{path}: not a readable MATLAB file ({error})") from None
    K = _meta_array(path, meta, "intrinsic_matrix", (3, 3)).astype(np.float64)
    if not (K[0, 0] > 0 and K[1, 1] > 0) or K[0, 1] != 0 or np.any(K[2] != (0, 0, 1)):
        raise ValueError(f"{path}: intrinsic_matrix is not a pinhole K without skew: {K.tolist()}")
    factor = _meta_array(path, meta, "factor_depth", None)
    factor = float(factor.ravel()[0]) if factor.size == 1 else np.nan
    if not factor > 0:
        raise ValueError(f"{path}: factor_depth must be one positive number (counts per metre)")
    classes = _meta_array(path, meta, "cls_indexes", None)
    classes = classes.reshape(-1)
    if np.any(classes != np.round(classes)) or np.any(classes < 1):
        raise ValueError(f"{path}: cls_indexes must be positive integers, got {classes.tolist()}")
    poses = _meta_array(path, meta, "poses", None)
    if poses.shape == (3, 4) and len(classes) == 1:
        poses = poses[..., None]
    if poses.shape != (3, 4, len(classes)):
        raise ValueError(f"{path}: poses has shape {poses.shape}; with {len(classes)} "
                         f"cls_indexes it must be (3, 4, {len(classes)})")  # fmt: skip
    matrices = np.zeros((len(classes), 4, 4))
    matrices[:, :3, :] = np.moveaxis(poses.astype(np.float64), -1, 0)
    matrices[:, 3, 3] = 1.0
    rotations = matrices[:, :3, :3]
    drift = np.abs(rotations.transpose(0, 2, 1) @ rotations - np.eye(3)).max(initial=0.0)
    if drift > _ROTATION_TOLERANCE or np.any(np.linalg.det(rotations) < 0):
        raise ValueError(f"{path}: poses[:, :3, i] are not rotations (|R^T R - I| up to "
                         f"{drift:.2g}, or a reflection)")  # fmt: skip
    return K, factor, classes.astype(int), matrices


def _read_frame(prefix: Path, name: str, models: dict[str, np.ndarray] | None) -> YcbvFrame:
    K, factor, classes, poses = _read_meta(Path(f"{prefix}-meta.mat"))
    depth_path = Path(f"{prefix}-depth.png")
    counts = read_depth_counts(depth_path)
    height, width = counts.shape
    rgb_path, label_path = Path(f"{prefix}-color.png"), Path(f"{prefix}-label.png")
    rgb, label = read_rgb(rgb_path), _read_label(label_path)
    for path, image in ((rgb_path, rgb), (label_path, label)):
        if image.shape[:2] != (height, width):
            raise ValueError(f"{path}: {image.shape[1]}x{image.shape[0]} (width x height), but "
                             f"the depth image {depth_path.name} is {width}x{height}")  # fmt: skip
    names = list(models) if models is not None else CLASS_NAMES
    if classes.max(initial=0) > len(names):
        raise ValueError(f"{prefix}-meta.mat: class index {classes.max()} but only {len(names)} "
                         "models are listed (models.txt)")  # fmt: skip
    intrinsics = Intrinsics(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)
    depth = np.where(counts > 0, counts / factor, np.nan).astype(np.float32)
    boxes = _read_boxes(Path(f"{prefix}-box.txt"))
    instances = tuple(
        YcbvInstance(
            class_index=int(c),
            model_name=names[c - 1],
            mask=label == c,
            truth=SE3.from_matrix(pose),
            model_points=None if models is None else models[names[c - 1]],
            box=boxes.get(names[c - 1]),
        )
        for c, pose in zip(classes, poses, strict=True)
    )
    return YcbvFrame(name, RGBDFrame(depth, intrinsics, rgb=rgb), label, instances)


def _frame_ids(folder: Path) -> list[str]:
    """The frame ids of a sequence folder (any of the four files names one), in order."""
    ids = {m[1] for p in folder.iterdir() if (m := _FILE.fullmatch(p.name))}
    return sorted(ids, key=lambda i: (int(i), i))


def _prefixes(path: Path) -> list[tuple[Path, str]]:
    """``(file prefix, frame name)`` of every frame that ``path`` names, sorted."""
    if not path.is_dir():
        match = re.fullmatch(r"(\d+)(-(color|depth|label)\.png|-meta\.mat)?", path.name)
        if match is None or not path.parent.is_dir():
            raise ValueError(
                f"{path}: no such folder or frame; pass a YCB-Video sequence folder "
                "(holding NNNNNN-color.png, -depth.png, -label.png, -meta.mat), one frame's "
                "prefix (.../0000/000001) or the dataset root holding data/<sequence>/"
            )
        return [(path.parent / match[1], f"{path.parent.name}/{match[1]}")]
    if _frame_ids(path):
        return [(path / i, f"{path.name}/{i}") for i in _frame_ids(path)]
    data = path / "data" if (path / "data").is_dir() else path
    sequences = sorted(p for p in data.iterdir() if p.is_dir() and _frame_ids(p))
    if not sequences:
        raise ValueError(
            f"{path}: no YCB-Video frames (files NNNNNN-color.png, -depth.png, -label.png, "
            "-meta.mat) in it, nor in its data/<sequence>/ or <sequence>/ folders"
        )
    return [(seq / i, f"{seq.name}/{i}") for seq in sequences for i in _frame_ids(seq)]


def _find_models(path: Path) -> Path | None:
    """The ``models/`` folder beside a ``data/`` folder at ``path`` or above it."""
    for folder in (path, *path.parents):
        if (folder / "models" / "models.txt").is_file() and (folder / "data").is_dir():
            return folder / "models"
    return None


def read_ycbv(path: str | Path, *, models: str | Path | None = None) -> list[YcbvFrame]:
    """Read YCB-Video frames with their annotated instances (see the module docstring).

    Args:
        path: a sequence folder (``.../data/0000``), one frame's prefix
            (``.../data/0000/000001``, or one of its files), or the dataset root holding
            ``data/<sequence>/`` (or a folder of sequence folders).
        models: the folder of ``models.txt`` and ``<name>/points.xyz``; default: the
            ``models/`` beside ``data/``, found walking up from ``path``; when there is none,
            the instances' ``model_points`` are ``None``.

    Returns:
        The frames sorted by (sequence, frame id).

    Raises:
        ValueError: no frames at ``path``; a frame's file missing or malformed (the message
            names the file); a class index beyond the models' list.
    """
    path = Path(path)
    prefixes = _prefixes(path)
    if models is None:
        found = _find_models(path if path.is_dir() else path.parent)
        loaded = None if found is None else read_ycbv_models(found)
    else:
        loaded = read_ycbv_models(models)
    return [_read_frame(prefix, name, loaded) for prefix, name in prefixes]
