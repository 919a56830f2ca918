"""Padded sizes: a count of rows (points, starts, problems) rounded up so that data of
similar size shares one compiled program instead of compiling one per count, and the rows
that fill an array up to such a size."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["bucket", "pad_rows", "power_of_two"]


def bucket(rows: int, minimum: int = 32) -> int:
    """``rows`` rounded up to a multiple of an eighth of its leading power of two (at most
    12.5% padding, 8 sizes per doubling), and to at least ``minimum``. Padding rows cost
    what real rows do (a 1,280-start ICP sweep of 800 points is 7% faster at 832 rows than
    at 896), so the steps are fine; a long-running process meets a few sizes per doubling."""
    if rows <= minimum:
        return minimum
    step = 1 << (rows.bit_length() - 4)
    return -(-rows // step) * step


def power_of_two(rows: int, minimum: int = 1) -> int:
    """The smallest power of two that is at least ``rows`` and at least ``minimum`` (itself a
    power of two): one size per doubling, for tables whose length need not be tight."""
    return max(minimum, 1 << max(0, int(rows) - 1).bit_length())


def pad_rows(values, size: int, fill=None):
    """``values`` ``(N, ...)`` grown to ``(size, ...)`` by rows appended after its own.

    Args:
        values: a numpy or JAX array with at least one axis; the result is of the same kind
            and dtype.
        size: the rows wanted, ``>= N``.
        fill: the value of the appended rows (e.g. NaN for points that ICP ignores), or
            ``None`` for copies of the last row: valid input for a program that treats rows
            (lanes, starts, problems) independently, whose extra results the caller drops.

    Raises:
        ValueError: ``size < N``, or copies of the last row of an empty array.
    """
    count = values.shape[0]
    if size < count:
        raise ValueError(f"cannot pad {count} rows to {size}")
    if size == count:
        return values
    xp = jnp if isinstance(values, jax.Array) else np
    if fill is None:
        if count == 0:
            raise ValueError("an empty array has no last row to copy")
        extra = xp.repeat(values[-1:], size - count, axis=0)
    else:
        extra = xp.full((size - count, *values.shape[1:]), fill, values.dtype)
    return xp.concatenate([values, extra])
