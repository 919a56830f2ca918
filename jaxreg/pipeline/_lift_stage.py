"""The lift stage of :func:`jaxreg.estimate_pose` (:func:`lift_stage`) and its host-side
work: a segment's pixels with depth lifted into the base frame, and the filters that drop
what a depth camera gets wrong at an object's edges (flying pixels between two surfaces,
points below the table band, isolated points).

Frames are :mod:`jaxreg.camera.model`'s: pixels ``(row, col)`` index the depth image, points are in
the frame's base frame (``base_T_camera`` applied). Everything is numpy except the lifting
itself, one stored program over a padded pixel list.
"""

from __future__ import annotations

import time

import numpy as np

from jaxreg.camera.model import RGBDFrame
from jaxreg.core._program_cache import persistent_jit
from jaxreg.core._sizes import pad_rows, power_of_two
from jaxreg.pipeline._stages import _Failed
from jaxreg.pipeline.records import LiftedSegment, LiftRecord
from jaxreg.pipeline.segment import TablePlane
from jaxreg.pipeline.settings import LiftSettings
from jaxreg.search.neighbors import voxel_downsample
from jaxreg.uncertainty import DepthNoise

__all__ = ["below_band", "lift_pixels", "lift_region", "lift_stage"]


def _flying(depth: np.ndarray, rows: np.ndarray, cols: np.ndarray, tolerance: np.ndarray, need):
    """Bool per pixel ``(rows, cols)``: fewer than ``need`` of its 8 neighbours have depth
    within ``tolerance`` (per pixel) of its own."""
    if len(rows) == 0:
        return np.zeros(0, bool)
    top, left = rows.min(), cols.min()
    h, w = rows.max() - top + 1, cols.max() - left + 1
    # the pixels' box and a border of one (NaN beyond the image: no neighbour there)
    around = np.full((h + 2, w + 2), np.nan, depth.dtype)
    r0, r1 = max(top - 1, 0), min(top + h + 1, depth.shape[0])
    c0, c1 = max(left - 1, 0), min(left + w + 1, depth.shape[1])
    around[r0 - top + 1 : r1 - top + 1, c0 - left + 1 : c1 - left + 1] = depth[r0:r1, c0:c1]
    allowed = np.zeros((h, w), np.asarray(tolerance).dtype)
    allowed[rows - top, cols - left] = tolerance
    centre = around[1:-1, 1:-1]
    consistent = np.zeros((h, w), np.int32)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                shifted = around[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
                consistent += np.abs(shifted - centre) <= allowed
    return consistent[rows - top, cols - left] < need


def _isolated(points: np.ndarray, voxel: float, need: int = 2) -> np.ndarray:
    """Bool per point: fewer than ``need`` other points' voxels among the 26 around its own."""
    keys = np.floor(points / voxel).astype(np.int64)
    keys -= keys.min(0) - 1
    dims = keys.max(0) + 2
    code = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    occupied = np.unique(code)
    count = np.zeros(len(points), np.int32)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                if dx == dy == dz == 0:
                    continue
                other = ((keys[:, 0] + dx) * dims[1] + keys[:, 1] + dy) * dims[2] + keys[:, 2] + dz
                idx = np.searchsorted(occupied, other)
                count += (idx < len(occupied)) & (
                    occupied[np.minimum(idx, len(occupied) - 1)] == other
                )
    return count < need


# Pixels lifted by one program: footprints pad to 2^15 pixels (an object of 8% of an 848x480
# image) or the next power of two, so every segment of a frame size shares a program or a few.
_PIXELS = 1 << 15


@persistent_jit
def _lift_pixels(frame: RGBDFrame, rows, cols):
    """Base-frame points ``(P, 3)`` of the given pixels (padded index arrays): one stored
    program per padded length."""
    return frame.points_at(rows, cols)


def lift_pixels(frame: RGBDFrame, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Base-frame points ``(P, 3)`` of the pixels ``(rows, cols)`` (NaN at holes), lifted
    in a list padded to a bucketed length (a few stored programs serve every count)."""
    size = power_of_two(len(rows), _PIXELS)  # the padding lifts pixel (0, 0), dropped
    r_pad, c_pad = (pad_rows(np.asarray(a, np.int32), size, 0) for a in (rows, cols))
    return np.asarray(_lift_pixels(frame, r_pad, c_pad))[: len(rows)]


@persistent_jit
def _project(intrinsics, camera_points):
    """Pixels ``(P, 2)`` of camera-frame points ``(P, 3)``: one stored program per padded
    length."""
    return intrinsics.project(camera_points)


def project_points(frame: RGBDFrame, camera_points: np.ndarray) -> np.ndarray:
    """Pixels ``(P, 2)`` (u, v; float) of camera-frame points ``(P, 3)`` (metres, z > 0)
    through ``frame``'s intrinsics and their distortion, projected in a list padded to a
    bucketed length (a few stored programs serve every count)."""
    count = len(camera_points)
    # the padding rows (1, 1, 1) lie in front of the camera: a finite projection
    padded = pad_rows(np.asarray(camera_points, np.float32), power_of_two(count, 1024), 1.0)
    return np.asarray(_project(frame.intrinsics, padded))[:count]


def _band_floor(sigma: np.ndarray, min_height: float, band_sigmas: float) -> np.ndarray:
    """The lowest height above the table (metres) a point with depth noise ``sigma`` (metres,
    any shape) keeps: ``max(min_height, band_sigmas sigma)``."""
    return np.maximum(min_height, band_sigmas * sigma)


def below_band(frame: RGBDFrame, region: np.ndarray, plane: TablePlane, noise, settings):
    """``(H, W)`` bool: the pixels of ``region`` ``(H, W)`` with depth that the lift's band
    leaves out as the table's (lower than :func:`_band_floor` above the ``plane``, or below
    it). ``noise``: the camera's ``DepthNoise``; ``settings``: ``LiftSettings``."""
    depth = np.asarray(frame.depth)
    rows, cols = np.nonzero(np.asarray(region, bool) & np.isfinite(depth))
    height = lift_pixels(frame, rows, cols) @ np.asarray(plane.normal) + float(plane.offset)
    sigma = noise.axial_sigma(depth[rows, cols])
    low = height <= _band_floor(sigma, settings.min_height, settings.band_sigmas)
    out = np.zeros(depth.shape, bool)
    out[rows[low], cols[low]] = True
    return out


def lift_region(
    frame: RGBDFrame,
    rows: np.ndarray,
    cols: np.ndarray,
    sigma: np.ndarray,
    plane_normal: np.ndarray | None,
    plane_offset: float | None,
    *,
    min_height: float,
    max_height: float,
    band_sigmas: float,
    voxel_size: float,
    min_consistent_neighbors: int,
) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """Lift the pixels ``(rows, cols)`` (each with depth; ``sigma`` its depth noise, metres)
    into the base frame and filter them: flying pixels (fewer than
    ``min_consistent_neighbors`` of 8 neighbours within ``max(4 mm, 4 sigma)``), points not
    between ``max(min_height, band_sigmas sigma)`` and ``max_height`` above the plane
    ``n . x + d = 0`` (no such filter when ``plane_normal`` is ``None``: a frame without a
    table), a ``voxel_size`` downsample, and isolated voxels.

    Returns ``(mask, points, counts)``: ``(H, W)`` bool of the pixels kept, ``(K, 3)``
    float32 base-frame points, and the counts of pixels kept and removed by each filter.
    """
    depth = np.asarray(frame.depth)
    shape = depth.shape
    flying = _flying(depth, rows, cols, np.maximum(0.004, 4 * sigma), min_consistent_neighbors)
    rows, cols, sigma = rows[~flying], cols[~flying], sigma[~flying]
    lifted = lift_pixels(frame, rows, cols)
    if plane_normal is None:
        band = np.ones(len(lifted), bool)
    else:
        height = lifted @ plane_normal + plane_offset
        band = (height > _band_floor(sigma, min_height, band_sigmas)) & (height < max_height)
    rows, cols, lifted = rows[band], cols[band], lifted[band]
    mask = np.zeros(shape, bool)
    mask[rows, cols] = True
    points = voxel_downsample(lifted, voxel_size) if len(lifted) else np.zeros((0, 3))
    isolated = _isolated(points, voxel_size) if len(points) else np.zeros(0, bool)
    points = points[~isolated].astype(np.float32)
    counts = {
        "pixels": int(len(rows)),
        "flying_pixels_removed": int(flying.sum()),
        "below_band_removed": int((~band).sum()),
        "isolated_points_removed": int(isolated.sum()),
        "points": int(len(points)),
    }
    return mask, points, counts


def lift_stage(
    frame, region, plane: TablePlane | None, noise: DepthNoise, settings: LiftSettings,
    voxel_size: float, max_height: float = np.inf,
) -> LiftedSegment:  # fmt: skip
    """The lift stage of :func:`jaxreg.estimate_pose`: the segment's footprint ``region``
    ``(H, W)`` lifted and filtered (:func:`lift_region`; the band above the ``plane``, if any,
    up to ``max_height`` metres) and voxelled at ``voxel_size``. Raises ``_Failed`` with too
    little valid depth or too few points left."""
    s = settings
    start = time.perf_counter()
    depth = np.asarray(frame.depth)
    rows, cols = np.nonzero(region)
    has_depth = np.isfinite(depth[rows, cols])
    valid_fraction = float(has_depth.mean()) if len(rows) else 0.0
    rows, cols = rows[has_depth], cols[has_depth]
    record = LiftRecord(
        ms=0.0, footprint_pixels=int(region.sum()), valid_depth_fraction=round(valid_fraction, 3)
    )
    if valid_fraction < s.min_valid_fraction:
        raise _Failed(
            "lift",
            f"too little valid depth: {valid_fraction:.0%} of the segment's {int(region.sum())} "
            f"pixels have depth (need {s.min_valid_fraction:.0%}); dark, shiny or grazing "
            "surfaces, or the object too near the camera",
            record.with_ms(start),
            mask=region,
        )
    sigma = noise.axial_sigma(depth[rows, cols])
    normal, offset = (None, None) if plane is None else (np.asarray(plane.normal), plane.offset)
    mask, points, counts = lift_region(
        frame, rows, cols, sigma, normal, None if offset is None else float(offset),
        min_height=s.min_height, max_height=max_height, band_sigmas=s.band_sigmas,
        voxel_size=voxel_size,
        min_consistent_neighbors=s.min_consistent_neighbors,
    )  # fmt: skip
    record = record.with_ms(start, **counts)
    if len(points) < s.min_segment_points:
        raise _Failed(
            "lift",
            f"only {len(points)} points left after filtering (need {s.min_segment_points}): "
            "the segment is too small or too noisy to register",
            record,
            mask=mask,
            points=points,
        )
    return LiftedSegment(mask, points, record)
