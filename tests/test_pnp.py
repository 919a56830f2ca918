"""Projection, general PnP and planar PnP (IPPE), checked against OpenCV when it imports.

Compile time dominates on a small CPU, so each solver is compiled once per configuration on one
batch that holds every case the tests need (random views, Monte Carlo draws, finite-difference
perturbations, padded and degenerate lanes); the tests read their slices of it.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3

from jaxreg.pnp import (
    PnPStatus,
    detect_tags,
    pose_jacobian,
    project,
    projection_jacobian,
    reprojection_error,
    solve_pnp,
    solve_pnp_planar,
    solve_pnp_planar_result,
    solve_pnp_result,
    tag_object_points,
    undistort_points,
)

try:
    import cv2
except ImportError:
    cv2 = None

needs_cv2 = pytest.mark.skipif(cv2 is None, reason="OpenCV (peers extra) not installed")

K = np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0], [0.0, 0.0, 1.0]])
DIST = np.array([-0.28, 0.09, 1.2e-3, -8e-4, -0.02])
TAG = 0.045
TAG_POINTS = np.array(tag_object_points(TAG), np.float64)
FACING = np.diag([1.0, -1.0, -1.0])  # tag z (out of its face) toward the camera, y up in image
# OpenCV's LM stops early by default; these criteria let it reach the minimum ours reaches.
CV_TIGHT = (3, 500, 1e-14)  # TERM_CRITERIA_COUNT + TERM_CRITERIA_EPS


def _rotation(rotvec):
    with jax.enable_x64(True):
        return np.array(SO3.exp(jnp.asarray(rotvec, jnp.float64)).as_matrix())


def _project_np(R, t, X):
    """Reference pinhole projection (no distortion) in float64 numpy."""
    Xc = X @ R.T + t
    return (Xc[:, :2] / Xc[:, 2:3]) @ K[:2, :2].T + K[:2, 2]


def _tag_view(rng, tilt_deg):
    """A tag facing the camera 0.5-0.6 m away, tilted by `tilt_deg` about a random axis in the
    image plane, with any in-plane spin."""
    axis = np.array([*rng.normal(size=2), 0.0])
    axis *= np.deg2rad(tilt_deg) / np.linalg.norm(axis)
    R = _rotation(axis) @ FACING @ _rotation([0.0, 0.0, rng.uniform(-np.pi, np.pi)])
    t = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.5, 0.6)])
    return R, t


def _pose_gap(T, R, t):
    """(translation gap in mm, rotation gap in degrees) between a 4x4 pose and (R, t).

    The angle comes from the chordal distance |R1 - R2|_F = 2 sqrt(2) sin(angle / 2), which
    keeps float32 poses' small gaps (arccos of the trace would add ~0.03 degrees of rounding)."""
    chord = np.linalg.norm(np.asarray(T[:3, :3], np.float64) - R)
    angle = 2.0 * np.arcsin(min(chord / (2.0 * np.sqrt(2.0)), 1.0))
    return np.linalg.norm(T[:3, 3] - t) * 1e3, np.rad2deg(angle)


def _cv_candidates(obj, img, flags, refine):
    """OpenCV's candidates as (rmse px, R, t), best first; rmse per point as ours."""
    if flags == "sqpnp":
        _, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
        rvecs, tvecs = [rvec], [tvec]
    else:
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, None, flags=flags)
    out = []
    for rvec, tvec in zip(rvecs, tvecs, strict=True):
        if refine:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec, criteria=CV_TIGHT)
        proj, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
        rmse = np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=-1)))
        out.append((rmse, cv2.Rodrigues(rvec)[0], tvec.ravel()))
    return sorted(out, key=lambda c: c[0])


# --------------------------------------------------------------------------------------------
# Projection
# --------------------------------------------------------------------------------------------


@needs_cv2
@pytest.mark.parametrize("ncoef", [4, 5])
def test_project_matches_opencv_with_distortion(x64, ncoef):
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-0.3, 0.3, (50, 2)), rng.uniform(0.4, 1.5, 50)])
    ours = np.asarray(project(points, K, DIST[:ncoef]))
    ref, _ = cv2.projectPoints(points, np.zeros(3), np.zeros(3), K, DIST[:ncoef])
    np.testing.assert_allclose(ours, ref.reshape(-1, 2), atol=1e-8)
    # OpenCV has no skew; ours adds K[0, 1] * y'' to u.
    K_skew = K.copy()
    K_skew[0, 1] = 0.7
    skewed = np.asarray(project(points, K_skew, DIST[:ncoef]))
    distorted_y = (ours[:, 1] - K[1, 2]) / K[1, 1]
    np.testing.assert_allclose(skewed[:, 0] - ours[:, 0], 0.7 * distorted_y, atol=1e-9)


def test_undistort_inverts_projection(x64):
    rng = np.random.default_rng(1)
    xy = rng.uniform(-0.4, 0.4, (2, 3, 20, 2))  # leading batch axes
    points = np.concatenate([xy, np.ones((2, 3, 20, 1))], axis=-1)
    np.testing.assert_allclose(undistort_points(project(points, K, DIST), K, DIST), xy, atol=1e-10)
    np.testing.assert_allclose(undistort_points(project(points, K), K), xy, atol=1e-12)


@jax.jit
def _jacobians_and_differences(cam, pose, obj, h):
    """Analytic Jacobians and central differences of `project` and of the pixels under a right
    perturbation of the pose, all in one compiled call."""
    J = projection_jacobian(cam, K, DIST)
    steps = jnp.eye(3, dtype=cam.dtype) * h
    shift = steps.reshape(3, *(1,) * (cam.ndim - 1), 3)
    fd = (project(cam + shift, K, DIST) - project(cam - shift, K, DIST)) / (2 * h)
    Jp = pose_jacobian(pose, obj, K, DIST)

    def pixels(tangent):
        T = pose @ SE3.exp(tangent)  # first order is all a central difference sees
        R, t = T.rotation().as_matrix(), T.translation()
        return project(jnp.einsum("...ij,...nj->...ni", R, obj) + t[..., None, :], K, DIST)

    tangents = jnp.eye(6, dtype=cam.dtype) * h
    fdp = jax.vmap(
        lambda e: (
            (
                pixels(jnp.broadcast_to(e, (*pose.get_batch_axes(), 6)))
                - pixels(jnp.broadcast_to(-e, (*pose.get_batch_axes(), 6)))
            )
            / (2 * h)
        )
    )(tangents)
    return J, jnp.moveaxis(fd, 0, -1), Jp, jnp.moveaxis(fdp, 0, -1), pixels(jnp.zeros(6))


def test_jacobians_and_reprojection_error(x64):
    batch = (3, 2)
    rng = np.random.default_rng(2)
    n = 5
    cam = np.concatenate(
        [rng.uniform(-0.2, 0.2, (*batch, n, 2)), rng.uniform(0.5, 1.0, (*batch, n, 1))], -1
    )
    pose = SE3.from_rotation_and_translation(
        SO3.exp(jnp.asarray(rng.normal(scale=0.3, size=(*batch, 3)))),
        jnp.asarray(np.broadcast_to([0.01, -0.02, 0.6], (*batch, 3))),
    )
    obj = rng.uniform(-0.05, 0.05, (*batch, n, 3))
    J, fd, Jp, fdp, pixels = _jacobians_and_differences(cam, pose, obj, 1e-6)
    assert J.shape == (*batch, n, 2, 3) and Jp.shape == (*batch, n, 2, 6)
    np.testing.assert_allclose(J, fd, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(Jp, fdp, rtol=1e-6, atol=1e-4)
    observed = np.asarray(pixels) + np.array([3.0, 4.0])
    np.testing.assert_allclose(reprojection_error(pose, obj, observed, K, DIST), 5.0, rtol=1e-12)


# --------------------------------------------------------------------------------------------
# Planar PnP: one float32 solve (the default dtype) of every planar case
# --------------------------------------------------------------------------------------------

N_VIEWS, N_DRAWS, N_FRONTO = 64, 1000, 64
MC_R = _rotation([np.deg2rad(30.0), 0.0, 0.0]) @ FACING @ _rotation([0.0, 0.0, 0.3])
MC_T = np.array([0.03, -0.02, 0.55])


@pytest.fixture(scope="module")
def planar():
    rng = np.random.default_rng(10)
    views = [_tag_view(rng, rng.uniform(0.0, 40.0)) for _ in range(N_VIEWS)]
    images = np.stack([_project_np(R, t, TAG_POINTS) for R, t in views])
    images += rng.normal(scale=0.2, size=images.shape)
    mc = _project_np(MC_R, MC_T, TAG_POINTS) + rng.normal(scale=0.2, size=(N_DRAWS, 4, 2))
    R0, t0 = _tag_view(rng, 0.0)
    fronto = _project_np(R0, t0, TAG_POINTS) + rng.normal(scale=0.2, size=(N_FRONTO, 4, 2))
    nan_corner = images[0].copy()
    nan_corner[2] = np.nan
    collinear = np.column_stack([np.linspace(300, 360, 4), np.linspace(200, 230, 4)])
    batch = np.concatenate([images, mc, fronto, nan_corner[None], collinear[None]])
    result = solve_pnp_planar_result(TAG_POINTS, batch, K, sigma_px=0.2)
    return dict(views=views, images=images, batch=batch, result=jax.device_get(result))


def _lanes(result, start, stop):
    return jax.tree.map(lambda leaf: leaf[start:stop], result)


@needs_cv2
def test_planar_candidates_match_opencv_ippe_square_refined(planar):
    """Both refined candidates equal OpenCV's IPPE_SQUARE candidates after solvePnPRefineLM."""
    c = planar["result"].candidates
    poses = np.asarray(c.pose.as_matrix())
    assert np.all(np.asarray(c.status._value[:N_VIEWS]) == PnPStatus.success._value)
    for b in range(N_VIEWS):
        ref = _cv_candidates(TAG_POINTS, planar["images"][b], cv2.SOLVEPNP_IPPE_SQUARE, True)
        dt, dr = _pose_gap(poses[b, 0], ref[0][1], ref[0][2])
        assert dt < 0.05 and dr < 0.02, (b, dt, dr)
        dt, dr = _pose_gap(poses[b, 1], ref[1][1], ref[1][2])
        assert dt < 0.05 and dr < 0.02, (b, dt, dr)
        # float32 pixel residuals round at ~3e-5 px (coordinates ~400 px)
        np.testing.assert_allclose(c.reprojection_rmse_px[b], [ref[0][0], ref[1][0]], atol=1e-4)


def test_planar_tuple_api_is_the_result_sorted(planar):
    poses, rmse = solve_pnp_planar(TAG_POINTS, planar["batch"], K)
    c = planar["result"].candidates
    np.testing.assert_array_equal(np.asarray(poses.wxyz_xyz), c.pose.wxyz_xyz)
    np.testing.assert_array_equal(np.asarray(rmse), c.reprojection_rmse_px)
    finite = np.isfinite(c.reprojection_rmse_px).all(-1)
    assert np.all(np.diff(c.reprojection_rmse_px[finite], axis=-1) >= 0)
    best = planar["result"].best
    assert best.pose.wxyz_xyz.shape == (len(planar["batch"]), 7)
    np.testing.assert_array_equal(best.covariance, c.covariance[:, 0])


def test_covariance_predicts_monte_carlo_spread(planar):
    """0.2 px corner noise on a 45 mm tag at 0.55 m, tilted 30 degrees: the depth axis is many
    times noisier than the in-plane axes, and the first-order covariance predicts the spread."""
    c = _lanes(planar["result"], N_VIEWS, N_VIEWS + N_DRAWS).candidates
    truth = SE3.from_rotation_and_translation(SO3.from_matrix(MC_R), jnp.asarray(MC_T))
    # The covariance describes the minimum near the truth; the flip is the ratio's business.
    errors = [np.asarray((SE3(c.pose.wxyz_xyz[:, i]).inverse() @ truth).log()) for i in (0, 1)]
    near = np.where(
        np.linalg.norm(errors[0][:, 3:], axis=1) <= np.linalg.norm(errors[1][:, 3:], axis=1), 0, 1
    )
    assert near.mean() < 0.01  # at 30 degrees the best candidate is the right one
    rows = np.arange(N_DRAWS)
    delta = np.where(near[:, None] == 0, errors[0], errors[1])
    t_cam = c.pose.wxyz_xyz[rows, near, 4:] - MC_T
    empirical_t = t_cam.std(axis=0)
    predicted_t = c.translation_sigma[rows, near].mean(axis=0)
    assert empirical_t[2] > 5 * max(empirical_t[:2])
    assert predicted_t[2] > 5 * max(predicted_t[:2])
    np.testing.assert_allclose(predicted_t, empirical_t, rtol=0.2)
    empirical_r = np.rad2deg(delta[:, 3:].std(axis=0))
    np.testing.assert_allclose(c.rotation_sigma_deg[rows, near].mean(axis=0), empirical_r, rtol=0.2)
    # The whole 6x6 matrix: squared Mahalanobis distances average 6 (chi-square, 6 dof).
    cov = c.covariance[rows, near]
    mahalanobis = np.einsum("ni,nij,nj->n", delta, np.linalg.inv(cov), delta)
    assert 5.4 < mahalanobis.mean() < 6.6


def test_ambiguity_ratio_flags_fronto_parallel_views(planar):
    tilted = planar["result"].ambiguity_ratio[N_VIEWS : N_VIEWS + N_DRAWS]
    fronto = planar["result"].ambiguity_ratio[N_VIEWS + N_DRAWS : -2]
    assert np.median(fronto) < 1.5 < 3.0 < np.median(tilted)
    assert np.mean(tilted > 1.5) > 0.99


def test_planar_degenerate_lanes_are_flagged_without_failing_the_batch(planar):
    status = planar["result"].candidates.status._value
    assert np.all(status[-2] == PnPStatus.too_few_points._value)  # a NaN corner
    assert np.all(status[-1] == PnPStatus.degenerate._value)  # collinear corners
    assert np.all(status[:-2] == PnPStatus.success._value)
    assert np.all(planar["result"].candidates.num_steps[-2:] <= 1)  # no LM spent on them


@needs_cv2
def test_ippe_candidates_equal_opencv_ippe_square(x64):
    """Unrefined, our two IPPE candidates are OpenCV's IPPE_SQUARE candidates."""
    rng = np.random.default_rng(11)
    views = [_tag_view(rng, rng.uniform(0.0, 40.0)) for _ in range(32)]
    images = np.stack([_project_np(R, t, TAG_POINTS) for R, t in views])
    images += rng.normal(scale=0.2, size=images.shape)
    result = solve_pnp_planar_result(TAG_POINTS, images, K, refine=False)
    poses = np.asarray(result.candidates.pose.as_matrix())
    for b in range(len(views)):
        ref = _cv_candidates(TAG_POINTS, images[b], cv2.SOLVEPNP_IPPE_SQUARE, False)
        for i in (0, 1):
            dt, dr = _pose_gap(poses[b, i], ref[i][1], ref[i][2])
            assert dt < 1e-6 and dr < 1e-6, (b, i, dt, dr)
        _, _, _, cv_err = cv2.solvePnPGeneric(
            TAG_POINTS, images[b], K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        # solvePnPGeneric reports the per-coordinate RMS: ours / sqrt(2).
        np.testing.assert_allclose(
            np.sort(cv_err.ravel()),
            result.candidates.reprojection_rmse_px[b] / np.sqrt(2),
            rtol=1e-9,
        )


# --------------------------------------------------------------------------------------------
# General PnP: one float64 solve of every 3D case
# --------------------------------------------------------------------------------------------

N_POINTS, N_GENERAL = 8, 24
FD_STEP = 1e-4  # pixels


def _general_view(rng, coplanar=False):
    X = rng.uniform(-0.05, 0.05, (N_POINTS, 3))
    if coplanar:
        X[:, 2] = 0.0
    rotvec = rng.normal(size=3)
    rotvec *= rng.uniform(0.0, 0.8 * np.pi) / np.linalg.norm(rotvec)
    R = _rotation(rotvec)
    t = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), rng.uniform(0.4, 0.7)])
    return X, R, t, _project_np(R, t, X) + rng.normal(scale=0.3, size=(N_POINTS, 2))


@pytest.fixture(scope="module")
def general():
    rng = np.random.default_rng(20)
    objs, images, weights = [], [], []
    for _ in range(N_GENERAL):
        X, _, _, img = _general_view(rng)
        objs.append(X)
        images.append(img)
    # Central differences for the gradient test: +-FD_STEP on each pixel coordinate of view 0.
    steps = np.eye(2 * N_POINTS).reshape(2 * N_POINTS, N_POINTS, 2) * FD_STEP
    fd_images = np.concatenate([images[0] + steps, images[0] - steps])
    objs += [objs[0]] * len(fd_images)
    images += list(fd_images)
    special = {}
    X, _, _, img = _general_view(rng, coplanar=True)
    special["coplanar"] = (X, img)
    X, _, _, img = _general_view(rng)
    X_pad, img_pad = X.copy(), img.copy()
    X_pad[6:] = rng.normal(size=(2, 3))  # padding rows: garbage, one NaN pixel
    img_pad[6] = np.nan
    special["padded"] = (X_pad, img_pad)
    X, _, _, img = _general_view(rng)
    X[:, :2] = np.outer(np.linspace(-1, 1, N_POINTS), [0.04, 0.02])  # on a line
    X[:, 2] = np.linspace(-1, 1, N_POINTS) * 0.03
    special["collinear"] = (X, img)
    X, _, _, img = _general_view(rng)
    special["too_few"] = (X, img)  # weights keep 3 of its points
    # A point set straddling the camera plane: one point's true position is behind the camera.
    X, R, t, _ = _general_view(rng)
    X[0] = R.T @ (np.array([0.02, 0.01, -0.1]) - t)
    Xc = X @ R.T + t
    special["behind"] = (X, (Xc[:, :2] / Xc[:, 2:3]) @ K[:2, :2].T + K[:2, 2])
    names = list(special)
    for name in names:
        objs.append(special[name][0])
        images.append(special[name][1])
    weights = np.ones((len(objs), N_POINTS))
    weights[N_GENERAL + len(fd_images) + names.index("padded"), 6:] = 0.0
    weights[N_GENERAL + len(fd_images) + names.index("too_few"), 3:] = 0.0
    with jax.enable_x64(True):
        result = solve_pnp_result(np.stack(objs), np.stack(images), K, weights=weights)
        result = jax.device_get(result)
    lane = {name: N_GENERAL + len(fd_images) + i for i, name in enumerate(names)}
    return dict(objs=objs, images=images, result=result, lane=lane, fd=fd_images)


@needs_cv2
def test_general_pnp_matches_opencv_refined(general):
    result, lane = general["result"], general["lane"]
    poses = np.asarray(result.pose.as_matrix())
    checks = list(range(N_GENERAL)) + [lane["coplanar"]]
    for b in checks:
        ref = _cv_candidates(general["objs"][b], general["images"][b], "sqpnp", True)
        dt, dr = _pose_gap(poses[b], ref[0][1], ref[0][2])
        assert dt < 0.05 and dr < 0.02, (b, dt, dr)
        assert result.status._value[b] == PnPStatus.success._value
    # Padding (zero weights, a NaN pixel) is ignored: same pose as OpenCV on the 6 real points.
    b = lane["padded"]
    ref = _cv_candidates(general["objs"][b][:6], general["images"][b][:6], "sqpnp", True)
    dt, dr = _pose_gap(poses[b], ref[0][1], ref[0][2])
    assert dt < 0.05 and dr < 0.02, (dt, dr)


def test_general_failures_are_per_lane_status(general):
    status, lane = general["result"].status._value, general["lane"]
    assert status[lane["collinear"]] == PnPStatus.degenerate._value
    assert status[lane["too_few"]] == PnPStatus.too_few_points._value
    assert status[lane["behind"]] == PnPStatus.behind_camera._value
    flagged = {lane["collinear"], lane["too_few"], lane["behind"]}
    ok = [i for i in range(len(status)) if i not in flagged]
    assert np.all(status[ok] == PnPStatus.success._value)
    assert np.all(general["result"].converged[ok])


def test_pose_gradient_matches_central_differences(general, x64):
    """jacrev through the implicit adjoint of Levenberg-Marquardt equals central differences
    of the refined pose tangent with respect to the image points (float64, rel. error < 1e-3)."""
    X, img = general["objs"][0], general["images"][0]
    J = np.asarray(jax.jacrev(lambda uv: solve_pnp(X, uv, K).log())(jnp.asarray(img)))
    assert J.shape == (6, N_POINTS, 2) and np.all(np.isfinite(J))
    n = 2 * N_POINTS
    tangents = np.asarray(SE3(jnp.asarray(general["result"].pose.wxyz_xyz)).log())
    fd = tangents[N_GENERAL : N_GENERAL + n] - tangents[N_GENERAL + n : N_GENERAL + 2 * n]
    fd = (fd / (2 * FD_STEP)).T.reshape(6, N_POINTS, 2)
    assert np.abs(J - fd).max() < 1e-3 * np.abs(fd).max()


# --------------------------------------------------------------------------------------------
# Host-side errors and tag detection
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("solver", [solve_pnp, solve_pnp_planar])
def test_static_problems_raise_on_the_host(solver):
    with pytest.raises(ValueError, match="at least 4"):
        solver(TAG_POINTS[:3], np.zeros((3, 2)), K)
    with pytest.raises(ValueError, match="object points but"):
        solver(TAG_POINTS, np.zeros((5, 2)), K)
    with pytest.raises(ValueError, match="K must be"):
        solver(TAG_POINTS, np.zeros((4, 2)), K[:2])
    with pytest.raises(ValueError, match="dist_coeffs"):
        solver(TAG_POINTS, np.zeros((4, 2)), K, dist_coeffs=np.zeros(3))
    with pytest.raises(ValueError, match="broadcast"):
        solver(np.zeros((2, 4, 3)), np.zeros((3, 4, 2)), K)


@needs_cv2
def test_detect_tags_returns_corners_in_object_order():
    """A rendered ArUco tag is found, with corners at their projections (IPPE_SQUARE order)."""
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    side = 120
    marker = cv2.aruco.generateImageMarker(dictionary, 7, side)
    R = _rotation([0.4, 0.2, 0.3]) @ FACING
    t = np.array([0.01, -0.02, 0.5])
    # marker pixel (a, b) -> tag plane (x, y): pixel edges at -0.5 and side - 0.5
    S = np.array(
        [
            [TAG / side, 0, -TAG / 2 + TAG / (2 * side)],
            [0, -TAG / side, TAG / 2 - TAG / (2 * side)],
            [0, 0, 1],
        ]
    )
    H = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ S
    # Render at 4x and average 4x4 blocks (low-res pixel i is high-res 4 i + 1.5): no aliasing.
    up = np.array([[4.0, 0.0, 1.5], [0.0, 4.0, 1.5], [0.0, 0.0, 1.0]])
    fine = cv2.warpPerspective(marker, up @ H, (2560, 1920), borderValue=255)
    image = cv2.resize(fine, (640, 480), interpolation=cv2.INTER_AREA)
    corners, ids = detect_tags(image, "DICT_4X4_50")
    assert ids.tolist() == [7]
    # OpenCV's sub-pixel refinement pulls the outer corners of a ~55 px tag ~0.25 px inward.
    np.testing.assert_allclose(corners[0], _project_np(R, t, TAG_POINTS), atol=0.35)
