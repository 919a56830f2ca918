"""What the stages of :func:`jaxreg.estimate_pose` share: its settings (one frozen record
built by keyword), the failure that stops the pipeline, the padded clouds given to compiled
code, and the stage clock.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

# depth agreement (metres) of the image's judgement of a pose; more where the depth noise's
# NOISE_SIGMAS sigma_z(z) is more (see visibility)
_TOLERANCE = np.float32(0.01)


@dataclasses.dataclass(frozen=True)
class _Settings:
    """:func:`estimate_pose`'s keyword settings, as its stages read them."""

    pixel: tuple[float, float] | None
    box: tuple[float, float, float, float] | None
    voxel_size: float
    stride: int
    plane_distance: float
    min_height: float
    lift_min_height: float
    cluster_distance: float
    cluster_margin: float
    max_candidates: int
    num_starts: int
    resting_yaws: int
    coarse_points: int
    coarse_screen: int
    coarse_survivors: int
    coarse_first: int
    coarse_keep: int
    max_points: int
    min_segment_points: int
    min_valid_fraction: float
    min_consistent_neighbors: int
    min_inlier_fraction: float
    max_inlier_rmse: float
    max_contradicted: float
    max_overhang: float
    rest_tolerance: float = 0.015
    refined_starts: int = 4
    coarse_distances: np.ndarray = dataclasses.field(
        default_factory=lambda: np.geomspace(0.04, 0.01, 20).astype(np.float32)
    )

    @property
    def fine_distances(self) -> np.ndarray:
        """The refinement's correspondence distances (metres, 15 mm down to 1.5 voxels)."""
        return np.geomspace(0.015, 1.5 * self.voxel_size, 30).astype(np.float32)


class _Failed(Exception):
    """A stage found no pose to claim: its name, the reason, and what it had segmented."""

    def __init__(self, stage: str, reason: str, mask=None, points=None):
        super().__init__(reason)
        self.stage, self.reason, self.mask, self.points = stage, reason, mask, points


def _padded(points: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """``(size, 3)`` float32: ``points`` subsampled (without replacement) when longer, NaN
    rows (ignored by ICP) after them when shorter."""
    if len(points) > size:
        points = points[np.sort(rng.choice(len(points), size, replace=False))]
    out = np.full((size, 3), np.nan, np.float32)
    out[: len(points)] = points
    return out


def _ms(start: float) -> float:
    return round((time.perf_counter() - start) * 1e3, 2)
