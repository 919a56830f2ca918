"""Checked reads of the BOP format's files: JSON documents, their number lists, and the PNGs
(16-bit depth, 8-bit masks and colour). Host side; every problem is a ``ValueError`` naming the
file, what is wrong and what to try."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
from PIL import Image

__all__ = ["load_json", "numbers", "read_counts", "read_image_size", "read_mask", "read_rgb"]


def load_json(path: Path, what: str):
    """The parsed JSON document at `path`; `what` names the file's role in the error."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise ValueError(
            f"{path}: no such file (the {what}); is the dataset complete and is the path its "
            "root folder (the one holding models/ and the split folders)?"
        ) from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not valid JSON ({error}); re-extract the {what}") from None


def numbers(path: Path, label: str, values, count: int) -> np.ndarray:
    """`values` as `(count,)` float64, checked to be a list of `count` finite numbers; `label`
    says where in the file they are (``"image 3: cam_K"``)."""
    valid = isinstance(values, list) and all(
        isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in values
    )
    if not valid or len(values) != count:
        if values is None:
            shown = "nothing (the key is missing)"
        else:
            shown = f"{len(values)} values" if isinstance(values, list) else repr(values)[:40]
        raise ValueError(f"{path}: {label} must be a list of {count} finite numbers, got {shown}")
    return np.asarray(values, dtype=np.float64)


def _open(path: Path, what: str) -> Image.Image:
    try:
        return Image.open(path)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file (the {what})") from None
    except OSError as error:
        raise ValueError(f"{path}: not a readable image ({error}); the {what}") from None


def read_image_size(path: Path, what: str) -> tuple[int, int]:
    """`(height, width)` of the image at `path`, read from its header only."""
    with _open(path, what) as image:
        return image.height, image.width


def read_counts(path: Path) -> np.ndarray:
    """`(H, W)` uint16 counts of a BOP depth PNG (one 16-bit channel)."""
    with _open(path, "depth image") as image:
        if image.mode not in ("I;16", "I;16B", "I;16L", "I"):
            raise ValueError(
                f"{path}: a BOP depth image must be one 16-bit channel of counts (Pillow mode "
                f"I;16), got mode {image.mode!r}; is this the colour image saved under depth/?"
            )
        counts = np.asarray(image)
    if counts.min() < 0 or counts.max() > np.iinfo(np.uint16).max:
        raise ValueError(f"{path}: depth counts outside 0..65535")
    return counts.astype(np.uint16)


def read_mask(path: Path) -> np.ndarray:
    """`(H, W)` bool of a mask PNG (one channel, nonzero = the object)."""
    with _open(path, "mask") as image:
        if image.mode not in ("1", "L", "I;16", "I"):
            raise ValueError(
                f"{path}: a mask must be one channel (Pillow mode L or 1), got {image.mode!r}"
            )
        return np.asarray(image) > 0


def read_rgb(path: Path) -> np.ndarray:
    """`(H, W, 3)` uint8 colour image."""
    with _open(path, "colour image") as image:
        return np.asarray(image.convert("RGB"))
