"""Images from files: object masks, 16-bit depth counts and colour, read with Pillow.

One reader per kind of image, used wherever the library reads one (depth-PNG frames, BOP
splits, the command line's ``--mask``); each problem is a ``ValueError`` naming the file.

**Masks** (:func:`read_mask`) are one grey channel, nonzero = the object: 1-bit, 8-bit or
16-bit (Pillow modes ``1``, ``L``, ``I;16``, ``I;16B``, ``I;16L``, ``I``). An RGB, RGBA, grey
+ alpha or palette image is read as the same grey channel when it is one: every pixel grey
(R = G = B) and any alpha channel fully opaque. A colour image (a label image that tells several
objects apart by colour) or a transparent one is refused, not guessed at: its nonzero pixels
would be every labelled object at once, and transparency has no agreed meaning for a mask.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

__all__ = ["read_depth_counts", "read_image_size", "read_mask", "read_rgb"]

_GREY = ("1", "L", "I;16", "I;16B", "I;16L", "I")
_DEPTH = ("I;16", "I;16B", "I;16L", "I")


def _open(path: str | Path, what: str) -> Image.Image:
    """The image at ``path`` (lazily read by Pillow); ``what`` names it in errors."""
    try:
        return Image.open(path)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file (the {what})") from None
    except OSError as error:
        raise ValueError(f"{path}: the {what} is not a readable image ({error})") from None


def read_image_size(path: str | Path, what: str = "image") -> tuple[int, int]:
    """``(height, width)`` of the image at ``path``, read from its header only."""
    with _open(path, what) as image:
        return image.height, image.width


def read_mask(path: str | Path) -> np.ndarray:
    """``(H, W)`` bool mask of an image file: True where the object is (nonzero grey).

    See the module docstring for the images accepted: one grey channel of 1, 8 or 16 bits, or
    a colour or palette image whose pixels are all grey with any alpha fully opaque.

    Raises:
        ValueError: a missing or unreadable file, colours (R, G, B not all equal somewhere),
            transparency, or a mode that is not an image of levels (e.g. float).
    """
    with _open(path, "mask image") as image:
        mode = image.mode
        if mode in _GREY:
            return np.asarray(image) != 0
        if mode == "P":
            image = image.convert("RGBA")
        elif mode not in ("LA", "RGB", "RGBA"):
            raise ValueError(
                f"{path}: a mask must be a grey image (nonzero = the object), got Pillow mode "
                f"{mode!r}; save it as an 8-bit grey PNG"
            )
        values = np.asarray(image)
    has_alpha = values.shape[-1] in (2, 4)  # LA, RGBA (and palettes, converted to RGBA)
    levels = values[..., :-1] if has_alpha else values
    if has_alpha and np.any(values[..., -1] != np.iinfo(values.dtype).max):
        raise ValueError(
            f"{path}: the mask has transparent pixels; save it without an alpha channel as a "
            "grey PNG (nonzero = the object)"
        )
    if np.any(levels != levels[..., :1]):
        raise ValueError(
            f"{path}: the mask has colours (is it a label image of several objects?); save the "
            "one object's mask as a grey PNG (nonzero = the object)"
        )
    return levels[..., 0] != 0


def read_depth_counts(path: str | Path, what: str = "depth PNG") -> np.ndarray:
    """``(H, W)`` uint16 counts of a depth image: one 16-bit channel (0 = no depth); the
    counts' unit is the caller's (a depth scale). ``what`` names the image in errors.

    Raises:
        ValueError: a missing or unreadable file, or an image that is not one 16-bit channel.
    """
    with _open(path, what) as image:
        if image.mode not in _DEPTH:
            raise ValueError(
                f"{path}: a {what} must be one 16-bit channel of counts (Pillow mode I;16), got "
                f"mode {image.mode!r}: is it a colour image? Save depth as uint16 counts "
                "(millimetres with a depth scale of 0.001)"
            )
        counts = np.asarray(image)
    if counts.min() < 0 or counts.max() > np.iinfo(np.uint16).max:
        raise ValueError(f"{path}: depth counts outside 0..65535")
    return counts.astype(np.uint16)


def read_rgb(path: str | Path, what: str = "colour image") -> np.ndarray:
    """``(H, W, 3)`` uint8 colour image (grey and palette images converted to RGB)."""
    with _open(path, what) as image:
        return np.asarray(image.convert("RGB"))
