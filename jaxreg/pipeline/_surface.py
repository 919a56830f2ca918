"""The object's surface inside a caller's mask.

A segmenter's mask is evidence, not truth: its border holds pixels of the background behind
the object and of occluders in front of it (a label drawn by hand or predicted by a network
misses the silhouette by a pixel or two, and a depth camera's silhouette is blurred by its
matching window). Those pixels lie across a depth discontinuity from the object's surface.
:func:`mask_surface` keeps the pixels that the depth image connects to the object: two
4-neighbouring pixels are on one surface when their depths differ by less than
:func:`depth_step` at their depth (the noise of both, and the step of a surface slanted up to
``MAX_SLANT_DEG`` to the ray). The largest such surface is the object, with the pieces of it
an occluder splits off (surfaces of a quarter of its size or more, at its depth).

Pixels are ``(row, col)`` of the depth image; depths are metres along the camera's axis.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from jaxreg.uncertainty import DepthNoise

__all__ = ["depth_step", "mask_surface"]

# The steepest surface (degrees between its normal and the ray) whose depth step between
# neighbouring pixels is still one surface: beyond it a depth camera returns few pixels.
MAX_SLANT_DEG = 75.0
# Depth noise allowed in a step between two pixels, in standard deviations of their difference.
STEP_SIGMAS = 4.0
# A piece of the mask's surface joins the largest when it has this share of its pixels.
PIECE_SHARE = 0.25


def depth_step(depth: np.ndarray, sigma_z: np.ndarray, focal: float) -> np.ndarray:
    """The largest depth difference (metres) between neighbouring pixels of one surface at
    ``depth`` (metres, any shape): ``STEP_SIGMAS`` standard deviations of the difference of
    two noisy depths (``sqrt(2) sigma_z``) plus the step of a surface slanted
    ``MAX_SLANT_DEG`` to the ray across one pixel (``depth / focal`` metres wide).
    ``sigma_z``: the depth noise's standard deviation at ``depth`` (metres)."""
    slant = np.tan(np.radians(MAX_SLANT_DEG))
    return STEP_SIGMAS * np.sqrt(2.0) * sigma_z + depth / focal * slant


def mask_surface(
    depth: np.ndarray, mask: np.ndarray, noise: DepthNoise, focal: float
) -> np.ndarray:
    """``(H, W)`` bool: the pixels of ``mask`` ``(H, W)`` with depth that lie on the object's
    surface (see the module docstring). ``depth`` ``(H, W)`` metres with NaN holes;
    ``noise``: the camera's depth noise (its ``axial_sigma``); ``focal``: the focal length
    (pixels). Holes and pixels off the surface are False; an empty mask gives an empty
    surface."""
    valid = np.asarray(mask, bool) & np.isfinite(depth)
    out = np.zeros(valid.shape, bool)
    rows, cols = np.flatnonzero(valid.any(1)), np.flatnonzero(valid.any(0))
    if len(rows) == 0:
        return out
    box = np.s_[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]
    valid = valid[box]
    z = np.where(valid, np.asarray(depth, np.float64)[box], 0.0)
    sigma = noise.axial_sigma(z)
    limit = depth_step(z, sigma, focal)
    # pixels at even rows and columns of a grid twice the size, the links between 4-neighbours
    # on one surface between them: its 4-connected components are the surfaces, labelled in
    # the order of their first pixel
    h, w = valid.shape
    grid = np.zeros((2 * h - 1, 2 * w - 1), bool)
    grid[::2, ::2] = valid
    for axis, links in ((1, grid[::2, 1::2]), (0, grid[1::2, ::2])):
        a, b = (np.s_[:, :-1], np.s_[:, 1:]) if axis else (np.s_[:-1], np.s_[1:])
        links[...] = (
            valid[a] & valid[b] & (np.abs(z[a] - z[b]) <= np.minimum(limit[a], limit[b]))
        )  # fmt: skip
    labels, count = ndimage.label(grid)
    labels = labels[::2, ::2][valid] - 1
    z = z[valid]
    sizes = np.bincount(labels, minlength=count)
    largest = int(np.argmax(sizes))
    near, far = np.percentile(z[labels == largest], [2, 98])
    keep = np.zeros(count, bool)
    keep[largest] = True
    for k in np.flatnonzero(sizes >= PIECE_SHARE * sizes[largest]):
        middle = np.median(z[labels == k])
        keep[k] |= bool(near - (far - near) <= middle <= far + (far - near))
    out[box][valid] = keep[labels]
    return out
