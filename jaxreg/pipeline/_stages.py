"""What the stages of :func:`jaxreg.estimate_pose` share: the failure that stops the pipeline
with the failing stage's record, and the padded clouds given to compiled code.
"""

from __future__ import annotations

import numpy as np


class _Failed(Exception):
    """A stage found no pose to claim: its name, the reason, its record, and what it had
    segmented (the lifted pixels ``(H, W)`` and points ``(K, 3)``, or ``None``)."""

    def __init__(self, stage: str, reason: str, record, mask=None, points=None):
        super().__init__(reason)
        self.stage, self.reason, self.record = stage, reason, record
        self.mask, self.points = mask, points


def _padded(points: np.ndarray, size: int, rng: np.random.Generator) -> np.ndarray:
    """``(size, 3)`` float32: ``points`` subsampled (without replacement) when longer, NaN
    rows (ignored by ICP) after them when shorter."""
    if len(points) > size:
        points = points[np.sort(rng.choice(len(points), size, replace=False))]
    out = np.full((size, 3), np.nan, np.float32)
    out[: len(points)] = points
    return out
