"""The segment stage's colour cue: whether a candidate's pixels show the model's colours.

Colours are compared by chromaticity, each sRGB channel over the sum of the three: under white
light a surface's shading scales its three display values alike (``(albedo * light)^gamma`` is
``albedo^gamma * light^gamma``), so a lit face and one in shade of the same paint share it,
and the depth image's look-alikes of another colour do not. A pixel is judged when it is bright
enough that its 8-bit counts fix the chromaticity to a third of the tolerance (a channel's
rounding moves it by about one over the sum of the counts) and no channel is clipped at 255
(a clipped channel's share is not the paint's).

Conventions: colours are sRGB; the frame's ``rgb`` is ``(H, W, 3)`` uint8, a model's colours
``(M, 3)`` (one per model point, as a textured model's vertex colours) or ``(3,)`` (one paint),
floats in [0, 1] or uint8 counts.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

__all__ = ["colour_match", "model_palette", "other_colour"]


def model_palette(model_colors, points: int) -> np.ndarray:
    """The distinct chromaticities ``(K, 2)`` (red and green shares, rounded to 0.005) of
    ``model_colors`` ``(M, 3)`` (``M`` = ``points``, the model's) or ``(3,)`` (see the module),
    or ``ValueError``: another shape, non-finite values, floats outside [0, 1], or only black
    (no chromaticity)."""
    colors = np.asarray(model_colors)
    if colors.ndim == 1:
        colors = colors[None]
    elif colors.ndim == 2 and len(colors) != points:
        raise ValueError(
            f"model_colors holds {len(colors)} colours for {points} model points: give one per "
            "point, or one (3,) colour for the whole model"
        )
    if colors.ndim != 2 or colors.shape[1] != 3 or len(colors) == 0:
        raise ValueError(
            f"model_colors must be (M, 3) (one sRGB colour per model point) or (3,), got shape "
            f"{np.shape(model_colors)}"
        )
    if colors.dtype == np.uint8:
        colors = colors / 255.0
    elif not np.issubdtype(colors.dtype, np.floating):
        raise ValueError(f"model_colors must be floats in [0, 1] or uint8, got {colors.dtype}")
    elif not (np.all(np.isfinite(colors)) and colors.min() >= 0.0 and colors.max() <= 1.0):
        raise ValueError(
            "model_colors must be sRGB floats in [0, 1] (a PLY's 0-255 vertex colours as "
            f"uint8, or divided by 255), got values in [{np.nanmin(colors):.3g}, "
            f"{np.nanmax(colors):.3g}]"
        )
    total = colors.sum(1)
    lit = total > 0
    if not lit.any():
        raise ValueError("model_colors are all black: black has no chromaticity to compare")
    shares = colors[lit, :2] / total[lit, None]
    return np.unique(np.round(shares / 0.005) * 0.005, axis=0)


def colour_match(pixels: np.ndarray, palette: np.ndarray, tolerance: float):
    """Which of ``pixels`` ``(..., 3)`` (uint8 sRGB) are judged (see the module) and which of
    those show a colour of the ``palette`` (:func:`model_palette`: chromaticity within
    ``tolerance`` of one of its): two bool arrays ``(...)``."""
    counts = np.asarray(pixels, np.float64)
    total = counts.sum(-1)
    judged = (total >= 3.0 / tolerance) & (counts.max(-1) < 255)
    shares = counts[judged][:, :2] / total[judged][:, None]
    near, _ = cKDTree(palette).query(shares, distance_upper_bound=tolerance)
    match = np.zeros(judged.shape, bool)
    match[judged] = np.isfinite(near)
    return judged, match


def other_colour(judged: np.ndarray, match: np.ndarray, within: np.ndarray, rim: int):
    """``(H, W)`` bool: the pixels of ``within`` (``(H, W)`` bool) that show another colour
    than the model's (``judged`` and ``match``: :func:`colour_match` of the image), a pixel
    too dark or clipped to judge taking the verdict of the nearest judged pixel of ``within``
    (a face in shade beside the lit faces of the same object), in pieces wider than
    ``2 rim + 1`` pixels: a rim narrower than that along a silhouette is the depth and the
    colour disagreeing about the edge (a stereo camera's edges fatten, a registration is a
    pixel off), not a neighbour. Nothing when no pixel of ``within`` is judged."""
    judged = judged & within
    if not judged.any():
        return np.zeros(within.shape, bool)
    rows, cols = ndimage.distance_transform_edt(~judged, return_distances=False,
                                                return_indices=True)  # fmt: skip
    other = within & ~match[rows, cols]
    return ndimage.binary_opening(other, np.ones((2 * rim + 1, 2 * rim + 1), bool))
