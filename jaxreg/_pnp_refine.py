"""Levenberg-Marquardt refinement of a PnP pose, for one problem (vmapped by `jaxreg.pnp`).

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
solve of the 6x6 normal equations: `jaxreg._pnp_linalg`), so a vmapped batch of thousands of
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

import jax
import jax.numpy as jnp
from jaxlie import SE3, SO3
from jaxtyping import Array

from jaxreg._pnp_linalg import matmul, spd_solve
from jaxreg.camera import apply_intrinsics, distort, pose_jacobian

__all__ = ["chart_jacobian", "refine_pose", "weighted_jacobian"]

_QUADRATIC_PX = 1e-2  # below this Gauss-Newton change of the residuals, take the full step


def _tolerance(dtype) -> float:
    """Convergence threshold on the Gauss-Newton step's change of the residuals, in pixels."""
    return 1e-5 if jnp.finfo(dtype).bits <= 32 else 1e-8


def _rotation_coefficients(w: Array):
    """`(sin t / t, (1 - cos t) / t^2, (t - sin t) / t^3)` at t = |w|, double-where at 0."""
    theta_sq = jnp.sum(w * w)
    small = theta_sq < (1e-5 if jnp.finfo(w.dtype).bits <= 32 else 1e-10)
    safe = jnp.where(small, 1.0, theta_sq)
    theta = jnp.sqrt(safe)
    sin = jnp.sin(theta)
    a = jnp.where(small, 1.0 - theta_sq / 6.0, sin / theta)
    b = jnp.where(small, 0.5 - theta_sq / 24.0, 2.0 * (jnp.sin(0.5 * theta) / theta) ** 2)
    c = jnp.where(small, 1.0 / 6.0 - theta_sq / 120.0, (theta - sin) / (safe * theta))
    return a, b, c


def _rotation_increment(w: Array, X: Array) -> Array:
    """`SO3.exp(w) @ X - X` for points X (N, 3), without the cancellation of subtracting X:
    `A w x X + B w x (w x X)` with A = sin(t)/t, B = (1 - cos t)/t^2."""
    a, b, _ = _rotation_coefficients(w)
    wx = jnp.cross(w, X)
    return a * wx + b * jnp.cross(w, wx)


def _chart(T0: SE3, delta: Array) -> SE3:
    """The pose at chart coordinate delta = (v, w): X -> T0 (exp(w) X + v)."""
    return T0 @ SE3.from_rotation_and_translation(SO3.exp(delta[3:]), delta[:3])


def _distortion_increment(xy0: Array, dxy: Array, dist: Array | None) -> Array:
    """`distort(xy0 + dxy) - distort(xy0)` for one problem, without cancellation: every term
    is a product with an increment, so float32 keeps its relative precision on small steps."""
    if dist is None:
        return dxy
    k1, k2, p1, p2, k3 = (dist[i] for i in range(5))
    x0, y0 = xy0[:, 0], xy0[:, 1]
    dx, dy = dxy[:, 0], dxy[:, 1]
    x1, y1 = x0 + dx, y0 + dy
    r0 = x0 * x0 + y0 * y0
    r1 = x1 * x1 + y1 * y1
    dx2 = dx * (2.0 * x0 + dx)  # x1^2 - x0^2
    dy2 = dy * (2.0 * y0 + dy)
    dr = dx2 + dy2
    dxy_ = dx * y1 + x0 * dy  # x1 y1 - x0 y0
    radial1 = 1.0 + r1 * (k1 + r1 * (k2 + r1 * k3))
    dradial = dr * (k1 + k2 * (r1 + r0) + k3 * (r1 * r1 + r1 * r0 + r0 * r0))
    ddx = dx * radial1 + x0 * dradial + 2.0 * p1 * dxy_ + p2 * (dr + 2.0 * dx2)
    ddy = dy * radial1 + y0 * dradial + p1 * (dr + 2.0 * dy2) + 2.0 * p2 * dxy_
    return jnp.stack([ddx, ddy], axis=-1)


def _chart_residuals(R0: Array, t0: Array, delta: Array, X, uv, K, dist, sw) -> Array:
    """Weighted pixel residuals (2N,) of the pose `_chart((R0, t0), delta)`.

    Evaluated as the residual at delta = 0 plus the change delta causes. Computed directly,
    pixel coordinates (~1e3) and depths round at ~1e-4 px in float32, a floor on which LM
    rejects every step; as start + increment the residual resolves changes of ~1e-7 of its
    own size. Its Jacobian at delta = 0 is that of the right perturbation `T0 @ SE3.exp(delta)`.
    """
    Xc = matmul(X, R0.T) + t0
    xy0 = Xc[:, :2] / Xc[:, 2:3]
    r0 = apply_intrinsics(distort(xy0, dist), K) - uv
    dXc = matmul(_rotation_increment(delta[3:], X) + delta[:3], R0.T)
    z1 = Xc[:, 2:3] + dXc[:, 2:3]
    dxy = (dXc[:, :2] * Xc[:, 2:3] - Xc[:, :2] * dXc[:, 2:3]) / (Xc[:, 2:3] * z1)
    du = matmul(_distortion_increment(xy0, dxy, dist), K[:2, :2].T)
    return ((r0 + du) * sw[:, None]).reshape(-1)


def weighted_jacobian(pose: SE3, X, K, dist, sw) -> Array:
    """d (weighted pixel residuals) / d delta, `(2N, 6)`, of the right perturbation at `pose`."""
    return (pose_jacobian(pose, X, K, dist) * sw[:, None, None]).reshape(-1, 6)


def _skew(w: Array) -> Array:
    zero = jnp.zeros_like(w[0])
    return jnp.stack(
        [
            jnp.stack([zero, -w[2], w[1]]),
            jnp.stack([w[2], zero, -w[0]]),
            jnp.stack([-w[1], w[0], zero]),
        ]
    )


def chart_jacobian(T0: SE3, delta: Array, X, K, dist, sw) -> Array:
    """d `_chart_residuals` / d delta at `delta`, `(2N, 6)`, in closed form.

    With `E = exp(w)` and the right Jacobian `Jr(w)` of SO(3), the chart's variation
    `(dv, dw)` is the right perturbation `(E^T dv, Jr dw)` of the pose it reaches, so this is
    `weighted_jacobian` there times `blockdiag(E^T, Jr)`.
    """
    w = delta[3:]
    a, b, c = _rotation_coefficients(w)
    W = _skew(w)
    W2 = matmul(W, W)
    eye = jnp.eye(3, dtype=delta.dtype)
    E = eye + a * W + b * W2
    Jr = eye - b * W + c * W2
    J = weighted_jacobian(_chart(T0, delta), X, K, dist, sw)
    return jnp.concatenate([matmul(J[:, :3], E.T), matmul(J[:, 3:], Jr)], axis=1)


def refine_pose(T0: SE3, active, X, uv, K, dist, w, *, max_iterations: int):
    """Levenberg-Marquardt from T0 (a constant for differentiation); see the module docstring.

    The variable is y = s * delta with s the column norms of the residual Jacobian at T0, so a
    unit change of any component moves the residuals by about one pixel. A lane that is not
    `active` (its input failed, or it is a start not worth refining) or has a non-finite start
    takes no step and returns T0 unchanged, 0 iterations and `converged` True; for
    differentiation its residual is `y` itself (zero-padded to 2N), whose well-posed Hessian
    keeps the implicit derivative finite (an all-zero problem would make it singular). Returns
    (pose, iterations, converged).
    """
    T0 = jax.lax.stop_gradient(T0)
    dtype = X.dtype
    ok = active & jnp.all(jnp.isfinite(T0.wxyz_xyz))
    dummy = jnp.zeros_like(T0.wxyz_xyz).at[0].set(1.0).at[6].set(1.0)  # identity, z = 1
    start = SE3(jnp.where(ok, T0.wxyz_xyz, dummy))
    X, uv = jnp.where(ok, X, 0.0), jnp.where(ok, uv, 0.0)
    sw = jnp.sqrt(jnp.where(ok, w, 0.0))
    R0, t0 = start.rotation().as_matrix(), start.translation()
    scale = jnp.linalg.norm(weighted_jacobian(start, X, K, dist, sw), axis=0)
    scale = jax.lax.stop_gradient(jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0))
    pad = jnp.zeros(2 * X.shape[0], dtype)

    def residual_fn(X, uv, K, dist, sw):
        def residuals(y):
            r = _chart_residuals(R0, t0, y / scale, X, uv, K, dist, sw)
            return jnp.where(ok, r, pad.at[:6].set(y))

        return residuals

    def jacobian_fn(X, K, dist, sw):
        def jacobian(y):
            J = chart_jacobian(start, y / scale, X, K, dist, sw) / scale
            return jnp.where(ok, J, jnp.zeros((pad.shape[0], 6), dtype).at[:6].set(jnp.eye(6)))

        return jacobian

    # The loop runs on constants (it is not differentiated); custom_root differentiates the
    # optimality condition at its solution instead.
    X_, uv_, K_, dist_, sw_ = jax.lax.stop_gradient((X, uv, K, dist, sw))
    found, iterations, converged = _levenberg_marquardt(
        residual_fn(X_, uv_, K_, dist_, sw_),
        jacobian_fn(X_, K_, dist_, sw_),
        jnp.zeros(6, dtype),
        ok,
        max_iterations,
    )
    residuals = residual_fn(X, uv, K, dist, sw)

    def gradient(y):
        return jax.grad(lambda y: 0.5 * jnp.sum(residuals(y) ** 2))(y)

    def tangent_solve(hessian_vector_product, b):
        return jnp.linalg.solve(jax.jacfwd(hessian_vector_product)(b), b)

    y = jax.lax.custom_root(gradient, found, lambda _, y0: y0, tangent_solve)
    pose = SE3(jnp.where(ok, _chart(start, y / scale).wxyz_xyz, T0.wxyz_xyz))
    return pose, iterations, converged


def _levenberg_marquardt(residuals, jacobian, y0, ok, max_iterations: int):
    """The damped Gauss-Newton loop of the module docstring. Returns (y, iterations,
    converged); a lane that is not `ok` takes no step."""
    dtype = y0.dtype
    tol = _tolerance(dtype)
    eye = jnp.eye(6, dtype=dtype)
    r, J = residuals(y0), jacobian(y0)
    state = dict(
        y=y0,
        r=r,
        J=J,
        cost=0.5 * jnp.sum(r * r),
        lam=jnp.asarray(1e-3, dtype),
        nu=jnp.asarray(2.0, dtype),
        iterations=jnp.zeros((), jnp.int32),
        done=~ok,
        converged=~ok,
    )

    def cond(s):
        return ~s["done"] & (s["iterations"] < max_iterations)

    def body(s):
        J = s["J"]
        A, g = matmul(J.T, J), jnp.sum(J * s["r"][:, None], axis=0)
        newton, definite = spd_solve(A, -g)
        change = jnp.sqrt(jnp.sum(jnp.sum(J * newton, axis=1) ** 2))  # |J newton|
        quadratic = definite & (change <= _QUADRATIC_PX)
        converged = definite & (change <= tol)
        damped, _ = spd_solve(A + s["lam"] * eye, -g)
        step = jnp.where(quadratic, newton, damped)
        y = s["y"] + step
        r, J = residuals(y), jacobian(y)
        cost = 0.5 * jnp.sum(r * r)
        predicted = 0.5 * jnp.sum(step * (s["lam"] * step - g))
        rho = (s["cost"] - cost) / jnp.where(predicted > 0, predicted, 1.0)
        finite = jnp.isfinite(cost) & jnp.all(jnp.isfinite(J))
        accept = finite & (quadratic | (cost < s["cost"]))
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        lam = jnp.where(accept, s["lam"] * jnp.where(quadratic, 1.0, shrink), s["lam"] * s["nu"])
        keep = lambda new, old: jnp.where(accept, new, old)  # noqa: E731
        return dict(
            y=keep(y, s["y"]),
            r=keep(r, s["r"]),
            J=keep(J, s["J"]),
            cost=keep(cost, s["cost"]),
            lam=lam,
            nu=jnp.where(accept, 2.0, 2.0 * s["nu"]),
            iterations=s["iterations"] + 1,
            done=converged,
            converged=converged,
        )

    s = jax.lax.while_loop(cond, body, state)
    return s["y"], s["iterations"], s["converged"]
