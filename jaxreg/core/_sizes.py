"""Padded sizes: a count of rows (points, starts, problems) rounded up so that data of
similar size shares one compiled program instead of compiling one per count."""

from __future__ import annotations

__all__ = ["bucket"]


def bucket(rows: int, minimum: int = 32) -> int:
    """``rows`` rounded up to a multiple of an eighth of its leading power of two (at most
    12.5% padding, 8 sizes per doubling), and to at least ``minimum``. Padding rows cost
    what real rows do (a 1,280-start ICP sweep of 800 points is 7% faster at 832 rows than
    at 896), so the steps are fine; a long-running process meets a few sizes per doubling."""
    if rows <= minimum:
        return minimum
    step = 1 << (rows.bit_length() - 4)
    return -(-rows // step) * step
