"""Perspective-n-Point: `camera_T_object` from 2D-3D correspondences, with a status and a
covariance per problem. One entry per problem: `solve_pnp` for any point set (`PnPResult`),
`solve_pnp_planar` for coplanar points such as a tag's corners (`PlanarPnPResult`, both
candidate poses of the planar two-fold ambiguity).

The camera model (projection, distortion, frames) is `jaxreg.camera.model`'s; the closed-form starts
(EPnP, IPPE) are in `jaxreg.camera._pnp_init`, the refinement in `jaxreg.camera._pnp_refine`, the
covariance in `jaxreg.camera._pnp_covariance`. Tangent vectors are jaxlie's `(vx, vy, vz, wx, wy,
wz)`; covariances are of the *right* perturbation `T_true = T_est @ SE3.exp(delta)`, i.e. in the
object frame. Reprojection RMSE is
`sqrt(mean_i |pi(X_i) - u_i|^2)` over the valid points, in pixels: the root-mean-square of
per-point Euclidean distances (what `cv2.calibrateCamera` reports; `cv2.solvePnPGeneric`
reports the per-coordinate RMS, this divided by sqrt(2)).

Which solution is returned
--------------------------
* General: EPnP's three starts and the two IPPE poses on the best-fit plane of the object
  points (EPnP is ill-posed for coplanar points). With more than 5 valid points the two starts
  that reproject best are refined (on coplanar input these are the two IPPE candidates, so the
  flip is resolved by the refined error, not the initial one); with 4 or 5 all five are, since
  several poses can then explain the pixels. The count is of valid points and the starts
  depend on the valid rows alone, so zero-weight padding never changes the answer. The winner
  is the refined pose with the lowest error among those that keep every point in front of the
  camera; only when none does may one that puts points behind it win, and its status says so.
  Errors equal up to rounding count as equal, and then a start whose refinement converged
  wins. (With n = 4 non-coplanar points the winner can still be a local minimum: P4P has
  several solutions, and no linear method ranks them.)
* Planar: both IPPE candidates, each refined and reported, sorted the same way (in front of the
  camera first, then by error); `ambiguity_ratio = rmse[1] / rmse[0]` measures how decisively
  the data separate them (near 1, possibly a rounding below it, when both reach one minimum).
* Refinement: Levenberg-Marquardt on the pixel reprojection error (`jaxreg.camera._pnp_refine`),
  differentiated by the implicit function theorem at the optimum; the start is a constant.
* Covariance: first order, `sigma_px^2 (J^T W J)^-1` with `J` the pixel Jacobian of the right
  perturbation at the returned pose, for independent isotropic pixel noise of standard
  deviation `sigma_px` per coordinate. Directions the data do not determine (an eigenvalue of
  the column-normalised `J^T W J` below `100 eps` of the largest) get `inf` variance: every
  row and column of the tangent coordinates they involve is `inf`, the others are the inverse
  on the determined directions, and the status is `degenerate`. Near fronto-parallel views of a
  small tag the out-of-plane rotation is so weakly determined that the first-order covariance
  underestimates its spread; the ambiguity ratio flags those views.

Failure handling
----------------
Shapes are checked on the host (at trace time): fewer than 4 points, mismatched point counts or
malformed `K` raise `ValueError`. Data-dependent failures are data: every result carries a
`status` (`PnPStatus`, one per problem) and `converged` is true only with `success`. The pose of
a failed problem is whatever the solver reached; check `status` before using it.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxlie import SE3, SO3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.camera._pnp_batch import checked_inputs, solve_batch, solve_padded
from jaxreg.camera._pnp_covariance import covariance as pose_covariance
from jaxreg.camera._pnp_init import general_starts, image_spread, ippe_candidates, weighted_pca
from jaxreg.camera._pnp_refine import _distort
from jaxreg.camera.model import undistort_points
from jaxreg.core._result import AbstractResult, select_status
from jaxreg.geometry.lie import geodesic_angle

__all__ = ["PlanarPnPResult", "PnPResult", "PnPStatus", "solve_pnp", "solve_pnp_planar"]

# Relative thresholds on standard deviations (square roots of PCA eigenvalues).
_COLLINEAR_TOL = 1e-3  # second/first principal std of object or image points
_PLANAR_TOL = 1e-2  # third/first principal std above which points are not coplanar
_NUM_STARTS = 5  # general PnP: EPnP's three and IPPE's two


class PnPStatus(eqx.Enumeration):
    """Outcome of one PnP solve, per problem (and per candidate of a planar solve); each
    member's value is its message. `result.status == PnPStatus.success` is a boolean array."""

    success = "success: the refined pose is determined in every direction"
    too_few_correspondences = (
        "fewer than 4 valid correspondences (NaN pixels, NaN object points and zero weights "
        "are dropped): pass at least 4"
    )
    degenerate = (
        "degenerate geometry: the object or image points are collinear or coincident, or "
        "otherwise leave the pose undetermined in some direction (its covariance is inf "
        "there): add points off that line"
    )
    not_planar = "the object points are not coplanar: use solve_pnp for 3D point sets"
    behind_camera = (
        "the pose puts object points behind the camera (z <= 0) and no start gave one that "
        "does not: check K, the point order and the object frame"
    )
    non_finite = "non-finite values in the solve: check for inf coordinates or a singular K"
    max_iterations = (
        "Levenberg-Marquardt reached max_iterations before converging: raise max_iterations; "
        "the pose may be inaccurate"
    )


class PnPResult(AbstractResult):
    """One PnP solution and its diagnostics. Every leaf has the batch shape `(...)` in front.

    - `pose`: `SE3` camera_T_object, batch `(...)`.
    - `status`: `PnPStatus`, per problem.
    - `converged`: `(...)` bool, Levenberg-Marquardt met its tolerance (or was not asked to run)
      and `status` is `success`.
    - `iterations`: `(...)` Levenberg-Marquardt steps taken (0 when not refined).
    - `reprojection_rmse_px`: `(...)`, RMS of per-point Euclidean pixel errors over valid points.
    - `covariance`: `(..., 6, 6)` right-perturbation covariance, tangent order
      `(vx, vy, vz, wx, wy, wz)` in the object frame, for `sigma_px` pixel noise per coordinate;
      `inf` in the rows and columns of directions the data do not determine.
    - `translation_sigma`: `(..., 3)` standard deviation of the object origin along the camera's
      x, y, z axes (z is depth), the same units as the object points.
    - `rotation_sigma_deg`: `(..., 3)` standard deviation of the rotation about the object's own
      x, y, z axes, in degrees (for a tag: x, y are out-of-plane tilts, z the in-plane spin).
    """

    pose: SE3
    status: PnPStatus
    converged: Bool[Array, "*batch"]
    iterations: Int[Array, "*batch"]
    reprojection_rmse_px: Float[Array, "*batch"]
    covariance: Float[Array, "*batch 6 6"]
    translation_sigma: Float[Array, "*batch 3"]
    rotation_sigma_deg: Float[Array, "*batch 3"]


class PlanarPnPResult(AbstractResult):
    """Both IPPE candidates of a planar PnP problem, best first.

    - `candidates`: `PnPResult` whose leaves have shape `(..., 2, ...)`: the candidate axis
      follows the problem's batch axes; index 0 is the best (in front of the camera first, then
      the lower reprojection error; see the module docstring for ties).
    - `ambiguity_ratio`: `(...)`, `rmse[1] / rmse[0]`. Near 1 the two poses explain the corners
      equally well (a near-fronto-parallel or small tag); threshold it (e.g. > 3) before trusting
      the best candidate's out-of-plane rotation. `inf` when the second candidate is no
      alternative (it puts points behind the camera, or is non-finite) and the best is.
    - `separation_deg`: `(...)`, geodesic angle between the two candidate rotations. When
      refinement drives both starts into the same minimum it is ~0 and the ratio ~1: then there
      is one solution, whose out-of-plane uncertainty `best.rotation_sigma_deg` shows.
    - `pose`, `status`, `converged`, `iterations`: the best candidate's (`candidates[..., 0]`),
      so a planar result reads like a `PnPResult` where one pose is wanted.

    `result[i]` indexes the problem's batch axes (the candidate axis stays).
    """

    pose: SE3
    status: PnPStatus
    converged: Bool[Array, "*batch"]
    iterations: Int[Array, "*batch"]
    candidates: PnPResult
    ambiguity_ratio: Float[Array, "*batch"]
    separation_deg: Float[Array, "*batch"]

    @property
    def best(self) -> PnPResult:
        """The best candidate, as a `PnPResult` with the problem's batch shape."""
        return self._candidate(0)

    @property
    def second(self) -> PnPResult:
        """The other candidate, as a `PnPResult` with the problem's batch shape."""
        return self._candidate(1)

    def _candidate(self, index: int) -> PnPResult:
        prefix = (slice(None),) * self.ambiguity_ratio.ndim
        return jax.tree.map(lambda leaf: leaf[prefix + (index,)], self.candidates)


# --------------------------------------------------------------------------------------------
# Diagnostics: fit quality, ranking, covariance, status (one problem)
# --------------------------------------------------------------------------------------------


def _sanitise(X, uv, w):
    """Zero out invalid points (NaN pixel or object point, non-positive weight)."""
    valid = jnp.all(jnp.isfinite(uv), -1) & jnp.all(jnp.isfinite(X), -1)
    valid &= jnp.isfinite(w) & (w > 0)
    w = jnp.where(valid, w, 0.0)
    X = jnp.where(valid[:, None], X, 0.0)
    uv = jnp.where(valid[:, None], uv, 0.0)
    return X, uv, w, jnp.sum(valid)


def _geometry_status(obj_evals, img_evals, count, *, planar: bool) -> PnPStatus:
    """Data-dependent checks on the input (PCA eigenvalues, ascending: `(3,)` of the object
    points, `(2,)` of the image points), most fundamental first."""
    obj_std = jnp.sqrt(obj_evals[::-1])
    img_std = jnp.sqrt(img_evals[::-1])
    collinear = (obj_std[1] <= _COLLINEAR_TOL * obj_std[0]) | (
        img_std[1] <= _COLLINEAR_TOL * img_std[0]
    )
    curved = planar & (obj_std[2] > _PLANAR_TOL * obj_std[0])
    return select_status(
        [
            (count < 4, PnPStatus.too_few_correspondences),
            (collinear, PnPStatus.degenerate),
            (curved, PnPStatus.not_planar),
        ],
        PnPStatus.success,
    )


def _normalised_rmse(pose: SE3, X: Array, m: Array, w: Array) -> Array:
    """RMS reprojection error in normalised (K^-1, undistorted) coordinates; inf if not finite."""
    Xc = pose @ X
    err = jnp.sum((Xc[:, :2] / Xc[:, 2:3] - m) ** 2, axis=-1)
    rmse = jnp.sqrt(jnp.sum(w * err) / jnp.maximum(jnp.sum(w), jnp.finfo(err.dtype).tiny))
    return jnp.where(jnp.isfinite(rmse), rmse, jnp.inf)


class _Reprojection(eqx.Module):
    """How well one pose explains one problem (batch `(...)` when vmapped)."""

    rmse: Array  # pixel reprojection RMSE over the valid points
    behind: Array  # some valid point at z <= 0 in the camera frame
    finite: Array  # pose and rmse finite

    @property
    def tier(self) -> Array:
        """0: usable, 1: points behind the camera, 2: non-finite (lower is better)."""
        return jnp.where(self.finite, jnp.where(self.behind, 1, 0), 2)


def _reprojection(pose: SE3, X, uv, K, dist, w) -> _Reprojection:
    # On scalars (per point an (N,) array): vmapped, the projection is a few fused loops.
    R = pose.rotation().as_matrix()
    t = pose.translation()
    Xc = [R[i, 0] * X[:, 0] + R[i, 1] * X[:, 1] + R[i, 2] * X[:, 2] + t[i] for i in range(3)]
    d = None if dist is None else tuple(dist[i] for i in range(5))
    xd, yd = _distort(Xc[0] / Xc[2], Xc[1] / Xc[2], d)
    sw = jnp.sqrt(w)
    ru = (K[0, 0] * xd + K[0, 1] * yd + K[0, 2] - uv[:, 0]) * sw
    rv = (K[1, 0] * xd + K[1, 1] * yd + K[1, 2] - uv[:, 1]) * sw
    rmse = jnp.sqrt(jnp.sum(ru * ru + rv * rv) / jnp.maximum(jnp.sum(w), jnp.finfo(ru.dtype).tiny))
    return _Reprojection(
        rmse=rmse,
        behind=jnp.any((Xc[2] <= 0) & (w > 0)),
        finite=jnp.all(jnp.isfinite(pose.wxyz_xyz)) & jnp.isfinite(rmse),
    )


def _ranking(fits: _Reprojection, converged: Array, eligible: Array | bool = True) -> Array:
    """Order of a batch `(S,)` of fits, best first: eligible before not, then by tier (in front
    of the camera before behind it before non-finite), then by reprojection error.

    Starts that reach the same minimum differ in error only by rounding (which zero-weight
    padding, for one, changes), so rounding must not decide which of them wins: among the best
    tier, fits within `sqrt(eps) * (1 + rmse)` pixels of the lowest error count as equal, and
    of those the ones whose Levenberg-Marquardt converged come first.
    """
    tier = jnp.where(eligible, fits.tier, 3)
    rmse = jnp.where(fits.finite, fits.rmse, jnp.inf)
    best_tier = jnp.min(tier)
    lowest = jnp.min(jnp.where(tier == best_tier, rmse, jnp.inf))
    slack = jnp.sqrt(jnp.finfo(rmse.dtype).eps) * (1.0 + lowest)
    tied = (tier == best_tier) & (rmse <= lowest + slack)
    return jnp.lexsort((rmse, ~(tied & converged), tier))


def _swap_pair(fits: _Reprojection, converged: Array) -> Array:
    """Whether `_ranking` puts the second of a pair `(2,)` of fits first, as comparisons (a
    batched sort of pairs is a slow kernel on XLA's CPU backend)."""
    tier = fits.tier
    rmse = jnp.where(fits.finite, fits.rmse, jnp.inf)
    best_tier = jnp.minimum(tier[0], tier[1])
    lowest = jnp.minimum(
        jnp.where(tier[0] == best_tier, rmse[0], jnp.inf),
        jnp.where(tier[1] == best_tier, rmse[1], jnp.inf),
    )
    slack = jnp.sqrt(jnp.finfo(rmse.dtype).eps) * (1.0 + lowest)
    late = ~((tier == best_tier) & (rmse <= lowest + slack) & converged)
    # Lexicographic (tier, late, rmse), the first kept on equal keys (lexsort is stable).
    return (tier[1] < tier[0]) | (
        (tier[1] == tier[0]) & ((late[0] & ~late[1]) | ((late[0] == late[1]) & (rmse[1] < rmse[0])))
    )


def _result(
    pose,
    fit: _Reprojection,
    iterations,
    lm_converged,
    status,
    X,
    K,
    dist,
    w,
    sigma_px,
    covariance=None,
):
    """The `PnPResult` of one pose: covariance (`pose_covariance`'s, computed unless given), and the
    final status (input failures first)."""
    if covariance is None:
        covariance = pose_covariance(pose, X, K, dist, w, sigma_px)
    cov, t_sigma, r_sigma, undetermined = covariance
    late = select_status(
        [
            (~fit.finite, PnPStatus.non_finite),
            (fit.behind, PnPStatus.behind_camera),
            (undetermined, PnPStatus.degenerate),
            (~lm_converged, PnPStatus.max_iterations),
        ],
        PnPStatus.success,
    )
    status = select_status([(status != PnPStatus.success, status)], late)
    return PnPResult(
        pose=pose,
        status=status,
        converged=status == PnPStatus.success,
        iterations=jnp.asarray(iterations, jnp.int32),
        reprojection_rmse_px=fit.rmse,
        covariance=cov,
        translation_sigma=t_sigma,
        rotation_sigma_deg=r_sigma,
    )


# --------------------------------------------------------------------------------------------
# One problem: (X (N, 3), uv (N, 2), K (3, 3), dist (5,) or None, w (N,)); vmapped over batches
# --------------------------------------------------------------------------------------------


def _prologue(X, uv, K, dist, w, *, planar: bool):
    """Valid points, normalised image points, the object points' PCA and the input's status."""
    X, uv, w, count = _sanitise(X, uv, w)
    m = undistort_points(uv, K, dist)
    object_pca = weighted_pca(X, w)
    status = _geometry_status(object_pca[1], image_spread(m, w), count, planar=planar)
    return X, uv, w, count, m, object_pca, status


class _Refined(eqx.Module):
    """One problem's refined pose(s) before the covariance: batch `()` or `(2,)` (candidates)."""

    pose: SE3
    fit: _Reprojection
    iterations: Array
    converged: Array
    status: PnPStatus  # the input's, per problem
    X: Array  # the sanitised points and weights the covariance needs
    w: Array


class _Starts(eqx.Module):
    """One problem's sanitised input, its status and the starts to refine (batch `(S,)`)."""

    X: Array
    uv: Array
    w: Array
    status: PnPStatus
    starts: SE3
    go: Array  # (S,) refine this start
    eligible: Array  # (S,) may win


def _general_starts(X, uv, K, dist, w) -> _Starts:
    X, uv, w, count, m, object_pca, status = _prologue(X, uv, K, dist, w, planar=False)
    starts = general_starts(X, m, w, object_pca)
    order = jnp.argsort(jax.vmap(lambda T: _normalised_rmse(T, X, m, w))(starts))
    starts = jax.tree.map(lambda leaf: leaf[order], starts)
    # All five starts with 4 or 5 valid points, else the two that reproject best.
    eligible = jnp.arange(_NUM_STARTS) < jnp.where(count <= 5, _NUM_STARTS, 2)
    go = eligible & (status == PnPStatus.success)
    return _Starts(X, uv, w, status, starts, go, eligible)


def _planar_starts(X, uv, K, dist, w) -> _Starts:
    X, uv, w, count, m, object_pca, status = _prologue(X, uv, K, dist, w, planar=True)
    starts = ippe_candidates(X, m, w, object_pca)
    go = jnp.broadcast_to(status == PnPStatus.success, (2,))
    return _Starts(X, uv, w, status, starts, go, jnp.ones(2, bool))


def _general_choose(st: _Starts, poses, iterations, converged, K, dist) -> _Refined:
    """The best refined start (see the module docstring)."""
    fits = jax.vmap(lambda T: _reprojection(T, st.X, st.uv, K, dist, st.w))(poses)
    best = _ranking(fits, converged, st.eligible)[0]
    pose, fit, iterations, converged = jax.tree.map(
        lambda leaf: leaf[best], (poses, fits, iterations, converged)
    )
    return _Refined(pose, fit, iterations, converged, st.status, st.X, st.w)


def _planar_choose(st: _Starts, poses, iterations, converged, K, dist) -> _Refined:
    """Both candidates, best first."""
    fits = jax.vmap(lambda T: _reprojection(T, st.X, st.uv, K, dist, st.w))(poses)
    swap = _swap_pair(fits, converged)
    poses, fits, iterations, converged = jax.tree.map(
        lambda leaf: jnp.where(swap, leaf[::-1], leaf), (poses, fits, iterations, converged)
    )
    return _Refined(poses, fits, iterations, converged, st.status, st.X, st.w)


def _planar_result(refined: _Refined, K, dist, sigma_px, covariance) -> PlanarPnPResult:
    """Both candidates' results, the ambiguity ratio and the separation of one problem."""
    r = refined
    both = jax.vmap(
        lambda T, fit, it, conv, cov: _result(
            T, fit, it, conv, r.status, r.X, K, dist, r.w, sigma_px, cov
        )
    )(r.pose, r.fit, r.iterations, r.converged, covariance)
    rmse, tier = r.fit.rmse, r.fit.tier
    ratio = rmse[1] / jnp.maximum(rmse[0], jnp.finfo(rmse.dtype).tiny)
    ratio = jnp.where(tier[1] > tier[0], jnp.inf, ratio)
    rotations = r.pose.rotation()
    separation = jnp.rad2deg(geodesic_angle(SO3(rotations.wxyz[0]), SO3(rotations.wxyz[1])))
    best = jax.tree.map(lambda leaf: leaf[0], both)
    return PlanarPnPResult(
        pose=best.pose,
        status=best.status,
        converged=best.converged,
        iterations=best.iterations,
        candidates=both,
        ambiguity_ratio=ratio,
        separation_deg=separation,
    )


def _general_result(refined: _Refined, K, dist, sigma_px, covariance) -> PnPResult:
    r = refined
    return _result(
        r.pose,
        r.fit,
        r.iterations,
        r.converged,
        r.status,
        r.X,
        K,
        dist,
        r.w,
        sigma_px,
        covariance,
    )


@functools.partial(jax.jit, static_argnames=("batch", "max_iterations"))
def _solve_general(arrays, sigma_px, *, batch, max_iterations):
    return solve_batch(
        _general_starts,
        _general_choose,
        _general_result,
        arrays,
        batch,
        sigma_px,
        refine=True,
        iterations=max_iterations,
    )


@functools.partial(jax.jit, static_argnames=("batch", "max_iterations", "refine"))
def _solve_planar(arrays, sigma_px, *, batch, max_iterations, refine):
    return solve_batch(
        _planar_starts,
        _planar_choose,
        _planar_result,
        arrays,
        batch,
        sigma_px,
        refine=refine,
        iterations=max_iterations,
    )


# --------------------------------------------------------------------------------------------
# Public solvers
# --------------------------------------------------------------------------------------------


def solve_pnp(
    object_points: Float[ArrayLike, "*batch N 3"],
    image_points: Float[ArrayLike, "*batch N 2"],
    K: Float[ArrayLike, "*batch 3 3"],
    *,
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
    weights: Float[ArrayLike, "*batch N"] | None = None,
    sigma_px: float | Float[ArrayLike, ""] = 1.0,
    max_iterations: int = 100,
) -> PnPResult:
    """General PnP: camera_T_object from N >= 4 correspondences (coplanar allowed).

    - `object_points` `(..., N, 3)`: points in the object frame.
    - `image_points` `(..., N, 2)`: observed pixels (with distortion, if any). NaN rows are
      dropped like zero weights.
    - `K` `(3, 3)` or `(..., 3, 3)`, `dist_coeffs` `None` or `(..., 4|5)` (OpenCV order).
    - `weights` `(..., N)`: 0 marks padding; otherwise relative inverse variances of the pixels.
    - `sigma_px`: pixel noise std per coordinate, scales `covariance` and the sigmas.
    - `max_iterations`: Levenberg-Marquardt step budget per start (static: a new value
      recompiles).

    Leading batch axes of all arguments broadcast; one call solves every problem (vmap inside;
    the problem count is padded to a few sizes, so counts that change from call to call share
    compiled programs). Returns a `PnPResult` (pose camera_T_object, status, covariance;
    see the module docstring for which start wins); differentiable with respect to every
    floating input by implicit differentiation at the optimum. Raises `ValueError` for N < 4 or
    malformed shapes.
    """
    arrays, sigma_px, batch = checked_inputs(
        "solve_pnp", object_points, image_points, K, dist_coeffs, weights, sigma_px
    )
    return solve_padded(_solve_general, arrays, sigma_px, batch, max_iterations=max_iterations)


def solve_pnp_planar(
    object_points: Float[ArrayLike, "*batch N 3"],
    image_points: Float[ArrayLike, "*batch N 2"],
    K: Float[ArrayLike, "*batch 3 3"],
    *,
    dist_coeffs: Float[ArrayLike, "*batch D"] | None = None,
    weights: Float[ArrayLike, "*batch N"] | None = None,
    sigma_px: float | Float[ArrayLike, ""] = 1.0,
    refine: bool = True,
    max_iterations: int = 100,
) -> PlanarPnPResult:
    """Planar PnP (IPPE): both candidate poses camera_T_object of coplanar points.

    `object_points` `(..., N, 3)` must be coplanar (any plane; a tag's corners are usually
    `jaxreg.tag_object_points(size)`, on z = 0); other arguments as in `solve_pnp`. With
    `refine=False` the candidates are IPPE's analytic poses (what `cv2.solvePnPGeneric` with
    `SOLVEPNP_IPPE`/`IPPE_SQUARE` returns); by default each is refined by Levenberg-Marquardt
    to the nearest minimum of the pixel reprojection error, which for a 45 mm tag at 0.55 m with
    0.2 px corner noise moves the analytic pose by up to ~0.7 mm and a few degrees of tilt (the
    weakly determined directions). Returns a `PlanarPnPResult`: `.pose` / `.best` the best
    candidate, `.candidates` both (batch `(..., 2)`), `.ambiguity_ratio`, `.separation_deg`.
    """
    arrays, sigma_px, batch = checked_inputs(
        "solve_pnp_planar", object_points, image_points, K, dist_coeffs, weights, sigma_px
    )
    return solve_padded(
        _solve_planar, arrays, sigma_px, batch, max_iterations=max_iterations, refine=refine
    )
