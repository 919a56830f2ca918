"""General PnP and planar PnP (IPPE), checked against OpenCV when it imports.

Compile time dominates on a small CPU, so each solver is compiled once per configuration on one
batch that holds every case the tests need (random views, Monte Carlo draws, finite-difference
perturbations, padded and degenerate lanes); the tests read their slices of it.
"""

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3

from jaxreg.camera import pose_jacobian
from jaxreg.camera.pnp import (
    PlanarPnPResult,
    PnPResult,
    PnPStatus,
    _ranking,
    _Reprojection,
    _reprojection,
    _result,
    _solve_planar,
    _swap_pair,
    solve_pnp,
    solve_pnp_planar,
)
from jaxreg.camera.tags import tag_object_points

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
# Planar PnP: one float32 solve (the default dtype) of every planar case
# --------------------------------------------------------------------------------------------

N_VIEWS, N_DRAWS, N_FRONTO = 64, 1000, 64
MC_R = _rotation([np.deg2rad(30.0), 0.0, 0.0]) @ FACING @ _rotation([0.0, 0.0, 0.3])
MC_T = np.array([0.03, -0.02, 0.55])


def planar_batch():
    """Corner pixels `(1130, 4, 2)` of every planar case (the views, the Monte Carlo draws, the
    fronto-parallel draws, a NaN corner, collinear corners) and the views `(R, t)`."""
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
    return batch, views


@pytest.fixture(scope="module")
def planar():
    batch, views = planar_batch()
    result = solve_pnp_planar(TAG_POINTS, batch, K, sigma_px=0.2)
    images = batch[:N_VIEWS]
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


def test_planar_result_reads_as_its_best_candidate(planar):
    """`pose`, `status`, `converged`, `iterations` are candidate 0's; candidates are sorted
    (finite and in front of the camera first, then by error); a lane indexes every leaf."""
    result = planar["result"]
    c = result.candidates
    assert isinstance(result, PlanarPnPResult) and isinstance(c, PnPResult)
    np.testing.assert_array_equal(result.pose.wxyz_xyz, c.pose.wxyz_xyz[:, 0])
    np.testing.assert_array_equal(result.status._value, c.status._value[:, 0])
    np.testing.assert_array_equal(result.converged, c.converged[:, 0])
    np.testing.assert_array_equal(result.iterations, c.iterations[:, 0])
    success = result.status._value == PnPStatus.success._value
    np.testing.assert_array_equal(result.converged, success)
    finite = np.isfinite(c.reprojection_rmse_px).all(-1)
    rmse = c.reprojection_rmse_px[finite]
    slack = np.sqrt(np.finfo(np.float32).eps) * (1 + rmse[:, 0])  # equal up to rounding
    assert np.all(rmse[:, 1] >= rmse[:, 0] - slack)
    best, second = result.best, result.second
    assert best.pose.wxyz_xyz.shape == (len(planar["batch"]), 7)
    np.testing.assert_array_equal(best.covariance, c.covariance[:, 0])
    np.testing.assert_array_equal(second.reprojection_rmse_px, c.reprojection_rmse_px[:, 1])
    lane = result[3]
    assert lane.batch_shape == () and lane.candidates.pose.wxyz_xyz.shape == (2, 7)
    np.testing.assert_array_equal(lane.ambiguity_ratio, result.ambiguity_ratio[3])
    messages = result.status_message()
    assert messages.shape == (len(planar["batch"]),) and lane.status_message() == messages[3]
    assert messages[-2].startswith("fewer than 4 valid correspondences")


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
    assert np.all(status[-2] == PnPStatus.too_few_correspondences._value)  # a NaN corner
    assert np.all(status[-1] == PnPStatus.degenerate._value)  # collinear corners
    assert np.all(status[:-2] == PnPStatus.success._value)
    assert np.all(planar["result"].candidates.iterations[-2:] <= 1)  # no LM spent on them


REFERENCE = Path(__file__).parent / "fixtures" / "pnp" / "planar_reference.npz"


@pytest.mark.parametrize("refine", [False, True])
def test_planar_results_equal_the_frozen_reference(planar, refine):
    """The batched planar path reproduces, within float32 rounding, the results that
    `fixtures/pnp/make_planar_reference.py` froze (every 16th lane of the planar batch and
    its two failing lanes): statuses, candidate order, poses, errors, covariances, ratios.
    The NaN-corner lane is compared by status alone: with three valid corners the pose is
    whatever the solver reached (see `jaxreg.camera.pnp`)."""
    ref = np.load(REFERENCE)
    prefix = "refined" if refine else "unrefined"
    result = planar["result"]
    if not refine:
        result = jax.device_get(
            solve_pnp_planar(TAG_POINTS, planar["batch"], K, sigma_px=0.2, refine=False)
        )
    c = jax.tree.map(lambda leaf: np.asarray(leaf)[ref["lanes"]], result.candidates)
    expect = {key[len(prefix) + 1 :]: ref[key] for key in ref.files if key.startswith(prefix)}
    np.testing.assert_array_equal(c.status._value, expect["status"])
    np.testing.assert_allclose(c.iterations, expect["iterations"], atol=1)
    kept = expect["status"][:, 0] != PnPStatus.too_few_correspondences._value
    assert np.sum(~kept) == 1
    close = lambda actual, key, **tol: np.testing.assert_allclose(  # noqa: E731
        np.asarray(actual)[kept], expect[key][kept], **tol
    )
    close(c.pose.wxyz_xyz, "wxyz_xyz", atol=1e-5)  # quaternion and metres
    close(c.reprojection_rmse_px, "rmse", atol=1e-4)
    close(c.translation_sigma, "translation_sigma", rtol=1e-3)
    close(c.rotation_sigma_deg, "rotation_sigma_deg", rtol=1e-3)
    close(np.asarray(result.ambiguity_ratio)[ref["lanes"]], "ambiguity_ratio", rtol=1e-3)
    close(np.asarray(result.separation_deg)[ref["lanes"]], "separation_deg", atol=1e-3)
    # float32 inverses: the covariances' differences relative to their standard deviations
    sd = np.sqrt(np.abs(np.einsum("...ii->...i", expect["covariance"])))
    gap = (c.covariance - expect["covariance"]) / (sd[..., :, None] * sd[..., None, :])
    assert np.array_equal(np.isfinite(c.covariance), np.isfinite(expect["covariance"]))
    assert np.nanmax(np.abs(gap[kept])) < 1e-3


@needs_cv2
def test_ippe_candidates_equal_opencv_ippe_square(x64):
    """Unrefined, our two IPPE candidates are OpenCV's IPPE_SQUARE candidates."""
    rng = np.random.default_rng(11)
    views = [_tag_view(rng, rng.uniform(0.0, 40.0)) for _ in range(32)]
    images = np.stack([_project_np(R, t, TAG_POINTS) for R, t in views])
    images += rng.normal(scale=0.2, size=images.shape)
    result = solve_pnp_planar(TAG_POINTS, images, K, refine=False)
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

N_POINTS, N_GENERAL, N_FOUR = 8, 24, 64
# Lanes whose status is not `success`, or whose outcome a test checks on its own.
SPECIAL_LANES = ("collinear", "too_few", "behind", "all_behind")
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


def _four_point_views(count):
    """`count` problems of 4 non-coplanar points in front of the camera (P4P: several poses
    can fit, some of them behind the camera), each also padded to N_POINTS rows of garbage
    (object points, pixels, one NaN) with zero weight. Returns the padded (objects, images,
    weights) and the unpadded (objects, images)."""
    rng = np.random.default_rng(1)
    objs, images = [], []
    for _ in range(count):
        X = rng.uniform(-0.05, 0.05, (4, 3))
        rotvec = rng.normal(size=3)
        R = _rotation(rotvec * rng.uniform(0.0, 0.8 * np.pi) / np.linalg.norm(rotvec))
        t = np.array([*rng.uniform(-0.05, 0.05, 2), rng.uniform(0.4, 0.7)])
        objs.append(X)
        images.append(_project_np(R, t, X) + rng.normal(scale=0.3, size=(4, 2)))
    objs, images = np.stack(objs), np.stack(images)
    pad_objs = np.concatenate([objs, rng.normal(size=(count, N_POINTS - 4, 3))], axis=1)
    pad_images = np.concatenate([images, rng.uniform(0, 600, (count, N_POINTS - 4, 2))], axis=1)
    pad_images[:, -1] = np.nan
    weights = np.concatenate([np.ones((count, 4)), np.zeros((count, N_POINTS - 4))], axis=1)
    return (pad_objs, pad_images, weights), (objs, images)


@pytest.fixture(scope="module")
def general():
    rng = np.random.default_rng(20)
    objs, images = [], []
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
    # Every point behind the camera: no rigid pose in front reproduces these pixels.
    X, R, t, _ = _general_view(rng)
    Xc = X @ R.T + t * [1.0, 1.0, -1.0]
    special["all_behind"] = (X, (Xc[:, :2] / Xc[:, 2:3]) @ K[:2, :2].T + K[:2, 2])
    names = list(special)
    weights = np.ones((len(objs) + len(names), N_POINTS))
    for name in names:
        objs.append(special[name][0])
        images.append(special[name][1])
    lane = {name: N_GENERAL + len(fd_images) + i for i, name in enumerate(names)}
    weights[lane["padded"], 6:] = 0.0
    weights[lane["too_few"], 3:] = 0.0
    padded, four = _four_point_views(N_FOUR)
    lane["four"] = np.arange(len(objs), len(objs) + N_FOUR)
    objs += list(padded[0])
    images += list(padded[1])
    weights = np.concatenate([weights, padded[2]])
    with jax.enable_x64(True):
        result = solve_pnp(np.stack(objs), np.stack(images), K, weights=weights)
        result = jax.device_get(result)
    return dict(objs=objs, images=images, result=result, lane=lane, four=four)


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


def _depths(result, lanes, objs):
    """Camera-frame depths `(len(lanes), N)` of the object points under the returned poses."""
    R = np.asarray(result.pose.rotation().as_matrix())[lanes]
    t = np.asarray(result.pose.translation())[lanes]
    return np.einsum("bij,bnj->bni", R, np.asarray(objs))[..., 2] + t[:, None, 2]


def test_general_failures_are_per_lane_status(general):
    result, lane = general["result"], general["lane"]
    status = result.status._value
    assert status[lane["collinear"]] == PnPStatus.degenerate._value
    assert status[lane["too_few"]] == PnPStatus.too_few_correspondences._value
    assert not result.converged[lane["collinear"]] and not result.converged[lane["too_few"]]
    assert np.all(result.iterations[[lane["collinear"], lane["too_few"]]] == 0)
    ok = [i for i in range(len(status)) if i not in {lane[k] for k in SPECIAL_LANES}]
    assert np.all(status[ok] == PnPStatus.success._value)
    assert np.all(result.converged[ok])


def test_behind_camera_status_when_every_start_is_behind(general):
    """One point of this lane truly lies behind the camera and every start converges to that
    pose: the status names it and converged is False."""
    result, b = general["result"], general["lane"]["behind"]
    assert result.status._value[b] == PnPStatus.behind_camera._value
    assert not result.converged[b]
    assert _depths(result, [b], [general["objs"][b]]).min() <= 0
    assert result[b].status_message().startswith("the pose puts object points behind")


def test_a_start_behind_the_camera_never_wins(general):
    """Four points admit several poses; in some of these problems a pose behind the camera
    reprojects best (by error alone it would be returned). The pose returned keeps every valid
    point in front whenever a start does: on the 64 four-point problems (true pose in front)
    and on pixels made by points all behind the camera (a mirrored setup: the best rigid pose
    in front is returned, its error says how well it fits)."""
    result, lane = general["result"], general["lane"]
    four = lane["four"]
    depths = _depths(result, four, general["four"][0])
    assert depths.min() > 0
    assert np.all(result.status._value[four] == PnPStatus.success._value)
    b = lane["all_behind"]
    assert _depths(result, [b], [general["objs"][b]]).min() > 0
    assert result.status._value[b] != PnPStatus.behind_camera._value


def test_padding_never_changes_the_answer(general, x64):
    """Zero-weight rows (garbage points, a NaN pixel) change neither the number of starts nor
    the starts: each padded four-point problem equals the same problem solved unpadded."""
    result, four = general["result"], general["lane"]["four"]
    unpadded = jax.device_get(solve_pnp(*general["four"], K))
    assert unpadded.iterations.shape == (N_FOUR,)
    np.testing.assert_array_equal(unpadded.status._value, result.status._value[four])
    np.testing.assert_allclose(
        unpadded.pose.as_matrix(), np.asarray(result.pose.as_matrix())[four], atol=1e-8
    )
    np.testing.assert_allclose(
        unpadded.reprojection_rmse_px, result.reprojection_rmse_px[four], rtol=1e-8
    )


def test_singular_information_gives_inf_covariance_and_degenerate_status(general, x64):
    """Two weighted points cannot fix six pose parameters: J^T W J has rank 4. Its guarded
    inverse is `inf` on every coordinate touching the undetermined directions (never a finite
    inverse of a singular matrix, never NaN) and the status is `degenerate`; with all points
    weighted the covariance is the plain inverse."""
    b = 0
    pose = SE3(jnp.asarray(general["result"].pose.wxyz_xyz[b]))
    X, uv = jnp.asarray(general["objs"][b]), jnp.asarray(general["images"][b])
    K_ = jnp.asarray(K)

    @jax.jit  # one program for both weightings (eagerly, every primitive compiles alone)
    def finish(w):
        fit = _reprojection(pose, X, uv, K_, None, w)
        ok = PnPStatus.success
        return _result(pose, fit, 3, jnp.array(True), ok, X, K_, None, w, 0.5)

    w = jnp.zeros(N_POINTS).at[:2].set(1.0)
    singular = jax.device_get(finish(w))
    assert singular.status._value == PnPStatus.degenerate._value and not singular.converged
    assert np.isinf(singular.covariance).any() and not np.isnan(singular.covariance).any()
    assert np.isinf(singular.rotation_sigma_deg).any()
    assert not np.isnan(singular.translation_sigma).any()
    full = jax.device_get(finish(jnp.ones(N_POINTS)))
    assert full.status._value == PnPStatus.success._value
    J = np.asarray(pose_jacobian(pose, X, K_)).reshape(-1, 6)
    np.testing.assert_allclose(full.covariance, 0.25 * np.linalg.inv(J.T @ J), rtol=1e-6)


@pytest.mark.slow
def test_pose_gradient_matches_central_differences(general, x64):
    """jacrev through the implicit adjoint of Levenberg-Marquardt equals central differences
    of the refined pose tangent with respect to the image points (float64, rel. error < 1e-3)."""
    X, img = general["objs"][0], general["images"][0]
    J = np.asarray(jax.jacrev(lambda uv: solve_pnp(X, uv, K).pose.log())(jnp.asarray(img)))
    assert J.shape == (6, N_POINTS, 2) and np.all(np.isfinite(J))
    n = 2 * N_POINTS
    tangents = np.asarray(SE3(jnp.asarray(general["result"].pose.wxyz_xyz)).log())
    fd = tangents[N_GENERAL : N_GENERAL + n] - tangents[N_GENERAL + n : N_GENERAL + 2 * n]
    fd = (fd / (2 * FD_STEP)).T.reshape(6, N_POINTS, 2)
    assert np.abs(J - fd).max() < 1e-3 * np.abs(fd).max()


# --------------------------------------------------------------------------------------------
# Host-side errors
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


# --------------------------------------------------------------------------------------------
# The closed-form pieces of the batched path, against their references
# --------------------------------------------------------------------------------------------


def test_pair_order_is_the_rankings():
    """The planar path orders its two candidates by comparisons; they put the second first
    exactly when `_ranking` (the general path's sort) does, over every combination of tier
    (finite, behind the camera), error (equal, within the rounding slack, apart, inf) and
    convergence."""
    import itertools

    errors = [0.5, 0.5 + 1e-9, 0.5 + 1e-3, 0.7, np.inf]
    cases = list(
        itertools.product(
            [True, False],
            [True, False],
            [True, False],
            [True, False],
            errors,
            errors,
            [True, False],
            [True, False],
        )
    )
    columns = [np.array(c) for c in zip(*cases, strict=True)]
    f0, f1, b0, b1, e0, e1, c0, c1 = columns
    fits = _Reprojection(
        rmse=jnp.asarray(np.stack([e0, e1], -1), jnp.float32),
        behind=jnp.asarray(np.stack([b0, b1], -1)),
        finite=jnp.asarray(np.stack([f0, f1], -1) & np.isfinite(np.stack([e0, e1], -1))),
    )
    converged = jnp.asarray(np.stack([c0, c1], -1))
    swap = jax.vmap(_swap_pair)(fits, converged)
    first = jax.vmap(lambda fit, conv: _ranking(fit, conv)[0])(fits, converged)
    np.testing.assert_array_equal(np.asarray(swap), np.asarray(first) == 1)
    assert 0 < int(np.sum(swap)) < len(cases)


def test_unrolled_cholesky_solve_and_inverse_match_numpy(x64):
    from jaxreg.camera._pnp_linalg import spd_inverse, spd_solve

    rng = np.random.default_rng(3)
    M = rng.normal(size=(5, 8, 6))
    A = np.einsum("bki,bkj->bij", M, M) + 1e-3 * np.eye(6)
    b = rng.normal(size=(5, 6))
    x, ok = spd_solve(jnp.asarray(A), jnp.asarray(b))
    inv, ok_inv = spd_inverse(jnp.asarray(A))
    assert np.all(ok) and np.all(ok_inv)
    np.testing.assert_allclose(x, np.linalg.solve(A, b[..., None])[..., 0], rtol=1e-9)
    np.testing.assert_allclose(inv, np.linalg.inv(A), rtol=1e-8, atol=1e-10)
    indefinite = A[0] - 2 * np.linalg.eigvalsh(A[0])[-1] * np.eye(6)
    assert not spd_solve(jnp.asarray(indefinite), jnp.asarray(b[0]))[1]


def test_refinement_normal_equations_match_autodiff(x64):
    """The closed-form chart Jacobian of the refinement, away from the chart's centre and with
    distortion, gives the J^T J and J^T r of forward-mode autodiff of its residuals."""
    from jaxreg.camera._pnp_refine import _evaluate, _Problem, normal_equations

    rng = np.random.default_rng(4)
    R, t = _tag_view(rng, 25.0)
    X = jnp.asarray(TAG_POINTS)
    uv = jnp.asarray(_project_np(R, t, TAG_POINTS) + rng.normal(scale=0.3, size=(4, 2)))
    sw = jnp.asarray(rng.uniform(0.5, 1.5, 4))
    scale = jnp.asarray(rng.uniform(50.0, 500.0, 6))
    problem = _Problem.build(jnp.asarray(R), jnp.asarray(t), X, uv, K, DIST, sw, scale)
    y = jnp.asarray(rng.normal(scale=2.0, size=6))

    def residuals(y):
        return jnp.concatenate(_evaluate(problem, y, jacobian=False))

    J = jax.jacfwd(residuals)(y)
    A, g, cost = normal_equations(*_evaluate(problem, y))
    np.testing.assert_allclose(A, J.T @ J, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(g, J.T @ residuals(y), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(cost, 0.5 * np.sum(np.asarray(residuals(y)) ** 2), rtol=1e-12)


def test_closed_form_covariance_equals_the_eigendecomposition(planar):
    """Where the closed form decides (every direction determined, or none), it gives what the
    eigendecomposition gives; it leaves the near-singular lanes to it."""
    from jaxreg.camera._pnp_covariance import _covariance_closed_form, covariance

    c = planar["result"].candidates
    X, K_ = jnp.asarray(TAG_POINTS, jnp.float32), jnp.asarray(K, jnp.float32)
    # One program each, for every pose and weighting (eagerly, every primitive compiles alone).
    closed_form = jax.jit(_covariance_closed_form, static_argnums=3)
    eigen = jax.jit(covariance, static_argnums=3)
    lanes = list(range(0, N_VIEWS, 8)) + [N_VIEWS + N_DRAWS + 1]  # tilted views, a fronto one
    for b in lanes:
        for i in (0, 1):
            pose = SE3(jnp.asarray(c.pose.wxyz_xyz[b, i]))
            fast, decided = closed_form(pose, X, K_, None, jnp.ones(4), 0.2)
            exact = eigen(pose, X, K_, None, jnp.ones(4), 0.2)
            assert decided
            # float32 inverses: compare correlations and relative sigmas
            sd = np.sqrt(np.diagonal(exact[0]))
            np.testing.assert_allclose(
                fast[0] / np.outer(sd, sd), exact[0] / np.outer(sd, sd), atol=1e-3
            )
            np.testing.assert_allclose(fast[1], exact[1], rtol=1e-3)
            np.testing.assert_allclose(fast[2], exact[2], rtol=1e-3)
            assert not fast[3] and not exact[3]
    pose = SE3(jnp.asarray(c.pose.wxyz_xyz[0, 0]))
    w = jnp.zeros(4).at[:2].set(1.0)  # two points: rank 4, near singular, undecided
    assert not closed_form(pose, X, K_, None, w, 0.2)[1]
    none = closed_form(pose, X, K_, None, jnp.zeros(4), 0.2)
    exact = eigen(pose, X, K_, None, jnp.zeros(4), 0.2)
    assert none[1] and none[0][3] and np.all(np.isinf(none[0][0]))
    for a, e in zip(none[0], exact, strict=True):
        np.testing.assert_array_equal(a, e)


@pytest.mark.slow
def test_a_lane_refines_alike_alone_and_in_a_large_batch(planar):
    """The refinement steps the planar fixture's 2,260 starts 282 at a time, the first ones
    still running gathered afresh at every step; which lanes share a step changes neither a
    lane's pose nor, beyond one step, its step count (float32 rounding differs by batch size,
    and a lane at the tolerance's edge may stop one step sooner or later): the slowest lanes
    solved as a batch of 8 (too few to gather) agree."""
    c = planar["result"].candidates
    slow = np.argsort(-c.iterations[:N_VIEWS].max(axis=1))[:8]
    assert c.iterations[slow].max() > 10  # stepped in many different companies
    small = jax.device_get(
        solve_pnp_planar(TAG_POINTS, planar["batch"][slow], K, sigma_px=0.2)
    ).candidates
    # Candidates that reach one minimum tie, and rounding may order them either way.
    steps = np.sort(small.iterations, axis=1) - np.sort(c.iterations[slow], axis=1)
    assert np.abs(steps).max() <= 1 and np.mean(steps == 0) >= 0.9, steps
    for b, lane in enumerate(slow):
        gaps = [
            np.abs(small.pose.wxyz_xyz[b] - c.pose.wxyz_xyz[lane][order]).max()
            for order in ([0, 1], [1, 0])
        ]
        assert min(gaps) < 2e-5, (lane, gaps)  # float32 rounding differs by batch size


@pytest.mark.slow
def test_tag_counts_that_change_call_by_call_share_one_compiled_solver(planar):
    """A tracker's tag count changes frame by frame: 5, 6 and 7 tags all run as a batch of 8
    (padded with copies of the last tag, trimmed away), so the solver compiles at most once
    for them, and the lanes they share answer alike, bit for bit (one program, independent
    lanes). The padding is invisible: each result has the caller's batch shape."""
    images = planar["images"]
    before = _solve_planar._cache_size()
    results = [
        jax.device_get(solve_pnp_planar(TAG_POINTS, images[:n], K, max_iterations=37))
        for n in (5, 6, 7)
    ]
    assert _solve_planar._cache_size() - before <= 1
    for n, result in zip((5, 6, 7), results, strict=True):
        assert result.pose.wxyz_xyz.shape == (n, 7)
        assert result.candidates.covariance.shape == (n, 2, 6, 6)
        jax.tree.map(np.testing.assert_array_equal, _lanes(result, 0, 5), results[0])
    grid = jax.device_get(solve_pnp_planar(TAG_POINTS, images[:6].reshape(2, 3, 4, 2), K))
    assert grid.pose.wxyz_xyz.shape == (2, 3, 7)
    # a frame without tags, and one tag without a batch axis
    assert solve_pnp_planar(TAG_POINTS, images[:0], K).pose.wxyz_xyz.shape == (0, 7)
    one = jax.device_get(solve_pnp_planar(TAG_POINTS, images[0], K, max_iterations=37))
    np.testing.assert_allclose(one.pose.wxyz_xyz, results[0].pose.wxyz_xyz[0], atol=2e-5)
