"""BOP result files: the BOP19 CSV of pose estimates that the toolkit's evaluation reads.

One header line ``scene_id,im_id,obj_id,score,R,t,time`` then one row per estimate: integer
ids, the confidence ``score``, ``R`` the 9 entries of ``cam_R_m2c`` row-major separated by
spaces, ``t`` the 3 entries of ``cam_t_m2c`` in millimetres separated by spaces, and ``time``
the seconds spent on the estimate's whole image (the same for every row of an image; -1 when
not measured). Numbers are written as Python's shortest round-trip ``repr``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable
from pathlib import Path

import numpy as np

__all__ = ["HEADER", "BopResult", "read_bop_results", "write_bop_results"]

HEADER = "scene_id,im_id,obj_id,score,R,t,time"
_MM_PER_M = 1000.0


@dataclasses.dataclass(frozen=True, eq=False)
class BopResult:
    """One pose estimate of one object in one image.

    Attributes:
        scene_id, im_id, obj_id: the image and the object (the dataset's ids).
        score: confidence; BOP keeps, per object and image, the highest-scoring estimates.
        R: `(3, 3)` rotation of `camera_T_object` (model -> camera).
        t: `(3,)` translation of `camera_T_object`, metres.
        time: seconds spent on the whole image, or -1 when not measured.
    """

    scene_id: int
    im_id: int
    obj_id: int
    score: float
    R: np.ndarray
    t: np.ndarray
    time: float = -1.0

    @property
    def camera_T_object(self) -> np.ndarray:
        """`(4, 4)` float64 model -> camera, metres."""
        pose = np.eye(4)
        pose[:3, :3] = self.R
        pose[:3, 3] = self.t
        return pose


def _row(result: BopResult, index: int) -> str:
    rotation = np.asarray(result.R, dtype=np.float64)
    translation = np.asarray(result.t, dtype=np.float64).reshape(-1)
    if rotation.shape != (3, 3) or translation.shape != (3,):
        raise ValueError(
            f"result {index}: R must be (3, 3) and t (3,), got {rotation.shape} and "
            f"{np.shape(result.t)}"
        )
    values = (result.score, result.time, *rotation.ravel(), *translation)
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"result {index}: score, time, R and t must be finite numbers")
    fields = [
        str(int(result.scene_id)),
        str(int(result.im_id)),
        str(int(result.obj_id)),
        repr(float(result.score)),
        " ".join(repr(float(v)) for v in rotation.ravel()),
        " ".join(repr(float(v) * _MM_PER_M) for v in translation),
        repr(float(result.time)),
    ]
    return ",".join(fields)


def write_bop_results(path: str | Path, results: Iterable[BopResult]) -> Path:
    """Write `results` as a BOP19 CSV at `path` (see the module docstring); returns the path.

    Raises:
        ValueError: a result whose `R` is not `(3, 3)`, `t` not `(3,)`, or with a non-finite
            number.
    """
    path = Path(path)
    lines = [HEADER] + [_row(result, k) for k, result in enumerate(results)]
    path.write_text("\n".join(lines) + "\n")
    return path


def _floats(path: Path, number: int, name: str, text: str, count: int) -> list[float]:
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise ValueError(
            f"{path}: line {number}: {name} must be {count} finite numbers separated by "
            f"spaces, got {text!r}"
        )
    return values


def _parse(path: Path, number: int, line: str) -> BopResult:
    fields = line.split(",")
    if len(fields) != 7:
        raise ValueError(
            f"{path}: line {number} has {len(fields)} comma-separated fields, a BOP result has "
            f"7 ({HEADER})"
        )
    try:
        scene_id, im_id, obj_id = (int(v) for v in fields[:3])
    except ValueError:
        raise ValueError(
            f"{path}: line {number}: scene_id, im_id, obj_id must be integers"
        ) from None
    (score,) = _floats(path, number, "score", fields[3], 1)
    rotation = np.reshape(_floats(path, number, "R", fields[4], 9), (3, 3))
    translation = np.asarray(_floats(path, number, "t", fields[5], 3)) / _MM_PER_M
    (time,) = _floats(path, number, "time", fields[6], 1)
    return BopResult(scene_id, im_id, obj_id, score, rotation, translation, time)


def read_bop_results(path: str | Path) -> list[BopResult]:
    """The estimates of a BOP19 CSV (header optional, blank lines skipped), `t` in metres.

    Raises:
        ValueError: the file is missing, or a line does not have 7 fields, integer ids, 9
            numbers in R or 3 in t (the message names the file and the line).
    """
    path = Path(path)
    try:
        lines = path.read_text().splitlines()
    except FileNotFoundError:
        raise ValueError(f"{path}: no such results file") from None
    results = []
    for number, line in enumerate(lines, start=1):
        if not line.strip() or (number == 1 and line.strip() == HEADER):
            continue
        results.append(_parse(path, number, line.strip()))
    return results
