"""Checked reads of the BOP format's JSON documents and their number lists (its images are read
by :mod:`jaxreg.io.images`). Host side; every problem is a ``ValueError`` naming the file, what
is wrong and what to try."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

__all__ = ["load_json", "numbers"]


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
