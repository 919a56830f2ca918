"""Levenberg-Marquardt refinement of a PnP pose, for one problem (vmapped by `jaxreg.camera.pnp`).

The variable is a chart centred on the start pose T0, `delta = (v, w) -> T0 @ (SO3.exp(w), v)`:
a right perturbation on SO(3) x R^3. At delta = 0 it has the Jacobian of jaxlie's
`T0 @ SE3.exp(delta)` (so covariances are in jaxlie's tangent convention,
`(vx, vy, vz, wx, wy, wz)`, object frame) and the optimum is chart-independent; it lets the
residual be evaluated as start + increment, which keeps float32 accurate (see
`_chart_residuals`), and since the chart is centred on the start, refinement never nears the
rotation-vector singularity at pi. Each component is scaled so that a unit step moves the
residuals by about one pixel, so the isotropic damping treats depth, in-plane motion and tilts
alike.

Everything in a step is closed form and elementwise (residuals, their Jacobian, a Cholesky
solve of the 6x6 normal equations: `jaxreg.camera._pnp_linalg`), so a vmapped batch of thousands of
problems runs each step as a few fused array operations; the loop runs until every lane has
stopped, and a lane that has stopped keeps its values.

The step: the damped system `(J^T J + lambda I) d = -J^T r` (Nielsen's update of lambda from
the ratio of actual to predicted decrease), except where the undamped Gauss-Newton step would
change the residuals by less than `_QUADRATIC_PX` pixels (root-sum-square): there the
Gauss-Newton step is taken as it is. Near the minimum the decrease a step brings is below the
rounding of a float32 cost, so a test on the cost alone would reject every step there. The
solve has converged when the Gauss-Newton step changes the residuals by less than `tol` pixels
(`_tolerance`); that test is on the residuals, not on the pose, because in the directions the
data barely determine (a small tag's tilt) the step is dominated by rounding while the fit is
already as good as it gets.

Gradients come from the implicit function theorem at the optimum (`jax.lax.custom_root` on the
gradient of the squared error, with its exact Hessian); the start pose is a constant.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxlie import SE3, SO3
from jaxtyping import Array

from jaxreg.camera._pnp_linalg import cho_solve, cholesky, packed
from jaxreg.camera.model import pose_jacobian

__all__ = ["normal_equations", "refine_poses", "weighted_jacobian"]

_QUADRATIC_PX = 1e-2  # below this Gauss-Newton change of the residuals, take the full step
_SECANT_PX = 2e-5  # above it, the curvature measured along a step is resolved (float32)
_LAMBDA_AFTER_REJECT = 1e-3  # a rejected step raises lambda to at least this times nu
_MIN_RATIO = 0.25  # the secant correction lengthens a step at most 4-fold


def _tolerance(dtype) -> float:
    """Convergence threshold on the Gauss-Newton step's change of the residuals, in pixels."""
    return 1e-5 if jnp.finfo(dtype).bits <= 32 else 1e-8


# Everything below is written on scalars: a 3-vector is a tuple of three arrays, a matrix a
# tuple of rows, per point an array `(N,)` and per problem a 0-d array. Vmapped over problems,
# every operation then has the batch's shape `(B,)` or `(B, N)` and XLA fuses a whole step into
# a few loops; with `(B, 3, 3)` arrays it splits into ~100 small kernels (slices, reductions,
# batched dots) whose launch cost dominates.


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _mat_vec(M, v):
    return tuple(M[i][0] * v[0] + M[i][1] * v[1] + M[i][2] * v[2] for i in range(3))


def _row_mat(r, M):
    """Row vector times matrix: `r @ M`."""
    return tuple(r[0] * M[0][j] + r[1] * M[1][j] + r[2] * M[2][j] for j in range(3))


def _point_sum(x: Array) -> Array:
    """Sum over the points (the last axis), as a reduction. XLA's CPU compiler fuses no
    elementwise producer into a reduction over the minor axis, so the per-point Jacobian is
    computed once and each of the 28 sums reads it; written out as additions of slices, each
    sum became a fusion of its own that recomputed the whole Jacobian (a 2.4x larger step to
    compile, and no faster to run)."""
    return jnp.sum(x, axis=-1)


def _rotation_coefficients(w):
    """`(sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3)` at t = |w|, double-where at 0."""
    theta_sq = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
    small = theta_sq < (1e-5 if jnp.finfo(theta_sq.dtype).bits <= 32 else 1e-10)
    safe = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(safe)
    sin = jnp.sin(theta)
    a = jnp.where(small, 1.0 - theta_sq / 6.0, sin / theta)
    b = jnp.where(small, 0.5 - theta_sq / 24.0, 2.0 * (jnp.sin(0.5 * theta) / theta) ** 2)
    c = jnp.where(small, 1.0 / 6.0 - theta_sq / 120.0, (theta - sin) / (safe * theta))
    return a, b, c


def _pose_at(T0: SE3, delta: Array) -> SE3:
    """The pose at chart coordinate delta = (v, w): X -> T0 (exp(w) X + v)."""
    return T0 @ SE3.from_rotation_and_translation(SO3.exp(delta[3:]), delta[:3])


def _distort(x, y, dist):
    """Brown-Conrady distortion of normalised coordinates (as `jaxreg.camera.distort`)."""
    if dist is None:
        return x, y
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return (
        x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x),
        y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y,
    )


def _distortion_increment(x0, y0, dx, dy, dist):
    """`distort(xy0 + dxy) - distort(xy0)` without cancellation: every term is a product with
    an increment, so float32 keeps its relative precision on small steps."""
    if dist is None:
        return dx, dy
    k1, k2, p1, p2, k3 = dist
    x1, y1 = x0 + dx, y0 + dy
    r0 = x0 * x0 + y0 * y0
    r1 = x1 * x1 + y1 * y1
    dx2 = dx * (2.0 * x0 + dx)  # x1^2 - x0^2
    dy2 = dy * (2.0 * y0 + dy)
    dr = dx2 + dy2
    dxy = dx * y1 + x0 * dy  # x1 y1 - x0 y0
    radial1 = 1.0 + r1 * (k1 + r1 * (k2 + r1 * k3))
    dradial = dr * (k1 + k2 * (r1 + r0) + k3 * (r1 * r1 + r1 * r0 + r0 * r0))
    ddx = dx * radial1 + x0 * dradial + 2.0 * p1 * dxy + p2 * (dr + 2.0 * dx2)
    ddy = dy * radial1 + y0 * dradial + p1 * (dr + 2.0 * dy2) + 2.0 * p2 * dxy
    return ddx, ddy


def _distortion_jacobian(x, y, dist):
    """Rows of `d distort / d (x, y)` (as `jaxreg.camera.model`'s)."""
    if dist is None:
        one, zero = jnp.ones_like(x), jnp.zeros_like(x)
        return (one, zero), (zero, one)
    k1, k2, p1, p2, k3 = dist
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = 2.0 * (k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3))
    cross = x * y * dradial + 2.0 * (p1 * x + p2 * y)
    return (
        (radial + x * x * dradial + 2.0 * p1 * y + 6.0 * p2 * x, cross),
        (cross, radial + y * y * dradial + 6.0 * p1 * y + 2.0 * p2 * x),
    )


class _Problem(NamedTuple):
    """One refinement problem in scalar form (see above), centred on the start pose."""

    R0: tuple  # rows of the start rotation
    X: tuple  # object points, three (N,) arrays
    Xc0: tuple  # the points in the camera frame at the start
    xy0: tuple  # their normalised coordinates
    r0: tuple  # unweighted pixel residuals at the start, two (N,) arrays
    K: tuple  # (k00, k01, k10, k11): the intrinsics' linear part
    dist: tuple | None
    sw: Array  # (N,) square roots of the weights
    scale: tuple  # the six column scales of y = scale * delta

    @classmethod
    def build(cls, R0: Array, t0: Array, X, uv, K, dist, sw, scale) -> _Problem:
        R = tuple(tuple(R0[i, j] for j in range(3)) for i in range(3))
        Xs = (X[:, 0], X[:, 1], X[:, 2])
        Xc0 = tuple(c + t0[i] for i, c in enumerate(_mat_vec(R, Xs)))
        xy0 = (Xc0[0] / Xc0[2], Xc0[1] / Xc0[2])
        d = None if dist is None else tuple(dist[i] for i in range(5))
        xd, yd = _distort(*xy0, d)
        r0 = (
            K[0, 0] * xd + K[0, 1] * yd + K[0, 2] - uv[:, 0],
            K[1, 0] * xd + K[1, 1] * yd + K[1, 2] - uv[:, 1],
        )
        k = (K[0, 0], K[0, 1], K[1, 0], K[1, 1])
        return cls(R, Xs, Xc0, xy0, r0, k, d, sw, tuple(scale[i] for i in range(6)))


def _evaluate(p: _Problem, y, *, jacobian: bool = True):
    """Weighted residuals at chart coordinate `delta = y / scale`, evaluated as the residual at
    the start plus the change delta causes (computed directly, pixel coordinates ~1e3 round at
    ~1e-4 px in float32, a floor on which LM rejects every step; as start + increment the
    residual resolves changes of ~1e-7 of its own size).

    `y` is a `(6,)` array or six scalars. Returns the residuals `(ru, rv)` (two `(N,)` arrays)
    alone, or with `jacobian` the normal equations' entries: `A` (21 upper-triangle entries of
    `J^T J`, row by row), `g = J^T r` (6) and the cost `|r|^2 / 2`, with `J = d r / d y`.
    With `E = exp(w)` and the right Jacobian `Jr(w)` of SO(3), the chart's variation
    `(dv, dw)` is the right perturbation `(E^T dv, Jr dw)` of the pose it reaches, so
    `J = [P R0, rows (X x (P R0 E)) Jr] / scale` with `P` the pixels' Jacobian with respect to
    the camera-frame point.
    """
    delta = [y[i] / p.scale[i] for i in range(6)]
    v, w = delta[:3], delta[3:]
    a, b, c = _rotation_coefficients(w)
    wX = _cross(w, p.X)
    wwX = _cross(w, wX)
    dXc = _mat_vec(p.R0, tuple(a * wX[i] + b * wwX[i] + v[i] for i in range(3)))
    z0 = p.Xc0[2]
    z1 = z0 + dXc[2]
    dx = (dXc[0] * z0 - p.Xc0[0] * dXc[2]) / (z0 * z1)
    dy = (dXc[1] * z0 - p.Xc0[1] * dXc[2]) / (z0 * z1)
    ddx, ddy = _distortion_increment(*p.xy0, dx, dy, p.dist)
    k00, k01, k10, k11 = p.K
    ru = (p.r0[0] + k00 * ddx + k01 * ddy) * p.sw
    rv = (p.r0[1] + k10 * ddx + k11 * ddy) * p.sw
    if not jacobian:
        return ru, rv
    x1, y1 = p.xy0[0] + dx, p.xy0[1] + dy
    (d00, d01), (d10, d11) = _distortion_jacobian(x1, y1, p.dist)
    inv_z = p.sw / z1  # the weights ride along from here
    rows = []
    for q0, q1 in (
        (k00 * d00 + k01 * d10, k00 * d01 + k01 * d11),
        (k10 * d00 + k11 * d10, k10 * d01 + k11 * d11),
    ):
        P = (q0 * inv_z, q1 * inv_z, -(q0 * x1 + q1 * y1) * inv_z)
        B = _row_mat(P, p.R0)  # d pixel / d v
        # E = I + a W + b W^2 and Jr = I - b W + c W^2, applied without forming them.
        BE = _row_mat(B, _exp_matrix(w, a, b))
        Jw = _row_mat(_cross(p.X, BE), _right_jacobian(w, b, c))
        rows.append(tuple(col / p.scale[j] for j, col in enumerate((*B, *Jw))))
    J0, J1 = rows
    A = tuple(_point_sum(J0[i] * J0[j] + J1[i] * J1[j]) for i in range(6) for j in range(i, 6))
    g = tuple(_point_sum(J0[i] * ru + J1[i] * rv) for i in range(6))
    cost = 0.5 * _point_sum(ru * ru + rv * rv)
    return A, g, cost


def _skew(w):
    zero = jnp.zeros_like(w[0])
    return ((zero, -w[2], w[1]), (w[2], zero, -w[0]), (-w[1], w[0], zero))


def _exp_matrix(w, a, b):
    W = _skew(w)
    W2 = tuple(_row_mat(W[i], W) for i in range(3))
    return tuple(
        tuple((1.0 if i == j else 0.0) + a * W[i][j] + b * W2[i][j] for j in range(3))
        for i in range(3)
    )


def _right_jacobian(w, b, c):
    W = _skew(w)
    W2 = tuple(_row_mat(W[i], W) for i in range(3))
    return tuple(
        tuple((1.0 if i == j else 0.0) - b * W[i][j] + c * W2[i][j] for j in range(3))
        for i in range(3)
    )


def normal_equations(A21, g6, cost):
    """`(J^T J (6, 6), J^T r (6,), cost)` as arrays, from `_evaluate`'s scalars."""
    index = [[0] * 6 for _ in range(6)]
    k = 0
    for i in range(6):
        for j in range(i, 6):
            index[i][j] = index[j][i] = k
            k += 1
    A = jnp.stack([jnp.stack([A21[index[i][j]] for j in range(6)], -1) for i in range(6)], -2)
    return A, jnp.stack(g6, -1), cost


def weighted_jacobian(pose: SE3, X, K, dist, sw) -> Array:
    """d (weighted pixel residuals) / d delta, `(2N, 6)`, of the right perturbation at `pose`."""
    return (pose_jacobian(pose, X, K, dist) * sw[:, None, None]).reshape(-1, 6)


def refine_poses(T0: SE3, active, X, uv, K, dist, w, *, max_iterations: int, axes):
    """Levenberg-Marquardt from each start of a batch of problems; see the module docstring.

    `T0` has batch `(P, S)` (S starts of each of P problems) and `active` shape `(P, S)`;
    `X` `(P, N, 3)`, `uv` `(P, N, 2)`, `w` `(P, N)`; `K` and `dist` are per problem or shared
    as `axes` (their vmap axes, 0 or None) says. Returns (pose `(P, S)`, iterations `(P, S)`,
    converged `(P, S)`).

    The variable is y = s * delta with s the column norms of the residual Jacobian at T0, so a
    unit change of any component moves the residuals by about one pixel. A start that is not
    `active` (its input failed, or it is not worth refining) or is not finite takes no step
    and returns T0 unchanged, 0 iterations and `converged` True; for differentiation its
    residual is `y` itself, whose well-posed Hessian keeps the implicit derivative finite (an
    all-zero problem would make it singular). T0 is a constant for differentiation.
    """
    per_start = (0, 0, None, None, None, None, None)  # T0, active vary by start
    in_axes = (0, 0, 0, 0, axes[0], axes[1], 0)
    prepare = jax.vmap(jax.vmap(_start_state, in_axes=per_start), in_axes=in_axes)
    problem, state = prepare(T0, active, X, uv, K, dist, w)
    shape = state.shape[:2]
    flat = lambda a: a.reshape(-1, *a.shape[2:])  # noqa: E731
    state = _run(jax.tree.map(flat, problem), flat(state), max_iterations)
    state = state.reshape(*shape, *state.shape[1:])
    scale = jnp.stack(problem.scale, axis=-1)
    finish = jax.vmap(
        jax.vmap(_implicit_pose, in_axes=per_start + (0, 0)), in_axes=in_axes + (0, 0)
    )
    return finish(T0, active, X, uv, K, dist, w, scale, state)


def _start(T0: SE3, active, X, uv, K, dist, w):
    """The chart's centre and the problem's arrays as the loop sees them (see refine_poses)."""
    T0 = jax.lax.stop_gradient(T0)
    ok = active & jnp.all(jnp.isfinite(T0.wxyz_xyz))
    dummy = jnp.zeros_like(T0.wxyz_xyz).at[0].set(1.0).at[6].set(1.0)  # identity, z = 1
    start = SE3(jnp.where(ok, T0.wxyz_xyz, dummy))
    X, uv = jnp.where(ok, X, 0.0), jnp.where(ok, uv, 0.0)
    sw = jnp.sqrt(jnp.where(ok, w, 0.0))
    return T0, ok, start, start.rotation().as_matrix(), start.translation(), X, uv, sw


def _start_state(T0: SE3, active, X, uv, K, dist, w):
    """One start's problem (constants) and the loop's initial state. The normal equations at
    the start are evaluated once, unscaled: their diagonal gives the column scales (1 where
    zero or not finite), and rescaled they are the initial state's."""
    T0, ok, _, R0, t0, X, uv, sw = jax.lax.stop_gradient(_start(T0, active, X, uv, K, dist, w))
    K, dist = jax.lax.stop_gradient((K, dist))
    unscaled = _Problem.build(R0, t0, X, uv, K, dist, sw, jnp.ones(6, X.dtype))
    A, g, cost = _evaluate(unscaled, jnp.zeros(6, X.dtype))
    rows = packed(A)
    scale = jnp.sqrt(jnp.stack([rows[i][i] for i in range(6)]))
    scale = jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0)
    s = tuple(scale[i] for i in range(6))
    A = [rows[i][j] / (s[i] * s[j]) for i in range(6) for j in range(i, 6)]
    g = [g[i] / s[i] for i in range(6)]
    return unscaled._replace(scale=s), _initial_state(A, g, cost, ok)


def _implicit_pose(T0: SE3, active, X, uv, K, dist, w, scale, state):
    """The pose the loop reached, differentiable by the implicit function theorem at it
    (`scale` `(6,)`: the loop's column scales, a constant)."""
    T0, ok, start, R0, t0, X, uv, sw = _start(T0, active, X, uv, K, dist, w)
    differentiable = _Problem.build(R0, t0, X, uv, K, dist, sw, scale)

    def gradient(y):
        def cost(y):
            ru, rv = _evaluate(differentiable, y, jacobian=False)
            cost = 0.5 * jnp.sum(ru * ru + rv * rv)
            return jnp.where(ok, cost, 0.5 * jnp.sum(y * y))

        return jax.grad(cost)(y)

    def tangent_solve(hessian_vector_product, b):
        return jnp.linalg.solve(jax.jacfwd(hessian_vector_product)(b), b)

    found = jax.lax.stop_gradient(state[:6])
    y = jax.lax.custom_root(gradient, found, lambda _, y0: y0, tangent_solve)
    pose = SE3(jnp.where(ok, _pose_at(start, y / scale).wxyz_xyz, T0.wxyz_xyz))
    return pose, state[43].astype(jnp.int32), state[45] > 0


def _run(problem: _Problem, state: Array, max_iterations: int) -> Array:
    """The loop over a flat batch of starts `(L, ...)`, until each has converged or spent
    `max_iterations` steps.

    A step costs in proportion to the lanes it carries, finished or not, and most starts
    converge within ~8 steps while a few in flat valleys take several times that. So a step
    carries `L // 8` starts (all L when L < 64): the first ones still running, gathered afresh
    every step, so that a start that stops frees its place for the next one at once. There is
    one loop and one copy of the step to compile; a lane's steps and result do not depend on
    which lanes share its steps (up to float rounding)."""
    lanes = state.shape[0]
    capacity = lanes // 8 if lanes >= 64 else lanes
    step = jax.vmap(_step)

    def running(state):
        return (state[:, 44] == 0) & (state[:, 43] < max_iterations)

    def body(state):
        if capacity == lanes:
            return jnp.where(running(state)[:, None], step(problem, state), state)
        # Indices past the end fill the places no running start needs: they read the last
        # lane (clipped) and write nothing (dropped).
        subset = jnp.nonzero(running(state), size=capacity, fill_value=lanes)[0]
        part = state.at[subset].get(mode="clip")
        part_problem = jax.tree.map(lambda a: a.at[subset].get(mode="clip"), problem)
        live = running(part) & (subset < lanes)
        part = jnp.where(live[:, None], step(part_problem, part), part)
        return state.at[subset].set(part, mode="drop")

    return jax.lax.while_loop(lambda state: jnp.any(running(state)), body, state)


def _initial_state(A, g, cost, ok) -> Array:
    """The loop state of one start, one array: y (6), A (21), g (6), cost, lambda, nu, the last
    accepted step (6), its curvature ratio, iterations, done, converged, from the normal
    equations at the start (`_evaluate`'s). (As separate arrays, every carried scalar would be
    written by a kernel of its own each step.)"""
    dtype = cost.dtype
    zero = jnp.zeros((), dtype)
    notok = jnp.where(ok, 0.0, 1.0).astype(dtype)
    return jnp.stack(
        [*(zero,) * 6, *A, *g, cost, 1e-3 + zero, 2.0 + zero, *(zero,) * 6, 1.0 + zero]
        + [zero, notok, notok]
    )


def _step(problem: _Problem, state: Array) -> Array:
    """One step of the damped Gauss-Newton loop of the module docstring, on scalars."""
    dtype = state.dtype
    tol = _tolerance(dtype)
    zero = jnp.zeros((), dtype)

    def dot(a, b):
        return sum((ai * bi for ai, bi in zip(a, b, strict=True)), zero)

    s = [state[i] for i in range(state.shape[0])]
    y, A, g, cost, lam, nu = s[0:6], s[6:27], s[27:33], s[33], s[34], s[35]
    last, ratio, iterations = s[36:42], s[42], s[43]
    rows = packed(A)
    minus_g = [-gi for gi in g]
    L, inv_diag, definite = cholesky(rows)
    newton = cho_solve(L, inv_diag, minus_g)
    change = jnp.sqrt(jnp.maximum(dot(newton, minus_g), 0.0))  # |J newton|
    quadratic = definite & (change <= _QUADRATIC_PX)
    converged = definite & (change <= tol)
    # Secant correction along the last step: with the true curvature there `ratio` times
    # the Gauss-Newton one, the inverse of the corrected matrix (Sherman-Morrison).
    q = dot(last, [dot(row, last) for row in rows])
    secant = (ratio < 1.0) & (q > 0) & (change > _SECANT_PX)
    coef = (ratio - 1.0) / jnp.where(secant, q * ratio, 1.0) * dot(last, minus_g)
    newton = [jnp.where(secant, n - coef * d, n) for n, d in zip(newton, last, strict=True)]
    damped_rows = [[a + lam if i == j else a for j, a in enumerate(r)] for i, r in enumerate(rows)]
    L, inv_diag, _ = cholesky(damped_rows)
    damped = cho_solve(L, inv_diag, minus_g)
    step = [jnp.where(quadratic, n, d) for n, d in zip(newton, damped, strict=True)]
    y_new = [yi + si for yi, si in zip(y, step, strict=True)]
    A_new, g_new, cost_new = _evaluate(problem, y_new)
    predicted = 0.5 * dot(step, [lam * si - gi for si, gi in zip(step, g, strict=True)])
    rho = (cost - cost_new) / jnp.where(predicted > 0, predicted, 1.0)
    finite = jnp.isfinite(cost_new + sum(A_new))
    accept = finite & (quadratic | (cost_new < cost))
    shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
    lam_accept = lam * jnp.where(quadratic, 1.0, shrink)
    lam = jnp.where(accept, lam_accept, jnp.maximum(lam, _LAMBDA_AFTER_REJECT) * nu)
    curvature = dot(step, [a - b for a, b in zip(g_new, g, strict=True)])
    q_step = dot(step, [dot(row, step) for row in rows])
    ratio_new = jnp.clip(curvature / jnp.where(q_step > 0, q_step, 1.0), _MIN_RATIO, 1.0)
    ratio_new = jnp.where(q_step > 0, ratio_new, 1.0)
    new = [*y_new, *A_new, *g_new, cost_new, *step, ratio_new]
    old = [*y, *A, *g, cost, *last, ratio]
    kept = [jnp.where(accept, a, b) for a, b in zip(new, old, strict=True)]
    flag = jnp.where(converged, 1.0, 0.0).astype(dtype)
    return jnp.stack(
        kept[:34]
        + [lam, jnp.where(accept, 2.0, 2.0 * nu)]
        + kept[34:]
        + [iterations + 1.0, flag, flag]
    )
