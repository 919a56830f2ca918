"""Levenberg-Marquardt refinement of a PnP pose, for one problem (vmapped by `jaxreg.pnp`).

`optimistix.LevenbergMarquardt` runs on a chart centred on the start pose T0,
`delta = (v, w) -> T0 @ (SO3.exp(w), v)`: a right perturbation on SO(3) x R^3. At delta = 0 it
has the Jacobian of jaxlie's `T0 @ SE3.exp(delta)` (so covariances are in jaxlie's tangent
convention, `(vx, vy, vz, wx, wy, wz)`, object frame) and the optimum is chart-independent; it
lets the residual be evaluated as start + increment, which keeps float32 accurate (see
`_chart_residuals`), and since the chart is centred on the start, refinement never nears the
rotation-vector singularity at pi. Each component is scaled so that a unit step moves the
residuals by about one pixel, so LM's isotropic damping and optimistix's Cauchy termination
treat depth, in-plane motion and tilts alike. Gradients come from the implicit function theorem
at the optimum (`optimistix.ImplicitAdjoint`); the start pose is a constant.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxlie import SE3, SO3
from jaxtyping import Array

from jaxreg.camera import apply_intrinsics, distort, pose_jacobian

__all__ = ["refine_pose", "weighted_jacobian"]


def _tolerances(dtype) -> tuple[float, float]:
    """(rtol, atol) of optimistix's Cauchy test, in the pixel-scaled LM units of `refine`."""
    return (1e-5, 1e-5) if jnp.finfo(dtype).bits <= 32 else (1e-8, 1e-8)


class _LevenbergMarquardt(optx.LevenbergMarquardt):
    """optimistix's Levenberg-Marquardt plus MINPACK's step-size test: stop when, after a
    rejected step, the next proposed step is below the Cauchy tolerance. optimistix only tests
    accepted steps; at the optimum a float32 loss stops resolving the predicted decrease, every
    step is rejected and the solve would spin until max_iterations (keeping a whole vmapped
    batch iterating) although the iterate no longer moves."""

    def terminate(self, fn, y, args, options, state, tags):
        done, result = super().terminate(fn, y, args, options, state, tags)
        step = jnp.abs(state.y_eval - y) / (self.atol + self.rtol * jnp.abs(y))
        stalled = (state.num_steps_since_acceptance > 0) & (self.norm(step) < 1)
        return done | stalled, result


def _rotation_increment(w: Array, X: Array) -> Array:
    """`SO3.exp(w) @ X - X` for points X (N, 3), without the cancellation of subtracting X:
    `A w x X + B w x (w x X)` with A = sin(t)/t, B = (1 - cos t)/t^2 (double-where at t = 0)."""
    theta_sq = jnp.sum(w * w)
    small = theta_sq < (1e-5 if jnp.finfo(w.dtype).bits <= 32 else 1e-10)
    theta = jnp.sqrt(jnp.where(small, 1.0, theta_sq))
    a = jnp.where(small, 1.0 - theta_sq / 6.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta_sq / 24.0, 2.0 * (jnp.sin(0.5 * theta) / theta) ** 2)
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
    Xc = X @ R0.T + t0
    xy0 = Xc[:, :2] / Xc[:, 2:3]
    r0 = apply_intrinsics(distort(xy0, dist), K) - uv
    dXc = (_rotation_increment(delta[3:], X) + delta[:3]) @ R0.T
    z1 = Xc[:, 2:3] + dXc[:, 2:3]
    dxy = (dXc[:, :2] * Xc[:, 2:3] - Xc[:, :2] * dXc[:, 2:3]) / (Xc[:, 2:3] * z1)
    du = _distortion_increment(xy0, dxy, dist) @ K[:2, :2].T
    return ((r0 + du) * sw[:, None]).reshape(-1)


def weighted_jacobian(pose: SE3, X, K, dist, sw) -> Array:
    """d (weighted pixel residuals) / d delta, `(2N, 6)`, of the right perturbation at `pose`."""
    return (pose_jacobian(pose, X, K, dist) * sw[:, None, None]).reshape(-1, 6)


def refine_pose(T0: SE3, active, X, uv, K, dist, w, *, max_iterations: int):
    """Levenberg-Marquardt from T0 (a constant for differentiation).

    The variable is y = s * delta with s the column norms of the residual Jacobian at T0, so a
    unit change of any component moves the residuals by about one pixel: LM's isotropic damping
    and the Cauchy tolerances then mean the same for depth, in-plane motion and tilts, which
    differ by orders of magnitude in pixels per unit. A lane that is not `active` (its input
    failed, or it is a start not worth refining) or has a non-finite start gets the residual
    `y` itself (zero-padded to 2N): solved at the start, it stops at once, keeps a vmapped batch
    from iterating, and its well-posed Jacobian keeps the implicit adjoint's solve finite (an
    all-zero problem would make it singular). Such a lane returns T0 unchanged and 0
    iterations. Returns (pose, iterations, converged).
    """
    T0 = jax.lax.stop_gradient(T0)
    ok = active & jnp.all(jnp.isfinite(T0.wxyz_xyz))
    dummy = jnp.zeros_like(T0.wxyz_xyz).at[0].set(1.0).at[6].set(1.0)  # identity, z = 1
    start = SE3(jnp.where(ok, T0.wxyz_xyz, dummy))
    X, uv = jnp.where(ok, X, 0.0), jnp.where(ok, uv, 0.0)
    sw = jnp.sqrt(jnp.where(ok, w, 0.0))
    R0, t0 = start.rotation().as_matrix(), start.translation()
    scale = jnp.linalg.norm(weighted_jacobian(start, X, K, dist, sw), axis=0)
    scale = jax.lax.stop_gradient(jnp.where(jnp.isfinite(scale) & (scale > 0), scale, 1.0))

    def fn(y, args):
        residuals = _chart_residuals(R0, t0, y / scale, *args, sw)
        return jnp.where(ok, residuals, jnp.zeros_like(residuals).at[:6].set(y))

    rtol, atol = _tolerances(X.dtype)
    sol = optx.least_squares(
        fn,
        _LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=lx.QR()),
        jnp.zeros(6, X.dtype),
        args=(X, uv, K, dist),
        max_steps=max_iterations,
        throw=False,
        adjoint=optx.ImplicitAdjoint(linear_solver=lx.AutoLinearSolver(well_posed=None)),
    )
    pose = SE3(jnp.where(ok, _chart(start, sol.value / scale).wxyz_xyz, T0.wxyz_xyz))
    iterations = jnp.where(ok, sol.stats["num_steps"], 0).astype(jnp.int32)
    return pose, iterations, sol.result == optx.RESULTS.successful
