"""Covariance of a converged ICP pose: from measurement noise (:func:`icp_covariance`, the
sensitivity or "Censi" covariance) and from an uncertain start (:func:`init_spread`).

Both are public through :mod:`jaxreg.registration.icp`. The closed form differentiates the same
frozen-correspondence objective, gradient and Hessian that give ICP its implicit derivative
(:func:`jaxreg.registration._icp_core.pose_gradient`,
:func:`~jaxreg.registration._icp_core.pose_hessian`), so the two cannot drift apart; the noise
models come from :mod:`jaxreg.uncertainty.noise`.

Conventions: covariances are of the right perturbation ``T_true = T_est @ exp(delta)``,
``delta ~ N(0, Sigma)``, in the source (object) frame, tangent order
``(vx, vy, vz, wx, wy, wz)``; :func:`jaxreg.geometry.lie.adjoint_transport` moves them to the target
frame.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Float

from jaxreg.geometry.lie import se3_exp
from jaxreg.registration._icp_core import (
    LoopSettings,
    Problem,
    correspond,
    pose_gradient,
    pose_hessian,
    pseudo_inverse,
)
from jaxreg.registration._icp_setup import ICPOptions, prepare, resolve_options, run_starts
from jaxreg.uncertainty import AbstractPointNoise, IsotropicNoise

NoiseLike = AbstractPointNoise | float | None


def _as_noise(noise, name: str) -> AbstractPointNoise | None:
    if noise is None or isinstance(noise, AbstractPointNoise):
        return noise
    sigma = jnp.asarray(noise)
    if sigma.ndim != 0:
        raise ValueError(
            f"{name} must be a scalar sigma (metres) or a noise model (IsotropicNoise, "
            f"DepthNoise, PointCovariance), got an array of shape {sigma.shape}"
        )
    return IsotropicNoise(sigma)


@eqx.filter_jit
def _sensitivity_covariance(
    problem: Problem, opts: LoopSettings, pose: SE3, source_cov, target_cov
):
    """``H^+ (sum_i B_i C_i B_i^T) H^+`` with unobservable axes set to ``inf``."""
    pose = SE3(pose.wxyz_xyz.astype(problem.source.dtype))
    pairs = correspond(problem, opts, pose, opts.distances[-1])

    def gradient(source, target):
        prob = eqx.tree_at(lambda p: (p.source, p.target), problem, (source, target))
        return pose_gradient(prob, opts, pose, pairs)

    # B = d(grad_delta F)/d(points): six reverse passes, one per pose axis, run one after
    # the other. Not `jax.jacrev`: its vmapped scatter-add is miscompiled by XLA on CPU in
    # float32 once the update count passes ~2^15 (wrong B, jax 0.10.2; a test guards it).
    _, pullback = jax.vjp(gradient, problem.source, problem.target)
    eye = jnp.eye(6, dtype=problem.source.dtype)
    mixed_source, mixed_target = jax.lax.map(pullback, eye)
    spread = jnp.zeros((6, 6), eye.dtype)
    if source_cov is not None:
        spread += jnp.einsum("anj,njk,bnk->ab", mixed_source, source_cov, mixed_source)
    if target_cov is not None:
        spread += jnp.einsum("anj,njk,bnk->ab", mixed_target, target_cov, mixed_target)
    inverse, null, _ = pseudo_inverse(pose_hessian(problem, opts, pose, pairs))
    cov = inverse @ spread @ inverse
    # Axes that take part in an unconstrained direction have no finite variance.
    free = jnp.diag(null) > 1e-4
    cov = jnp.where(free[:, None] | free[None, :], jnp.inf, cov)
    return 0.5 * (cov + cov.T)


def _noise_covariance(noise: AbstractPointNoise | None, points, rows: int, dtype):
    """``(rows, 3, 3)`` covariances of the finite rows of ``points``, zero elsewhere and on
    the rows that :func:`jaxreg.registration.solver.prepare` appended as padding."""
    if noise is None:
        return None
    points = jnp.asarray(points, dtype)
    ok = jnp.all(jnp.isfinite(points), axis=-1)
    cov = noise.covariance(jnp.where(ok[:, None], points, 0.0))
    cov = jnp.where(ok[:, None, None], cov, 0.0)
    return jnp.pad(cov, ((0, rows - cov.shape[0]), (0, 0), (0, 0)))


def icp_covariance(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    pose: SE3,
    *,
    options: ICPOptions | None = None,
    point_sigma: Float[ArrayLike, ""] | None = None,
    source_noise: NoiseLike = None,
    target_noise: NoiseLike = None,
    init_covariance: Float[ArrayLike, "6 6"] | None = None,
    **overrides: Any,
) -> Float[Array, "6 6"]:
    """Covariance ``(6, 6)`` of a converged ICP pose under measurement noise.

    At the converged ``pose`` the correspondences are recomputed exactly as
    :func:`jaxreg.icp` forms them (nearest valid target point within the final
    ``max_correspondence_distance``, the same trimming and kernel) and held fixed. The
    objective ``F(delta, z)`` (``z`` the point coordinates, ``delta`` a right perturbation of
    ``pose``) is stationary in ``delta`` at the solution, so by the implicit function theorem
    a measurement perturbation ``dz`` moves the solution by ``-H^-1 B dz`` with
    ``H = d^2F/d delta^2`` and ``B = d^2F/(d delta dz)``. With independent point noise of
    covariances ``C_i``:

        ``Sigma = H^-1 (sum_i B_i C_i B_i^T) H^-1``

    (Censi's formula, here from automatic differentiation, so it holds for both methods,
    robust kernels and trimming alike). Target normals are treated as exact.

    How far it can be trusted, measured against Monte Carlo on PCL's milk.pcd (Kinect scan
    re-measured with depth noise ``sigma_z = 2 mm * z^2`` along each camera ray and
    re-registered with vmapped ICP; predicted / measured sigma per axis
    ``(vx, vy, vz, wx, wy, wz)``, from ``paper_figs/fig_covariance_vs_monte_carlo.py``):

    * point-to-plane, noisy scan registered to a 4 mm voxel model (300 draws):
      0.95 0.91 0.95 0.93 0.95 0.86. Within 20% (a test checks it).
    * point-to-plane, model registered to the noisy scan as target, normals re-estimated from
      every noisy copy (100 draws): 0.85 0.87 0.79 0.83 0.69 0.86. The formula holds normals
      fixed and sees no correspondence changes, so it is 15-30% optimistic here.
    * point-to-point, same data as the first (300 draws): 0.61 0.60 0.70 0.65 0.63 0.20.
      The closed form is overconfident by 30-40%, and fivefold about the axis the carton's
      faces barely constrain: point-to-point's solution jumps between discrete
      correspondence sets (a 4 mm target spacing against ~1.3 mm of noise), which a
      linearisation with frozen matches cannot see. The gap widens, not narrows, with less
      noise (ratios 0.1-0.5 at a tenth of it). Prefer point-to-plane for error bars.

    Neither includes the spread from where ICP starts: on a resampled surface there are many
    nearby fixed points, and the start picks one; ``init_covariance`` adds it.

    Args:
        source: ``(N, 3)`` source points (NaN rows ignored), as given to :func:`jaxreg.icp`.
        target: ``(M, 3)`` target points (NaN rows ignored).
        pose: the converged ``SE3`` source -> target (e.g. ``icp(...).pose``).
        options: the :class:`~jaxreg.ICPOptions` the registration was run with (see
            :func:`jaxreg.icp`); the covariance uses the last correspondence distance, and
            ``max_iterations`` and ``tolerance`` only with ``init_covariance``.
        point_sigma: shorthand for isotropic noise of ``point_sigma`` metres per axis on
            every point of *both* clouds; not allowed together with ``source_noise`` or
            ``target_noise``.
        source_noise, target_noise: the noise of each cloud: ``None`` (exact), a scalar
            sigma (isotropic, metres) or a noise model
            (:class:`~jaxreg.uncertainty.IsotropicNoise`,
            :class:`~jaxreg.uncertainty.DepthNoise` for lifted depth,
            :class:`~jaxreg.uncertainty.PointCovariance`), in the frame of that cloud.
        init_covariance: ``(6, 6)`` covariance of the initial pose's right perturbation. When
            given, the :func:`init_spread` of ICP re-run from 13 sigma points of that
            Gaussian around ``pose`` is added (zero when every start converges to the same
            pose; large when some fall into another basin).
        **overrides: fields of :class:`~jaxreg.ICPOptions` by name (``method=``,
            ``target_normals=``, ...), replacing those of ``options``.

    Returns:
        ``(6, 6)`` covariance of the right perturbation of ``pose`` in jaxlie's tangent order
        ``(vx, vy, vz, wx, wy, wz)`` (metres and radians, source frame). Axes that take part
        in a direction the geometry leaves unconstrained (a plane or a cylinder for
        point-to-plane, a sphere for both) have ``inf`` in their rows and columns.

    Raises:
        ValueError: bad shapes or grid (as :func:`jaxreg.icp`), no noise given, a noise that
            is neither a scalar nor a model, or ``point_sigma`` together with a per-cloud
            noise.
        TypeError: a keyword that is not a field of :class:`~jaxreg.ICPOptions`.
    """
    if point_sigma is not None:
        if source_noise is not None or target_noise is not None:
            raise ValueError(
                "give either point_sigma (the same isotropic noise on both clouds) or "
                "source_noise / target_noise, not both"
            )
        source_noise = target_noise = point_sigma
    source_noise = _as_noise(source_noise, "source_noise")
    target_noise = _as_noise(target_noise, "target_noise")
    if source_noise is None and target_noise is None:
        raise ValueError(
            "icp_covariance needs a noise model: point_sigma, source_noise or target_noise"
        )
    if not isinstance(pose, SE3) or pose.get_batch_axes() != ():
        raise ValueError("pose must be one jaxlie.SE3 (vmap icp_covariance for a batch)")
    options = resolve_options(options, overrides, "icp_covariance")
    problem, opts, sizes = prepare(source, target, options)
    dtype = problem.source.dtype
    cov = _sensitivity_covariance(
        problem,
        opts,
        pose,
        _noise_covariance(source_noise, source, problem.source.shape[0], dtype),
        _noise_covariance(target_noise, target, problem.target.shape[0], dtype),
    )
    if init_covariance is not None:
        cov = cov + _spread(problem, opts, sizes, pose, init_covariance, 1.0)
    return cov


def _sigma_points(covariance: Array, kappa: float) -> tuple[Array, Array]:
    """Unscented-transform points ``(2n+1, n)`` and weights ``(2n+1,)`` of ``N(0, cov)``."""
    n = covariance.shape[-1]
    lam, vec = jnp.linalg.eigh(covariance)
    root = vec * jnp.sqrt(jnp.maximum(lam, 0.0) * (n + kappa))  # columns: scaled axes
    points = jnp.concatenate([jnp.zeros((1, n), covariance.dtype), root.T, -root.T])
    weights = jnp.concatenate(
        [jnp.array([kappa / (n + kappa)]), jnp.full((2 * n,), 0.5 / (n + kappa))]
    ).astype(covariance.dtype)
    return points, weights


def _spread(
    problem: Problem, opts: LoopSettings, sizes: tuple[int, int], pose: SE3, init_covariance, kappa
) -> Float[Array, "6 6"]:
    """:func:`init_spread` on a prepared problem."""
    cov0 = jnp.asarray(init_covariance, pose.wxyz_xyz.dtype)
    if cov0.shape != (6, 6):
        raise ValueError(f"init_covariance must be (6, 6), got {cov0.shape}")
    if kappa < 0:
        raise ValueError(f"kappa must be >= 0, got {kappa}")
    points, weights = _sigma_points(cov0, kappa)
    starts = SE3(pose.wxyz_xyz[None]) @ se3_exp(points)
    results = run_starts(problem, opts, sizes, starts)
    deltas = (SE3(pose.wxyz_xyz[None]).inverse() @ results.pose).log()
    centred = deltas - weights @ deltas
    return jnp.einsum("s,si,sj->ij", weights, centred, centred)


def init_spread(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    pose: SE3,
    init_covariance: Float[ArrayLike, "6 6"],
    *,
    kappa: float = 1.0,
    options: ICPOptions | None = None,
    **overrides: Any,
) -> Float[Array, "6 6"]:
    """Covariance ``(6, 6)`` of ICP's result caused by an uncertain initial pose.

    The initial pose is modelled as ``pose @ exp(d)``, ``d ~ N(0, init_covariance)`` (right
    perturbation, jaxlie tangent order): the converged ``pose`` stands in for the truth. The
    13 unscented sigma points ``d = 0, +-sqrt((6 + kappa) lambda_k) u_k`` (``lambda_k, u_k``
    the eigenpairs of ``init_covariance``), with weights ``kappa / (6 + kappa)`` and
    ``1 / (2 (6 + kappa))``, are registered in one vmapped call (as
    :func:`jaxreg.multistart_icp` does), and the weighted covariance of the results' right
    perturbations ``log(pose^-1 @ T_j)`` is returned. Starts that converge to the same fixed
    point add nothing; starts that stop early or fall into another basin add their spread,
    which is the overconfidence a sensor-noise-only covariance hides.

    Args:
        source, target, pose: as for :func:`icp_covariance`.
        init_covariance: ``(6, 6)`` PSD, metres and radians.
        kappa: spread of the sigma points (``>= 0``); the default reaches
            ``sqrt(7) = 2.6`` standard deviations along each principal axis.
        options, **overrides: ICP's options, as for :func:`jaxreg.icp`.

    Returns:
        ``(6, 6)`` covariance of the right perturbation of ``pose``, ``(vx, vy, vz, wx, wy,
        wz)``, metres and radians, source frame.
    """
    options = resolve_options(options, overrides, "init_spread")
    problem, opts, sizes = prepare(source, target, options, grid_capacity=24)
    return _spread(problem, opts, sizes, pose, init_covariance, kappa)
