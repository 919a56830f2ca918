"""Exact neighbours by blocked brute force, and the slot conventions every engine shares.

:func:`knn` and :func:`radius_search` need no host step: the target may be traced (under
``jit``, ``vmap`` or ``grad``), which makes them the engine for clouds computed inside a
jitted function, the reference the grid is tested against, and the natural choice on GPUs.
Memory is bounded by mapping ``lax.map`` over blocks of queries (``block * M`` distances live
at once). Distances are screened with one matrix product on clouds centred at the target's
valid mean, and the kept ones recomputed exactly.

Users call them as :func:`jaxreg.search.neighbors.knn` and
:func:`~jaxreg.search.neighbors.radius_search` with the target given as points; they live in
``core`` so that :mod:`jaxreg.geometry.metrics` (ADD-S) shares them.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

__all__ = ["check_queries", "knn", "pad_slots", "radius_search", "valid_rows"]


def check_queries(queries: ArrayLike) -> Array:
    """``queries`` as an ``(N, 3)`` array.

    Raises:
        ValueError: any other shape (batches of query sets are ``vmap``-ed).
    """
    queries = jnp.asarray(queries)
    if queries.ndim != 2 or queries.shape[-1] != 3:
        raise ValueError(f"queries must be (N, 3) (vmap for batches), got {queries.shape}")
    return queries


def pad_slots(index, sq_dists, mask, width: int, sentinel):
    """Pads ``(N, w)`` neighbour slots to ``(N, width)`` with empty ones (sentinel index,
    ``inf`` distance, mask False)."""
    pad = ((0, 0), (0, width - index.shape[1]))
    return (
        jnp.pad(index, pad, constant_values=sentinel),
        jnp.pad(sq_dists, pad, constant_values=jnp.inf),
        jnp.pad(mask, pad),
    )


def valid_rows(points: Array, mask: ArrayLike | None) -> Bool[Array, " M"]:
    """``(M,)`` rows of ``points (M, 3)`` that are finite and, when given, set in ``mask``.

    Raises:
        ValueError: ``mask`` is not ``(M,)``.
    """
    ok = jnp.all(jnp.isfinite(points), axis=-1)
    if mask is None:
        return ok
    mask = jnp.asarray(mask)
    if mask.shape != ok.shape:
        raise ValueError(f"mask must be ({ok.shape[0]},), got {mask.shape}")
    return ok & mask


def _brute_setup(queries, points, mask, block):
    queries = check_queries(queries)
    points = jnp.asarray(points)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must be (M, 3), got {points.shape}")
    m = points.shape[0]
    dtype = jnp.result_type(queries.dtype, points.dtype)
    ok = valid_rows(points, mask)
    # Centre at the valid points' mean: the screening product then loses little to rounding.
    count = ok.sum()
    centre = jnp.where(ok[:, None], points, 0).sum(0) / jnp.maximum(count, 1)
    p = jnp.where(ok[:, None], points - centre, 0).astype(dtype)
    q = (queries - centre).astype(dtype)
    q_ok = jnp.all(jnp.isfinite(q), axis=-1)
    q = jnp.where(q_ok[:, None], q, 0)
    n = q.shape[0]
    if block is None:
        block = max(1, min(n, (1 << 22) // max(m, 1)))
    n_blocks = -(-n // block)
    qb = jnp.pad(q, ((0, n_blocks * block - n), (0, 0))).reshape(n_blocks, block, 3)
    return q, p, ok, q_ok, qb, n


def _screen(qb, p, ok):
    """``(block, M)`` squared distances by one matrix product, ``inf`` at invalid points."""
    pn = jnp.where(ok, (p * p).sum(-1), jnp.inf)
    return (qb * qb).sum(-1, keepdims=True) - 2 * qb @ p.T + pn


def _exact(q, p, ok, idx):
    """Exact squared distances ``(N, K)`` from queries to the chosen points (inf if invalid)."""
    d = q[:, None, :] - p[idx]
    return jnp.where(ok[idx], (d * d).sum(-1), jnp.inf)


def knn(
    queries: ArrayLike,
    points: ArrayLike,
    k: int,
    *,
    max_distance: ArrayLike | None = None,
    mask: ArrayLike | None = None,
    block: int | None = None,
) -> tuple[Int[Array, "N k"], Float[Array, "N k"], Bool[Array, "N k"]]:
    """:func:`jaxreg.search.neighbors.knn` with the target given as ``points`` ``(M, 3)``
    (see it for the arguments and results): blocked brute force, exact, jittable."""
    q, p, ok, q_ok, qb, n = _brute_setup(queries, points, mask, block)
    m = p.shape[0]
    kk = min(k, m)

    def one(qblock):
        d2 = _screen(qblock, p, ok)
        if kk == 1:
            return jnp.argmin(d2, axis=-1)[:, None].astype(jnp.int32)
        return jax.lax.top_k(-d2, kk)[1].astype(jnp.int32)

    if kk == 0:
        idx = jnp.zeros((n, 0), jnp.int32)
    else:
        idx = jax.lax.map(one, qb).reshape(-1, kk)[:n]
    d2 = _exact(q, p, ok, idx)
    neg, order = jax.lax.top_k(-d2, kk) if kk > 1 else (-d2, jnp.zeros_like(idx))
    idx = jnp.take_along_axis(idx, order, axis=1)
    d2 = -neg
    valid = q_ok[:, None] & jnp.isfinite(d2)
    if max_distance is not None:
        valid = valid & (d2 <= jnp.square(jnp.asarray(max_distance, d2.dtype)))
    idx = jnp.where(valid, idx, m)
    d2 = jnp.where(valid, d2, jnp.inf)
    return pad_slots(idx, d2, valid, k, m)


def radius_search(
    queries: ArrayLike,
    points: ArrayLike,
    radius: ArrayLike,
    capacity: int,
    *,
    mask: ArrayLike | None = None,
    block: int | None = None,
) -> tuple[Int[Array, "N c"], Float[Array, "N c"], Bool[Array, "N c"], Bool[Array, " N"]]:
    """:func:`jaxreg.search.neighbors.radius_search` with the target given as ``points``
    ``(M, 3)`` (see it for the arguments and results): blocked brute force, jittable."""
    q, p, ok, q_ok, qb, n = _brute_setup(queries, points, mask, block)
    m = p.shape[0]
    kk = min(capacity, m)
    r2 = jnp.square(jnp.asarray(radius, p.dtype))

    def one(qblock):
        d2 = _screen(qblock, p, ok)
        within = d2 <= r2
        idx = jax.lax.top_k(jnp.where(within, -d2, -jnp.inf), kk)[1].astype(jnp.int32)
        return idx, within.sum(-1)

    idx, count = jax.lax.map(one, qb)
    idx, count = idx.reshape(-1, kk)[:n], count.reshape(-1)[:n]
    d2 = _exact(q, p, ok, idx)
    neg, order = jax.lax.top_k(-d2, kk)
    idx = jnp.take_along_axis(idx, order, axis=1)
    d2 = -neg
    valid = q_ok[:, None] & (d2 <= r2)
    idx = jnp.where(valid, idx, m)
    d2 = jnp.where(valid, d2, jnp.inf)
    return *pad_slots(idx, d2, valid, capacity, m), q_ok & (count > capacity)
