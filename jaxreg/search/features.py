"""Local geometric descriptors (FPFH) and correspondences between them.

**FPFH** (Rusu et al., "Fast Point Feature Histograms for 3D registration", ICRA 2009), as
PCL and Open3D compute it. For a point ``p`` with unit normal ``n`` and a neighbour ``q``
with normal ``m``, at distance ``d = |q - p|``, the *source* of the pair is whichever of the
two makes the smaller angle between its normal and the line joining them (swapping the
roles, and the sign of ``q - p``, otherwise). With the source's normal ``u``, the other's
``m'`` and the unit direction ``e`` from source to other, the Darboux frame ``u``,
``v = (e x u) / |e x u|``, ``w = u x v`` gives three angles::

    theta = atan2(w . m', u . m')     in [-pi, pi]
    alpha = v . m'                    in [-1, 1]
    phi   = u . e                     in [-1, 1]   (of the original source, sign per swap)

each binned into 11 equal bins (33 in all, in the order theta, alpha, phi). A pair at zero
distance or with ``e`` parallel to ``u`` contributes the zero triplet (the middle bins),
as in Open3D. The *simplified* histogram (SPFH) of ``p`` bins its pairs with each of its
neighbours, each pair adding ``100 / (number of neighbours)``. The FPFH of ``p`` is::

    FPFH(p) = normalise( sum_q SPFH(q) / d_q^2 ) + SPFH(p)

where ``d_q^2`` is the *squared* distance (what PCL and Open3D divide by, the published
definition's ``1 / d`` notwithstanding), neighbours at zero distance are skipped, and
``normalise`` scales each of the three 11-bin sub-histograms to sum to 100. Each
sub-histogram of a point with neighbours therefore sums to 200.

Neighbourhoods are Open3D's hybrid search: the ``max_neighbors`` nearest points (the point
itself included) within ``radius``. A point with more than that many points in its
radius keeps the nearest ones and is flagged ``overflow`` (informational: Open3D does the
same silently). On a concrete cloud they come from exact compiled host loops
(:func:`jaxreg.search._knn.self_knn`); under ``jit`` from blocked brute force
(:func:`jaxreg.search.neighbors.radius_search`).

**Correspondences** (:func:`match_features`): each source descriptor's nearest target
descriptor (Euclidean, as Open3D), optionally kept only when mutual (the target's nearest
source descriptor is that source point) and when it passes Lowe's ratio test. The result
is padded to one row per source point with a mask. On concrete arrays the nearest rows come
from a k-d tree (scipy's, exact); under ``jit`` from blocked brute force. A descriptor row
that is all zero (an undefined FPFH: every defined one sums to 200 per sub-histogram) or not
finite takes no part, so undefined points never match each other.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int
from scipy.spatial import cKDTree

from jaxreg.core._brute import pad_slots, valid_rows
from jaxreg.core._sizes import bucket, pad_rows
from jaxreg.search.neighbors import radius_search
from jaxreg.search.normals import _host_knn, _is_concrete

__all__ = ["FPFH", "FeatureMatches", "fpfh", "match_features"]

BINS = 11
DIM = 3 * BINS


class FPFH(eqx.Module):
    """Result of :func:`fpfh` for ``N`` points.

    Attributes:
        histograms: ``(N, 33)`` descriptors (theta, alpha, phi; 11 bins each); zero rows
            where not ``valid``.
        valid: ``(N,)`` the point and its normal are usable and it has at least one
            neighbour within ``radius``.
        num_neighbors: ``(N,)`` neighbours used, the point itself excluded.
        overflow: ``(N,)`` more than ``max_neighbors`` points (the point included) lie
            within ``radius``: the nearest were used, as Open3D does.
    """

    histograms: Float[Array, "N 33"]
    valid: Bool[Array, " N"]
    num_neighbors: Int[Array, " N"]
    overflow: Bool[Array, " N"]


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _pair_features(p, n, q, m):
    """Open3D's ``ComputePairFeatures``: ``(theta, alpha, phi)`` of pairs of points ``p``,
    ``q`` with normals ``n``, ``m``, each given as its three coordinate arrays (broadcasting
    against each other); the zero triplet at zero distance or where the Darboux frame is
    undefined. Coordinates one array each: XLA's CPU backend vectorises these elementwise
    chains ~2x better than ``(..., 3)`` arrays."""
    d = tuple(qi - pi for qi, pi in zip(q, p, strict=True))
    dist = jnp.sqrt(_dot(d, d))
    live = dist > 0
    safe = jnp.where(live, dist, 1.0)
    cos_p, cos_q = _dot(n, d) / safe, _dot(m, d) / safe
    # The source is the end whose normal makes the smaller angle with the joining line.
    swap = jnp.abs(cos_p) < jnp.abs(cos_q)
    u = tuple(jnp.where(swap, b, a) for a, b in zip(n, m, strict=True))
    other = tuple(jnp.where(swap, a, b) for a, b in zip(n, m, strict=True))
    phi = jnp.where(swap, -cos_q, cos_p)
    # Unnormalised, as Open3D: the rounding of a near-zero cross product then agrees.
    v = _cross(tuple(jnp.where(swap, -x, x) for x in d), u)
    v_norm = jnp.sqrt(_dot(v, v))
    live = live & (v_norm > 0)
    v = tuple(x / jnp.where(live, v_norm, 1.0) for x in v)
    w = _cross(u, v)
    theta = jnp.arctan2(_dot(w, other), _dot(u, other))
    alpha = _dot(v, other)
    return [jnp.where(live, x, 0.0) for x in (theta, alpha, phi)]


def _bin(x, lo, hi):
    """Bin index in ``[0, 11)`` of values in ``[lo, hi]`` (clamped, as Open3D)."""
    return jnp.clip(jnp.floor(BINS * (x - lo) / (hi - lo)), 0, BINS - 1).astype(jnp.int32)


@jax.jit
def _histograms(points, normals, ok, idx, nbr_ok, overflow) -> FPFH:
    """SPFH then FPFH from neighbour indices ``(N, K)`` (self excluded; sentinel ``N``)."""
    n, k = idx.shape
    dtype = points.dtype
    nbr_ok = nbr_ok & ok[:, None] & ok.at[idx].get(mode="fill", fill_value=False)

    def gather(x):
        return tuple(c.at[idx].get(mode="fill", fill_value=0) for c in x.T)

    nbr_points = gather(points)
    own_points = tuple(c[:, None] for c in points.T)
    theta, alpha, phi = _pair_features(
        own_points, tuple(c[:, None] for c in normals.T), nbr_points, gather(normals)
    )
    count = nbr_ok.sum(-1)
    increment = jnp.where(count > 0, 100.0 / jnp.maximum(count, 1), 0.0).astype(dtype)
    # Histograms by one integer scatter of (point, bin) counts: ~5x a one-hot sum on CPU.
    slots = (
        jnp.stack(
            [_bin(theta, -jnp.pi, jnp.pi), _bin(alpha, -1, 1) + BINS, _bin(phi, -1, 1) + 2 * BINS],
            axis=-1,
        )
        + DIM * jnp.arange(n)[:, None, None]
    )
    counts = (
        jnp.zeros(n * DIM, jnp.int32)
        .at[slots.reshape(-1)]
        .add(jnp.repeat(nbr_ok.reshape(-1), 3).astype(jnp.int32))
    )
    spfh = counts.reshape(n, DIM).astype(dtype) * increment[:, None]
    d2 = _dot(*(tuple(a - b for a, b in zip(nbr_points, own_points, strict=True)),) * 2)
    weight = jnp.where(nbr_ok & (d2 > 0), 1.0 / jnp.where(d2 > 0, d2, 1.0), 0.0)

    def add_slot(j, total):  # one neighbour slot at a time: no (N, K, 33) gather
        return total + weight[:, j, None] * spfh.at[idx[:, j]].get(mode="fill", fill_value=0)

    summed = jax.lax.fori_loop(0, k, add_slot, jnp.zeros_like(spfh)).reshape(n, 3, BINS)
    total = summed.sum(-1, keepdims=True)
    summed = jnp.where(total > 0, summed * (100.0 / jnp.where(total > 0, total, 1.0)), 0.0)
    valid = ok & (count > 0)
    histograms = jnp.where(valid[:, None], summed.reshape(n, DIM) + spfh, 0.0)
    return FPFH(histograms, valid, count.astype(jnp.int32), overflow & valid)


def fpfh(
    points: Float[ArrayLike, "N 3"],
    normals: Float[ArrayLike, "N 3"],
    *,
    radius: float,
    max_neighbors: int = 100,
    mask: Bool[ArrayLike, " N"] | None = None,
) -> FPFH:
    """FPFH descriptors with their validity and neighbourhood counts (see the module
    docstring for the definition; same points, normals, radius and ``max_neighbors`` give
    Open3D's ``compute_fpfh_feature`` with ``KDTreeSearchParamHybrid(radius, max_nn)``).

    Args:
        points: ``(N, 3)`` cloud (metres, any frame).
        normals: ``(N, 3)`` unit normals in the same frame (their sign does not matter);
            rows that are zero or not finite (what :func:`jaxreg.estimate_normals` gives
            where a normal is undefined) mark the point as unusable.
        radius: neighbourhood radius (static; Open3D's tutorials use 5 voxel sizes).
        max_neighbors: static cap on the neighbourhood, the point itself included
            (Open3D's ``max_nn``).
        mask: ``(N,)`` optional validity; masked points neither get a descriptor nor serve
            as anyone's neighbour (nor do unusable ones).

    Returns:
        An :class:`FPFH`.

    Raises:
        ValueError: mis-shaped inputs, a non-positive radius or ``max_neighbors < 2``.
    """
    concrete = _is_concrete(points, normals, mask)
    points = jnp.asarray(points)
    if not jnp.issubdtype(points.dtype, jnp.floating):
        points = points.astype(jnp.result_type(float))
    normals = jnp.asarray(normals, points.dtype)
    if points.ndim != 2 or points.shape[-1] != 3 or normals.shape != points.shape:
        raise ValueError(
            f"points and normals must both be (N, 3), got {points.shape} and {normals.shape}"
        )
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    if max_neighbors < 2:
        raise ValueError(
            f"max_neighbors must be >= 2 (the point itself counts), got {max_neighbors}"
        )
    n = points.shape[0]
    norm_sq = jnp.sum(normals * normals, axis=-1)
    ok = valid_rows(points, mask) & jnp.isfinite(norm_sq) & (jnp.abs(norm_sq - 1) < 1e-2)
    if concrete:
        # Hybrid search (the nearest within the radius); one extra neighbour tells whether the
        # neighbourhood overflowed.
        host = np.asarray(points, np.float64)
        idx, nbr_ok = _host_knn(host, np.asarray(ok), max_neighbors + 1, radius)
        overflow = nbr_ok[:, -1]
        idx, nbr_ok = idx[:, :-1], nbr_ok[:, :-1]
    else:
        idx, _, nbr_ok, overflow = radius_search(points, points, radius, max_neighbors, mask=ok)
    idx = jnp.asarray(idx)
    # The point itself is not its own neighbour (a duplicate of it is, at zero distance).
    nbr_ok = jnp.asarray(nbr_ok) & (idx != jnp.arange(n)[:, None])
    return _histograms(points, normals, ok, idx, nbr_ok, jnp.asarray(overflow))


class FeatureMatches(eqx.Module):
    """Result of :func:`match_features`: one row per source descriptor, padded with a mask.

    Attributes:
        target_index: ``(N,)`` the matched target row, the sentinel ``M`` where ``mask`` is
            False.
        distance: ``(N,)`` Euclidean distance between the matched descriptors (``inf``
            where ``mask`` is False).
        mask: ``(N,)`` the match is kept (both rows valid, mutual and ratio tests passed
            when asked for).
    """

    target_index: Int[Array, " N"]
    distance: Float[Array, " N"]
    mask: Bool[Array, " N"]


def _usable(features: Array, mask) -> Bool[Array, " N"]:
    """Rows that are finite, not all zero and, when given, set in ``mask``."""
    return valid_rows(features, mask) & jnp.any(features != 0, axis=-1)


@functools.partial(jax.jit, static_argnames="second")
def _nearest(a, a_ok, b, b_ok, second: bool):
    """For every row of ``a (N, D)``, its nearest row of ``b (M, D)`` and, with ``second``,
    the second nearest: indices and exact squared distances ``(N, 1 or 2)``, the sentinel
    ``M`` and ``inf`` where missing. Rows equally near within the screen's float32 rounding
    may resolve to either (:func:`_host_nearest` gives exact ties the lower index).

    Blocked brute force (under ``jit``): squared distances are screened by one matrix product
    per block of ``a`` (about 4M distances at once) and the chosen ones recomputed exactly
    (:func:`_exact`). Row minima by ``argmin`` (a second masked pass for the runner-up) cost
    a third of ``top_k`` on CPU.
    """
    n, m = a.shape[0], b.shape[0]
    centre = jnp.where(b_ok[:, None], b, 0).sum(0) / jnp.maximum(b_ok.sum(), 1)
    a0 = jnp.where(a_ok[:, None], a - centre, 0)
    b0 = jnp.where(b_ok[:, None], b - centre, 0)
    b_norm = jnp.where(b_ok, (b0 * b0).sum(-1), jnp.inf)
    block = max(1, min(n, (1 << 22) // max(m, 1)))
    pad = -n % block
    blocks = jnp.pad(a0, ((0, pad), (0, 0))).reshape(-1, block, a.shape[1])

    def one(rows):
        d2 = b_norm - 2 * rows @ b0.T
        first = jnp.argmin(d2, axis=-1)
        if not second:
            return first[:, None]
        runner_up = jnp.where(jnp.arange(m) == first[:, None], jnp.inf, d2)
        return jnp.stack([first, jnp.argmin(runner_up, axis=-1)], axis=-1)

    index = jax.lax.map(one, blocks).reshape(n + pad, -1)[:n].astype(jnp.int32)
    if m == 1:
        index = index[:, :1]
    return _exact(a, a_ok, b, b_ok, index, second)


def _exact(a, a_ok, b, b_ok, index, second: bool):
    """The squared distances ``(N, 1 or 2)`` from each row of ``a`` to its chosen rows
    ``index`` of ``b`` (the sentinel ``M`` allowed), computed exactly; with ``second`` the
    two reordered by them (a screened near tie may swap). Returns ``(index, d2)`` as
    :func:`_nearest` does."""
    m = b.shape[0]
    row = jnp.minimum(index, m - 1)  # the sentinel reads a row, then counts as missing
    diff = a[:, None, :] - b[row]
    known = a_ok[:, None] & b_ok[row] & (index < m)
    d2 = jnp.where(known, (diff * diff).sum(-1), jnp.inf)
    if second and m > 1:
        order = jnp.argsort(d2, axis=-1)
        index, d2 = jnp.take_along_axis(index, order, -1), jnp.take_along_axis(d2, order, -1)
    found = jnp.isfinite(d2)
    index, d2, _ = pad_slots(jnp.where(found, index, m), d2, found, 2 if second else 1, m)
    return index, d2


_exact_jit = jax.jit(_exact, static_argnames="second")


def _host_nearest(a, a_ok, b, b_ok, second: bool):
    """:func:`_nearest` of concrete arrays by a k-d tree over the usable rows of ``b``
    (scipy's ``cKDTree``, exact in float64; a few thousand rows against tens of thousands of
    33-bin FPFH rows take a fraction of the brute force's time). Equally near rows resolve
    to the lower index: one neighbour more than needed is fetched, and where it ties the
    last kept one, every row within that distance is; the distances are then computed as
    :func:`_nearest` computes them."""
    n, m = a.shape[0], b.shape[0]
    k = 2 if second and m > 1 else 1
    index = np.full((n, k), m, np.int32)
    rows, cols = np.flatnonzero(np.asarray(a_ok)), np.flatnonzero(np.asarray(b_ok))
    if len(rows) and len(cols):
        queries, targets = np.asarray(a, np.float64)[rows], np.asarray(b, np.float64)[cols]
        fetch = min(k + 1, len(cols))
        tree = cKDTree(targets)
        distance, found = tree.query(queries, k=fetch, workers=-1)
        distance, found = distance.reshape(len(rows), fetch), found.reshape(len(rows), fetch)
        order = np.lexsort((found, distance), axis=-1)[:, :k]  # by distance, then index
        chosen = np.take_along_axis(found, order, -1)
        kept = min(k, fetch)
        if fetch > k:
            # where the row fetched beyond the kept ones is as near as the last kept, more
            # rows may be: all those within that distance, by distance and then index
            for i in np.flatnonzero(distance[:, -1] <= distance[:, kept - 1]):
                reach = distance[i, kept - 1] * (1 + 1e-9)  # the ball's rounding aside
                near = np.asarray(tree.query_ball_point(queries[i], reach), np.intp)
                gaps = np.linalg.norm(targets[near] - queries[i], axis=-1)
                chosen[i] = near[np.lexsort((near, gaps))[:k]]
        index[rows, :kept] = cols[chosen]
    return _exact_jit(a, a_ok, b, b_ok, jnp.asarray(index), second)


def match_features(
    source_features: Float[ArrayLike, "N D"],
    target_features: Float[ArrayLike, "M D"],
    *,
    mutual: bool = True,
    ratio: float | None = None,
    source_mask: Bool[ArrayLike, " N"] | None = None,
    target_mask: Bool[ArrayLike, " M"] | None = None,
) -> FeatureMatches:
    """Correspondences by nearest neighbour in descriptor space (jittable).

    Each usable source row is matched to its nearest usable target row (Euclidean; on
    concrete arrays by a k-d tree, exact, equally near rows to the lower index; under ``jit``
    by blocked brute force, which may settle a tie within float32 rounding either way;
    concrete rows are padded to :func:`~jaxreg.core._sizes.bucket` counts, so clouds of many
    sizes share a few compiled programs). With
    ``mutual`` the match is kept only if that target row's nearest source row is this one
    (Open3D's ``mutual_filter``); with ``ratio`` only if the nearest distance is below
    ``ratio`` times the second nearest (Lowe's test; 0.8-0.95 suits FPFH).

    Args:
        source_features: ``(N, D)`` descriptors (e.g. :func:`fpfh`'s ``histograms``).
        target_features: ``(M, D)`` descriptors of the same kind.
        mutual: keep mutual nearest neighbours only.
        ratio: optional ratio-test threshold in ``(0, 1]``.
        source_mask, target_mask: optional ``(N,)``, ``(M,)`` row validity; all-zero and
            non-finite rows are invalid whatever the masks say.

    Returns:
        :class:`FeatureMatches` with one row per source descriptor.

    Raises:
        ValueError: mis-shaped inputs, different descriptor lengths, or a ratio outside
            ``(0, 1]``.
    """
    a, b = jnp.asarray(source_features), jnp.asarray(target_features)
    if a.ndim != 2 or b.ndim != 2 or a.shape[1] != b.shape[1]:
        raise ValueError(
            "source_features and target_features must be (N, D) and (M, D) with the same D, "
            f"got {a.shape} and {b.shape}"
        )
    if ratio is not None and not 0 < ratio <= 1:
        raise ValueError(f"ratio must lie in (0, 1], got {ratio}")
    n, m = a.shape[0], b.shape[0]
    concrete = _is_concrete(a, b, source_mask, target_mask)
    if concrete:  # bucketed row counts: clouds of many sizes share a few programs
        (a, source_mask), (b, target_mask) = _bucketed(a, source_mask), _bucketed(b, target_mask)
    dtype = jnp.result_type(a.dtype, b.dtype, jnp.float32)
    a, b = a.astype(dtype), b.astype(dtype)
    a_ok, b_ok = _usable(a, source_mask), _usable(b, target_mask)
    if n == 0 or m == 0:
        return FeatureMatches(
            jnp.full(n, m, jnp.int32), jnp.full(n, jnp.inf, dtype), jnp.zeros(n, bool)
        )
    nearest = _host_nearest if concrete else _nearest
    top, d2 = nearest(a, a_ok, b, b_ok, ratio is not None)
    index = top[:, 0]
    keep = jnp.isfinite(d2[:, 0])
    if mutual:  # only the matched target rows need their nearest source row
        back, _ = nearest(b[jnp.minimum(index, b.shape[0] - 1)], keep, a, a_ok, False)
        keep = keep & (back[:, 0] == jnp.arange(a.shape[0]))
    if ratio is not None:
        keep = keep & (d2[:, 0] < ratio**2 * d2[:, 1])
    matches = (jnp.where(keep, index, m), jnp.where(keep, jnp.sqrt(d2[:, 0]), jnp.inf), keep)
    if concrete:  # the source's own rows, cut on the host (no program per count)
        matches = (jnp.asarray(np.asarray(x)[:n]) for x in matches)
    return FeatureMatches(*matches)


def _bucketed(features: Array, mask):
    """Concrete ``features`` ``(N, D)`` and their ``mask`` (``(N,)`` or ``None``) grown to
    :func:`~jaxreg.core._sizes.bucket` ``(N)`` rows (zero rows, unset in the mask: no part in
    any match), or ``ValueError`` for a mask that is not ``(N,)``."""
    rows = features.shape[0]
    if mask is not None and np.shape(mask) != (rows,):
        raise ValueError(f"mask must be ({rows},), got {np.shape(mask)}")
    if rows == 0:
        return features, mask
    size = bucket(rows)
    mask = np.arange(size) < rows if mask is None else pad_rows(np.asarray(mask, bool), size, False)
    return jnp.asarray(pad_rows(np.asarray(features), size, 0)), mask
