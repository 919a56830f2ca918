"""Robust kernels for iteratively reweighted least squares (IRLS).

Every kernel is written on the *squared* residual ``s = r**2`` (never on ``r``) so that
one convention holds for all of them:

* ``rho(s)`` is the robust loss, with ``rho(s) ~ s`` as ``s -> 0`` (every kernel agrees
  with least squares for small residuals);
* ``weight(s) = d rho / d s`` is the IRLS weight: minimising ``sum_i rho(r_i**2)`` and
  repeatedly solving the weighted least-squares problem ``sum_i w_i r_i**2`` with
  ``w_i = weight(r_i**2)`` share their fixed points.

``scale`` is an array leaf of each kernel Module, so a kernel can be vmapped over scales
and differentiated with respect to its scale. All functions broadcast over any shape of
``s``.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

__all__ = [
    "AbstractRobustKernel",
    "L2",
    "Huber",
    "Tukey",
    "Cauchy",
    "GemanMcClure",
    "Welsch",
    "trim_mask",
]


class AbstractRobustKernel(eqx.Module):
    """A robust loss ``rho(s)`` of the squared residual ``s`` and its IRLS weight."""

    @abc.abstractmethod
    def rho(self, s: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
        """Robust loss of the squared residual ``s >= 0``."""

    @abc.abstractmethod
    def weight(self, s: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
        """IRLS weight ``d rho / d s`` at the squared residual ``s >= 0``."""


class L2(AbstractRobustKernel):
    """Plain least squares: ``rho(s) = s``, weight 1."""

    def rho(self, s):
        return jnp.asarray(s)

    def weight(self, s):
        return jnp.ones_like(jnp.asarray(s))


class _ScaledKernel(AbstractRobustKernel):
    """A kernel with one scale parameter ``k`` (in residual units, e.g. metres)."""

    scale: Float[Array, ""]

    def __init__(self, scale: Float[ArrayLike, ""]):
        self.scale = jnp.asarray(scale)


class Huber(_ScaledKernel):
    """Huber: quadratic for ``|r| <= k``, linear beyond.

    ``rho(s) = s`` for ``s <= k^2``, else ``2 k sqrt(s) - k^2``; ``weight = min(1, k / |r|)``.
    """

    def rho(self, s):
        k2 = self.scale**2
        inside = s <= k2
        r = jnp.sqrt(jnp.where(inside, k2, s))  # no sqrt(0) on the dead branch
        return jnp.where(inside, s, 2.0 * self.scale * r - k2)

    def weight(self, s):
        k2 = self.scale**2
        inside = s <= k2
        r = jnp.sqrt(jnp.where(inside, k2, s))
        return jnp.where(inside, 1.0, self.scale / r)


class Tukey(_ScaledKernel):
    """Tukey's biweight: redescending, zero weight beyond ``|r| = k``.

    ``rho(s) = k^2/3 (1 - (1 - s/k^2)^3)`` for ``s <= k^2``, else ``k^2/3``;
    ``weight = (1 - s/k^2)^2`` inside, 0 outside.
    """

    def rho(self, s):
        k2 = self.scale**2
        x = jnp.clip(s / k2, None, 1.0)
        return k2 / 3.0 * x * (3.0 - 3.0 * x + x * x)  # = 1 - (1 - x)^3, no cancellation

    def weight(self, s):
        u = jnp.clip(1.0 - s / self.scale**2, 0.0, None)
        return u**2


class Cauchy(_ScaledKernel):
    """Cauchy (Lorentzian): ``rho(s) = k^2 log(1 + s/k^2)``, ``weight = 1 / (1 + s/k^2)``."""

    def rho(self, s):
        k2 = self.scale**2
        return k2 * jnp.log1p(s / k2)

    def weight(self, s):
        return 1.0 / (1.0 + s / self.scale**2)


class GemanMcClure(_ScaledKernel):
    """Geman-McClure: ``rho(s) = k^2 s / (k^2 + s)``, ``weight = (k^2 / (k^2 + s))^2``."""

    def rho(self, s):
        k2 = self.scale**2
        return k2 * s / (k2 + s)

    def weight(self, s):
        k2 = self.scale**2
        return (k2 / (k2 + s)) ** 2


class Welsch(_ScaledKernel):
    """Welsch (Leclerc): ``rho(s) = k^2 (1 - exp(-s/k^2))``, ``weight = exp(-s/k^2)``."""

    def rho(self, s):
        k2 = self.scale**2
        return -k2 * jnp.expm1(-s / k2)

    def weight(self, s):
        return jnp.exp(-s / self.scale**2)


def trim_mask(
    sq_residuals: Float[ArrayLike, "... N"],
    fraction: Float[ArrayLike, ""],
    valid: Bool[ArrayLike, "... N"] | None = None,
) -> Bool[Array, "... N"]:
    """Keep the best ``fraction`` of the valid residuals, with static shapes.

    Args:
        sq_residuals: ``(..., N)`` squared residuals (any monotone residual measure works).
        fraction: share of the valid entries to keep, in ``(0, 1]``; the count kept is
            ``ceil(fraction * n_valid)``. An array, so a new value does not recompile.
        valid: optional ``(..., N)`` mask of entries that take part (padding, rejected
            pairs); invalid and NaN entries are never kept.

    Returns:
        ``(..., N)`` boolean mask of the kept entries. Ties at the cut are broken by index,
        so exactly ``ceil(fraction * n_valid)`` entries are kept.

    The cut is found without sorting: a bisection over the residuals' bit patterns (32
    counting passes in float32, 64 in float64), several times faster than a sort on a CPU.
    """
    s = jnp.asarray(sq_residuals)
    valid = jnp.ones(s.shape, bool) if valid is None else jnp.asarray(valid, bool)
    valid = valid & ~jnp.isnan(s)
    key = _ordered_bits(jnp.where(valid, s, jnp.inf))
    n_valid = jnp.sum(valid, axis=-1, keepdims=True)
    n_keep = jnp.ceil(jnp.asarray(fraction) * n_valid - 1e-6).astype(jnp.int32)

    def halve(_, bounds):  # the smallest key with at least n_keep entries at or below it
        lo, hi = bounds
        mid = lo + (hi - lo) // 2
        enough = jnp.sum(key <= mid, axis=-1, keepdims=True) >= n_keep
        return jnp.where(enough, lo, mid + 1), jnp.where(enough, mid, hi)

    zero = jnp.zeros(n_keep.shape, key.dtype)
    _, cut = jax.lax.fori_loop(0, 8 * s.dtype.itemsize, halve, (zero, ~zero))
    below, tie = key < cut, key == cut
    room = n_keep - jnp.sum(below, axis=-1, keepdims=True)
    return valid & (below | (tie & (jnp.cumsum(tie, axis=-1) <= room)))


def _ordered_bits(x: Float[Array, "..."]) -> Array:
    """Unsigned integers of the floats ``x`` that order as ``x`` does (negative floats with
    their bits flipped, non-negative ones with the sign bit set; -0 as +0)."""
    x = jnp.where(x == 0, jnp.zeros_like(x), x)
    bits = jax.lax.bitcast_convert_type(x, jnp.uint32 if x.dtype.itemsize == 4 else jnp.uint64)
    sign = jnp.asarray(1, bits.dtype) << (8 * x.dtype.itemsize - 1)
    return jnp.where(bits & sign != 0, ~bits, bits | sign)
