"""Means of rotations and poses: `chordal_mean` and `karcher_mean`.

Public through :mod:`jaxreg.geometry.lie` (and ``jaxreg``), whose conventions they share: poses and
rotations are `jaxlie.SE3` / `jaxlie.SO3` batches, tangents follow jaxlie (`(v, w)` for SE(3)).

Both average the *last* batch axis: `x` with batch `(..., K)` gives a mean with batch `(...)`.
Weights `(..., K)` broadcast to the batch, are non-negative and are normalised per set; an
element with weight `<= 0` or non-finite parameters is ignored, so padding and holes may hold
NaN. A set with nothing left has a NaN mean under `jit` and raises `ValueError` on concrete
input.
"""

from __future__ import annotations

import functools
from typing import TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3, SO3
from jaxtyping import Array, ArrayLike, Float

from jaxreg.geometry.lie import _positive_w, se3_exp, top_eigenpair

__all__ = ["chordal_mean", "karcher_mean"]

Group = TypeVar("Group", SO3, SE3)


def _averaging_weights(batch: tuple[int, ...], weights, params: Array) -> tuple[Array, Array]:
    """`(valid, normalised weights)`, both `batch`-shaped; elements with weight <= 0 or
    non-finite `params` `(*batch, P)` are ignored, and every weight in a set is divided by the
    set's total."""
    dtype = params.dtype
    if weights is None:
        w = jnp.ones(batch, dtype)
    else:
        w = jnp.asarray(weights, dtype)
        try:
            np.broadcast_shapes(w.shape, batch)
        except ValueError:
            raise ValueError(f"weights of shape {w.shape} do not match the batch {batch}") from None
        w = jnp.broadcast_to(w, batch)
    valid = (w > 0) & jnp.all(jnp.isfinite(params), axis=-1)
    w = jnp.where(valid, w, 0.0)
    total = jnp.sum(w, axis=-1, keepdims=True)
    return valid, w / jnp.where(total > 0, total, 1.0)


def _reject_empty_sets(x: SO3 | SE3, weights, name: str) -> None:
    """On concrete input, a `ValueError` when an averaged set has no element with a positive
    weight and finite parameters (its mean is undefined); traced input is left alone."""
    params = x.parameters()
    if isinstance(params, jax.core.Tracer) or isinstance(weights, jax.core.Tracer):
        return
    params = np.asarray(params)
    valid = np.all(np.isfinite(params), axis=-1)
    if weights is not None:
        valid &= np.broadcast_to(np.asarray(weights), valid.shape) > 0
    empty = ~valid.any(axis=-1)
    if empty.any():
        first = tuple(int(i) for i in np.argwhere(empty)[0])
        raise ValueError(
            f"{name}: {int(empty.sum())} of {empty.size} averaged sets (first at batch index "
            f"{first}) have no element with a positive weight and finite parameters, so their "
            "mean is undefined: drop those sets or give them a positive weight"
        )


def _check_averaged_axis(x, name: str) -> tuple[int, ...]:
    batch = x.get_batch_axes()
    if len(batch) == 0:
        raise ValueError(
            f"{name} averages over the last batch axis; got an unbatched {type(x).__name__}"
        )
    return batch


def _chordal_mean_quaternion(q: Array, w: Array) -> Array:
    """Top eigenvector of `sum_k w_k q_k q_k^T` (sign-free in each `q_k`), NaN for an empty set."""
    a = jnp.einsum("...k,...ki,...kj->...ij", w, q, q)
    mean = _positive_w(top_eigenpair(a)[1])
    return jnp.where(jnp.sum(w, axis=-1, keepdims=True) > 0, mean, jnp.nan)


def chordal_mean(rotations: SO3, weights: Float[ArrayLike, "... K"] | None = None) -> SO3:
    """Weighted chordal L2 mean of rotations: `argmin_R sum_k w_k ||R - R_k||_F^2`.

    `rotations` has batch `(..., K)`; the last axis is averaged and the result has batch
    `(...)`. `weights` `(..., K)` (broadcastable) are non-negative; an element with weight
    `<= 0` or a non-finite quaternion is ignored (padding and holes may hold NaN).

    Since `||R - R_k||_F^2 = 8 (1 - (q . q_k)^2)` for unit quaternions, the minimiser is the top
    eigenvector of `sum_k w_k q_k q_k^T`: closed form, blind to the `q` / `-q` ambiguity, and
    identical to projecting `sum_k w_k R_k` onto SO(3). It is a good, cheap approximation of the
    geodesic (`karcher_mean`) mean and that mean's starting point. The returned quaternion has
    `w >= 0`. Compiled with `jax.jit`.

    Raises:
        ValueError: the batch is unbatched or `weights` does not broadcast to it; or, on
            concrete input, a set has no element with a positive weight and a finite
            quaternion. Under `jit` nothing can raise: such a set's mean is NaN, so a caller
            that may pass empty sets carries its own flag (`(weights > 0).any(-1)`).
    """
    mean = _chordal_mean(rotations, weights)
    _reject_empty_sets(rotations, weights, "chordal_mean")
    return mean


@jax.jit
def _chordal_mean(rotations: SO3, weights) -> SO3:
    batch = _check_averaged_axis(rotations, "chordal_mean")
    q = rotations.wxyz
    valid, w = _averaging_weights(batch, weights, q)
    q = jnp.where(valid[..., None], q, jnp.array([1.0, 0.0, 0.0, 0.0], q.dtype))
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return SO3(wxyz=_chordal_mean_quaternion(q, w))


def karcher_mean(
    x: Group,
    weights: Float[ArrayLike, "... K"] | None = None,
    *,
    max_iterations: int = 50,
    tolerance: float | None = None,
) -> Group:
    """Weighted Karcher (intrinsic, geodesic) mean of an `SO3` or `SE3` batch.

    `x` has batch `(..., K)`; the last axis is averaged and the result has batch `(...)`.
    `weights` `(..., K)` (broadcastable) are non-negative; an element with weight `<= 0` or
    non-finite parameters is ignored (padding and holes may hold NaN).

    The mean `m` solves `sum_k w_k log(m^-1 x_k) = 0`. It is found by the fixed-point
    iteration `m <- m @ exp(sum_k w_k log(m^-1 x_k) / sum_k w_k)` started from the chordal
    mean of the rotations (and the weighted mean of the translations for `SE3`), for at most
    `max_iterations` steps; a batch member stops moving once its step norm falls below
    `tolerance` (default `10 eps` of the dtype). For SO(3) this is the Riemannian
    (bi-invariant metric) mean. SE(3) has no bi-invariant metric; there the result is the
    bi-invariant group exponential barycentre (Pennec & Arsigny): its rotation is the SO(3)
    Karcher mean, and its translation equals the weighted mean of the translations only when
    the rotations agree. `tolerance` then applies to the step's 6-vector norm (metres and
    radians together). Either mean is unique when the data lie within a geodesic ball of
    radius pi/2.

    Differentiable: the gradient is the implicit-function-theorem derivative at the fixed
    point (no unrolling), finite wherever the mean is locally unique. Compiled with `jax.jit`
    (`max_iterations` is static; `tolerance` may be an array).

    Raises:
        TypeError: `x` is not an `SO3` or `SE3`.
        ValueError: `x` is unbatched or `weights` does not broadcast to it; or, on concrete
            input, a set has no element with a positive weight and finite parameters. Under
            `jit` nothing can raise: such a set's mean is NaN, so a caller that may pass
            empty sets carries its own flag (`(weights > 0).any(-1)`).
    """
    mean = _karcher_mean(x, weights, max_iterations=max_iterations, tolerance=tolerance)
    _reject_empty_sets(x, weights, "karcher_mean")
    return mean


@functools.partial(jax.jit, static_argnames=("max_iterations",))
def _karcher_mean(x: Group, weights, *, max_iterations: int, tolerance) -> Group:
    if not isinstance(x, (SO3, SE3)):
        raise TypeError(f"karcher_mean expects an SO3 or SE3 batch, got {type(x).__name__}")
    group = type(x)
    exp = SO3.exp if group is SO3 else se3_exp
    batch = _check_averaged_axis(x, "karcher_mean")
    params = x.parameters()
    dtype = params.dtype
    valid, w = _averaging_weights(batch, weights, params)
    identity = group.identity().parameters().astype(dtype)
    params = jnp.where(valid[..., None], params, identity)
    params = params.at[..., :4].set(
        params[..., :4] / jnp.linalg.norm(params[..., :4], axis=-1, keepdims=True)
    )
    tol = 10.0 * float(jnp.finfo(dtype).eps) if tolerance is None else tolerance

    def mean_step(mean_params, x_params, w):
        """Weighted mean of `log(m^-1 x_k)`: `(...)`-batched tangent `(..., D)`."""
        mean = group(mean_params[..., None, :])
        logs = (mean.inverse() @ group(x_params)).log()
        return jnp.einsum("...k,...kd->...d", w, logs)

    def initial(x_params, w):
        rotation = _chordal_mean_quaternion(x_params[..., :4], w)
        if group is SO3:
            return rotation
        return jnp.concatenate(
            [rotation, jnp.einsum("...k,...kd->...d", w, x_params[..., 4:])], axis=-1
        )

    def solve(x_params, w):
        def cond(state):
            i, _, step = state
            return (i < max_iterations) & jnp.any(step > tol)

        def body(state):
            i, mean_params, step = state
            delta = mean_step(mean_params, x_params, w)
            delta = jnp.where((step > tol)[..., None], delta, 0.0)
            mean = (group(mean_params) @ exp(delta)).normalize()
            return i + 1, mean.parameters(), jnp.linalg.norm(delta, axis=-1)

        start = initial(x_params, w)
        step = jnp.full(batch[:-1], jnp.inf, dtype)
        return jax.lax.while_loop(cond, body, (0, start, step))[1]

    mean_params = solve(jax.lax.stop_gradient(params), jax.lax.stop_gradient(w))

    # The fixed point, made differentiable by the implicit function theorem: `delta = 0` is the
    # root of F(delta) = mean_step(m exp(delta)); custom_root differentiates the root through
    # the (closed-over) data with one linear solve per batch member.
    def residual(delta):
        return mean_step((group(mean_params) @ exp(delta)).parameters(), params, w)

    def tangent_solve(linear, rhs):
        # `linear` acts on each batch member separately, so feeding it the basis vector e_j in
        # every member at once yields column j of every member's D x D Jacobian.
        basis = jnp.eye(rhs.shape[-1], dtype=rhs.dtype)[:, *([None] * (rhs.ndim - 1)), :]
        columns = jax.vmap(linear)(jnp.broadcast_to(basis, (rhs.shape[-1], *rhs.shape)))
        return jnp.linalg.solve(jnp.moveaxis(columns, 0, -1), rhs[..., None])[..., 0]

    zero = jnp.zeros((*batch[:-1], group.tangent_dim), dtype)
    delta = jax.lax.custom_root(residual, zero, lambda f, d0: d0, tangent_solve)
    return group(mean_params) @ exp(delta)
