import math
from statistics import NormalDist

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3

from jaxreg.geometry.kernels import Cauchy
from jaxreg.geometry.metrics import Symmetry
from jaxreg.io import load_points
from jaxreg.registration.icp import ICPStatus, icp, icp_covariance, init_spread
from jaxreg.search.neighbors import build_grid, voxel_downsample
from jaxreg.search.normals import estimate_normals
from jaxreg.uncertainty import (
    DepthNoise,
    GraspPrediction,
    IsotropicNoise,
    PointCovariance,
    error_budget,
    grasp_margin,
    grasp_prediction,
    grasp_success_probability,
    pose_statistics,
)
from jaxreg.uncertainty.budget import SOURCES, combine

DEG = 180 / np.pi


def box_surface(n, size=(0.06, 0.04, 0.03), seed=0):
    """``n`` points on the surface of an axis-aligned box centred at the origin."""
    rng = np.random.default_rng(seed)
    half = np.asarray(size) / 2
    pts = rng.uniform(-half, half, (n, 3))
    axis = rng.integers(0, 3, n)
    pts[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * half[axis]
    return pts


def box_normals(points, size=(0.06, 0.04, 0.03)):
    half = np.asarray(size) / 2
    axis = np.argmax(np.abs(points) / half, axis=1)
    n = np.zeros_like(points)
    n[np.arange(len(points)), axis] = np.sign(points[np.arange(len(points)), axis])
    return n


# --------------------------------------------------------------------------------------------
# Noise models.


def test_depth_noise_of_host_values_compiles_no_program():
    """A command line process pays for every JAX program it compiles or loads: a DepthNoise
    of Python or numpy values is built on the host, with the leaves jnp.asarray would give."""
    compiled = []

    def listen(event, duration, **kwargs):
        if event.endswith("backend_compile_duration"):
            compiled.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        plain = DepthNoise((0.001, 0.0, 0.0025))
        lateral = DepthNoise(np.array([0.0, 0.0, 0.003]), pixel_sigma=0.2, focal_length=(600, 610))
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert compiled == []
    np.testing.assert_array_equal(np.asarray(plain.base_T_camera.wxyz_xyz), [1, 0, 0, 0, 0, 0, 0])
    assert plain.pixel_sigma.weak_type and float(plain.pixel_sigma) == 0.0
    np.testing.assert_array_equal(np.asarray(lateral.focal_length), [600.0, 610.0])
    for leaf in (*jax.tree.leaves(plain), *jax.tree.leaves(lateral)):
        assert leaf.dtype == jnp.float32
    with pytest.raises(ValueError, match="needs focal_length"):
        DepthNoise((0.001,), pixel_sigma=0.5)


def test_axial_sigma_is_one_polynomial_on_the_host_and_under_jit():
    """``sigma_z = 1.2 mm + 2.5e-3 z^2``: numpy depths give float64 on the host without a
    program; JAX depths, jit and grad give the same values of the depth's dtype."""
    noise = DepthNoise((0.0012, 0.0, 0.0025))
    depth = np.array([[0.5, 1.0], [2.0, 0.0]])
    expected = 0.0012 + 0.0025 * depth**2
    compiled = []

    def listen(event, duration, **kwargs):
        if event.endswith("backend_compile_duration"):
            compiled.append(kwargs.get("fun_name"))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        host = noise.axial_sigma(depth)
        scalar = noise.axial_sigma(1.0)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert compiled == []
    assert isinstance(host, np.ndarray) and host.dtype == np.float64 and host.shape == (2, 2)
    np.testing.assert_allclose(host, expected, rtol=1e-6)
    assert float(scalar) == pytest.approx(0.0037, rel=1e-6)
    traced = jax.jit(lambda n, z: n.axial_sigma(z))(noise, jnp.asarray(depth, jnp.float32))
    assert isinstance(traced, jax.Array) and traced.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(traced), expected, rtol=1e-6)
    slope = jax.grad(lambda z: noise.axial_sigma(z))(jnp.float32(2.0))
    assert float(slope) == pytest.approx(2 * 0.0025 * 2.0, rel=1e-5)


@jax.jit
def _draws(noise, keys, points):
    """One draw of ``noise`` on ``points`` per key, as one compiled program (vmapped eagerly,
    every operation would compile on its own)."""
    return jax.vmap(noise.sample, in_axes=(0, None))(keys, points)


def test_noise_samples_have_the_modelled_covariance():
    """Draws of DepthNoise (axial along the camera ray through a hand-eye transform, plus
    pixel jitter) and IsotropicNoise have the covariance each model reports."""
    base_T_camera = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(2.6, 0.2, -0.5), jnp.array([0.4, 0.1, 0.9])
    )
    camera_points = jnp.array([[0.1, -0.05, 0.6], [-0.2, 0.1, 1.2], [0.0, 0.0, 0.9]])
    points = base_T_camera @ camera_points
    noise = DepthNoise(
        (0.001, 0.0, 0.002), base_T_camera, pixel_sigma=0.5, focal_length=(525.0, 520.0)
    )
    keys = jax.random.split(jax.random.key(0), 20000)
    draws = np.asarray(_draws(noise, keys, points), np.float64)
    predicted = np.asarray(noise.covariance(points))
    for i in range(3):
        empirical = np.cov(draws[:, i].T)
        np.testing.assert_allclose(empirical, predicted[i], atol=0.05 * predicted[i].max())
    # Axial part: along the ray from the camera centre, sigma = 1 mm + 2 mm * z^2.
    axial = DepthNoise((0.001, 0.0, 0.002), base_T_camera).covariance(points)
    lam, vec = np.linalg.eigh(np.asarray(axial))
    ray = np.array(points - base_T_camera.translation())
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(vec[:, :, 2] * ray, 1)), 1, atol=1e-5)
    z = np.asarray(camera_points[:, 2])
    stretch = np.linalg.norm(np.asarray(camera_points) / z[:, None], axis=1)  # |K^-1 (u,v,1)|
    np.testing.assert_allclose(np.sqrt(lam[:, 2]), (0.001 + 0.002 * z**2) * stretch, rtol=1e-4)

    iso = IsotropicNoise(0.002)
    d = np.asarray(_draws(iso, keys[:5000], points)) - np.asarray(points)
    assert np.std(d) == pytest.approx(0.002, rel=0.03)
    with pytest.raises(ValueError, match="focal_length"):
        DepthNoise((0.0, 0.0, 0.002), pixel_sigma=0.5)


# --------------------------------------------------------------------------------------------
# icp_covariance: exactness of the linearisation.


def _box_problem(method, n=300, seed=0, resample=True, noise=2e-4):
    """A box registered onto a noisy copy of itself: by default a different sampling of the
    surface (as a scan is of a model), else the same points."""
    src = box_surface(n, seed=seed)
    rng = np.random.default_rng(seed + 1)
    truth = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(0.05, -0.03, 0.08), jnp.array([0.004, -0.002, 0.003])
    )
    tgt_clean = box_surface(n, seed=seed + 7) if resample else src
    tgt = np.asarray(truth @ tgt_clean) + rng.normal(0, noise, (n, 3))
    normals = np.asarray(truth.rotation() @ box_normals(tgt_clean))
    opts = dict(
        method=method,
        target_normals=normals if method == "point_to_plane" else None,
        max_correspondence_distance=0.01,
        max_iterations=200,
        tolerance=1e-12,
    )
    return src, tgt, truth, opts


@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
def test_covariance_is_the_implicit_jacobian_sandwich(method, x64):
    """icp_covariance == J C J^T, with J = d log(pose0^-1 pose) / d points from jacrev through
    icp's implicit derivative (itself checked against central differences below and in
    test_icp.py): two independent routes to the same first-order propagation."""
    src, tgt, truth, opts = _box_problem(method, n=150)
    rng = np.random.default_rng(3)
    a = rng.normal(size=(len(tgt), 3, 3)) * 1e-3
    target_cov = a @ np.swapaxes(a, 1, 2)

    def delta(s, t):
        """log(pose0^-1 pose) with pose0 the solution held constant (the same value and
        derivative as with pose0 from a separate run), and pose0 itself."""
        pose = icp(s, t, truth, **opts).pose
        pose0 = jax.lax.stop_gradient(pose)
        return (pose0.inverse() @ pose).log(), pose0

    (j_src, j_tgt), pose0 = jax.jacrev(delta, argnums=(0, 1), has_aux=True)(
        jnp.asarray(src), jnp.asarray(tgt)
    )
    j_src, j_tgt = np.asarray(j_src), np.asarray(j_tgt)
    outer_src = np.einsum("anj,bnj->ab", j_src, j_src)
    cov = icp_covariance(
        src, tgt, pose0, source_noise=0.001, target_noise=PointCovariance(target_cov), **opts
    )
    expected = 1e-6 * outer_src + np.einsum("anj,njk,bnk->ab", j_tgt, target_cov, j_tgt)
    np.testing.assert_allclose(cov, expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())
    both = icp_covariance(src, tgt, pose0, point_sigma=0.001, **opts)
    expected = 1e-6 * (outer_src + np.einsum("anj,bnj->ab", j_tgt, j_tgt))
    np.testing.assert_allclose(both, expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())


@pytest.mark.slow
def test_float32_covariance_matches_float64_on_a_large_problem():
    """Regression: jax.jacrev's vmapped scatter-add is miscompiled on CPU in float32 once a
    cloud has more than ~1800 matched points (XLA, jax 0.10.2); icp_covariance must not be."""
    src, tgt, truth, opts = _box_problem("point_to_plane", n=2000)
    noise = IsotropicNoise(0.001)
    cov32 = np.asarray(
        icp_covariance(
            src.astype(np.float32), tgt.astype(np.float32), truth, target_noise=noise, **opts
        )
    )
    with jax.enable_x64(True):
        cov64 = np.asarray(
            icp_covariance(
                src, tgt, SE3(jnp.asarray(truth.wxyz_xyz, jnp.float64)), target_noise=noise, **opts
            )
        )
    np.testing.assert_allclose(np.sqrt(np.diag(cov32)), np.sqrt(np.diag(cov64)), rtol=2e-3)


def test_degenerate_directions_get_infinite_variance():
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-0.05, 0.05, (400, 2)), np.zeros(400)].astype(np.float32)
    normals = np.tile(np.float32([0, 0, 1]), (400, 1))
    cov = np.asarray(
        icp_covariance(
            plane,
            plane,
            SE3.identity(),
            method="point_to_plane",
            target_normals=normals,
            point_sigma=0.001,
        )
    )
    free = np.array([True, True, False, False, False, True])  # vx, vy, wz slide in the plane
    assert np.all(np.isinf(cov[free][:, free]))
    constrained = cov[np.ix_(~free, ~free)]
    assert np.all(np.isfinite(constrained))
    # tz is the mean of 400 points' z noise: (2 sigma^2 / 400) with both clouds noisy.
    assert constrained[0, 0] == pytest.approx(2 * 1e-6 / 400, rel=0.05)


def test_bad_arguments_raise():
    src, tgt, truth, opts = _box_problem("point_to_point", n=50)
    with pytest.raises(ValueError, match="noise model"):
        icp_covariance(src, tgt, truth, **opts)
    with pytest.raises(ValueError, match="not both"):
        icp_covariance(src, tgt, truth, point_sigma=0.001, source_noise=0.001, **opts)
    with pytest.raises(ValueError, match="source_noise"):
        icp_covariance(src, tgt, truth, source_noise=np.ones(3), **opts)
    with pytest.raises(ValueError, match="PointCovariance"):
        icp_covariance(src, tgt, truth, target_noise=PointCovariance(np.zeros((3, 3, 3))), **opts)
    with pytest.raises(TypeError, match="unknown keyword argument 'max_corr'"):
        icp_covariance(src, tgt, truth, point_sigma=0.001, max_corr=0.01)


# --------------------------------------------------------------------------------------------
# icp_covariance against Monte Carlo on a real scan.


@pytest.fixture(scope="module")
def milk_scan_to_model(pcl_dir):
    """Scan-to-model registration on milk.pcd (a Kinect capture, camera frame, z = 0.71-0.89
    m): the target is the 4 mm voxel model with its normals, the source 1500 raw scan points
    expressed in another frame (so the camera sits at ``truth^-1``), re-measured with depth
    noise sigma_z = 2 mm * z^2 (1.0-1.6 mm) along each camera ray."""
    scan = load_points(pcl_dir / "milk.pcd")
    model = voxel_downsample(scan, 0.004).astype(np.float32)
    normals = np.asarray(estimate_normals(model, k=20))
    rng = np.random.default_rng(0)
    view = scan[rng.choice(len(scan), 1500, replace=False)].astype(np.float32)
    truth = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(0.1, -0.2, 0.3), jnp.array([0.05, -0.02, 0.1])
    )
    source = np.asarray(truth.inverse() @ view)
    noise = DepthNoise((0.0, 0.0, 0.002), base_T_camera=truth.inverse())
    return dict(
        model=model,
        normals=normals,
        source=source,
        truth=truth,
        noise=noise,
        grid=build_grid(model, 0.01),
    )


def monte_carlo_sigmas(setup, method, draws):
    """Per-axis sigma (vx, vy, vz, wx, wy, wz) of ICP over ``draws`` re-noised scans, and the
    closed-form prediction from the first draw alone (as a user with one scan would)."""
    opts = dict(
        method=method,
        max_correspondence_distance=0.01,
        max_iterations=60,
        tolerance=1e-7,
        target_normals=setup["normals"] if method == "point_to_plane" else None,
    )
    keys = jax.random.split(jax.random.key(0), draws)
    scans = jax.vmap(lambda k: setup["noise"].sample(k, jnp.asarray(setup["source"])))(keys)
    register = jax.jit(
        jax.vmap(lambda s: icp(s, setup["model"], setup["truth"], neighbors=setup["grid"], **opts))
    )
    results = register(scans)
    usable = (results.status == ICPStatus.success) | (results.status == ICPStatus.max_iterations)
    assert bool(jnp.all(usable))
    measured = np.sqrt(np.diag(np.asarray(pose_statistics(results.pose).covariance)))
    first = SE3(results.pose.wxyz_xyz[0])
    cov = icp_covariance(
        scans[0],
        setup["model"],
        first,
        source_noise=setup["noise"],
        neighbors=setup["grid"],
        **opts,
    )
    return np.sqrt(np.diag(np.asarray(cov))), measured


@pytest.mark.slow
def test_point_to_plane_covariance_agrees_with_monte_carlo(milk_scan_to_model):
    """Measured: predicted / Monte Carlo sigma 0.87-0.96 per axis (200 draws)."""
    predicted, measured = monte_carlo_sigmas(milk_scan_to_model, "point_to_plane", 200)
    ratio = predicted / measured
    assert np.all((ratio > 0.8) & (ratio < 1.2)), ratio
    assert measured[0] > 10 * measured[2]  # the carton slides along x far more than along z


@pytest.mark.slow
def test_point_to_point_closed_form_is_overconfident(milk_scan_to_model):
    """The documented caveat, measured: the frozen-correspondence formula misses the spread
    point-to-point ICP gets from jumping between discrete matches (ratio 0.2-0.7 here)."""
    predicted, measured = monte_carlo_sigmas(milk_scan_to_model, "point_to_point", 200)
    ratio = predicted / measured
    assert np.all(ratio < 0.8), ratio
    assert np.all(ratio > 0.1), ratio


# --------------------------------------------------------------------------------------------
# Initialisation spread.


@pytest.mark.slow
def test_init_spread_is_zero_for_a_unique_fixed_point_and_large_outside_the_basin():
    src, tgt, truth, opts = _box_problem("point_to_plane", n=200, resample=False, noise=1e-5)
    # One grid for every call: the 13-start loop compiles once for init_spread and the total.
    grid = build_grid(tgt, opts["max_correspondence_distance"])
    opts = dict(opts, max_iterations=40, tolerance=1e-7, neighbors=grid)
    pose = icp(src, tgt, truth, **opts).pose
    small = np.diag([2e-3] * 3 + [np.radians(2)] * 3) ** 2
    inside = np.asarray(init_spread(src, tgt, pose, small, **opts))
    measurement = np.asarray(icp_covariance(src, tgt, pose, point_sigma=1e-5, **opts))
    assert np.all(np.sqrt(np.diag(inside)) < 0.1 * np.sqrt(np.diag(measurement)))
    # A 40 degree yaw sigma puts sigma points 106 degrees away: other box faces win there.
    wide = np.diag([2e-3] * 3 + [0.01, 0.01, np.radians(40)]) ** 2
    outside = np.asarray(init_spread(src, tgt, pose, wide, **opts))
    assert np.sqrt(outside[5, 5]) > np.radians(10)
    total = np.asarray(
        icp_covariance(src, tgt, pose, point_sigma=1e-5, init_covariance=wide, **opts)
    )
    np.testing.assert_allclose(total, measurement + outside, rtol=1e-4, atol=1e-12)


@pytest.mark.slow
def test_init_spread_sees_the_discrete_fixed_points_of_a_resampled_surface():
    """A scan is a different sampling of the surface than the model: ICP then has many
    nearby fixed points (correspondence sets), and where it stops depends on the start even
    well inside the basin. Measured on this box: about as large as the noise term."""
    src, tgt, truth, opts = _box_problem("point_to_plane", n=200)
    opts = dict(opts, max_iterations=40, tolerance=1e-7)
    pose = icp(src, tgt, truth, **opts).pose
    small = np.diag([2e-3] * 3 + [np.radians(2)] * 3) ** 2
    spread = np.sqrt(np.diag(np.asarray(init_spread(src, tgt, pose, small, **opts))))
    noise = np.sqrt(np.diag(np.asarray(icp_covariance(src, tgt, pose, point_sigma=2e-4, **opts))))
    assert np.max(spread[3:] / noise[3:]) > 0.25


# --------------------------------------------------------------------------------------------
# Implicit gradients of ICP with respect to every differentiable input.


def _gradient_problem():
    """The float64 point-to-plane problem of the gradient tests, and ``solve``: the pose's
    log of ICP run on it with any of its differentiable inputs replaced."""
    src, tgt, truth, opts = _box_problem("point_to_plane", n=150, seed=4)
    normals = opts.pop("target_normals")
    weights = np.random.default_rng(2).uniform(0.5, 1.5, len(src))
    values = dict(
        target=tgt, target_normals=normals, source_weights=weights, kernel_scale=np.float64(0.002)
    )

    def solve(**replaced):
        args = dict(values, **replaced)
        return icp(
            src,
            args["target"],
            truth,
            target_normals=args["target_normals"],
            source_weights=args["source_weights"],
            kernel=Cauchy(args["kernel_scale"]),
            **opts,
        ).pose.log()

    return values, solve


@pytest.fixture(scope="module")
def implicit_jacobians():
    """d pose log / d every differentiable input, from one reverse pass through ICP's implicit
    derivative (one compilation serves the four checks below)."""
    with jax.enable_x64(True):
        values, solve = _gradient_problem()
        jac = jax.jacrev(lambda v: solve(**v))({k: jnp.asarray(x) for k, x in values.items()})
        return {k: np.asarray(x) for k, x in jac.items()}


@pytest.mark.parametrize(
    "wrt",
    [
        "target",
        "target_normals",
        "source_weights",
        "kernel_scale",
    ],
)
def test_implicit_gradients_match_central_differences(wrt, implicit_jacobians, x64):
    """d pose / d (target points | target normals | source weights | Cauchy scale) by the
    implicit function theorem, against central differences of whole ICP runs (float64)."""
    values, solve = _gradient_problem()
    x0 = values[wrt]
    jac = implicit_jacobians[wrt]
    assert jac.shape == (6, *np.shape(x0)) and np.all(np.isfinite(jac))
    entries = [()] if np.ndim(x0) == 0 else [(3, 0), (90, 2)] if np.ndim(x0) == 2 else [(3,), (90,)]
    for index in entries:
        e = np.zeros_like(x0)
        e[index] = 1e-7
        fd = (np.asarray(solve(**{wrt: x0 + e})) - np.asarray(solve(**{wrt: x0 - e}))) / 2e-7
        column = jac[(slice(None), *index)]
        assert np.abs(fd - column).max() <= 1e-3 * np.abs(column).max() + 1e-9


# --------------------------------------------------------------------------------------------
# Pose statistics.


SIGMA_T = np.array([0.5e-3, 1.0e-3, 2.0e-3])
SIGMA_R = np.radians([0.2, 0.5, 1.0])
BIAS_T = np.array([1.0e-3, -2.0e-3, 0.5e-3])
TRUTH = SE3.from_rotation_and_translation(
    SO3.from_rpy_radians(0.3, -0.5, 2.0), jnp.array([0.4, -0.1, 0.2])
)
# A square container's four rotations about its vertical axis, which passes through
# (0.05, 0.05, 0) of an object frame whose origin sits at a corner.
CENTRE = np.array([0.05, 0.05, 0.0])
SQUARE = SE3.from_rotation_and_translation(
    SO3.from_z_radians(jnp.pi / 2 * jnp.arange(1, 4)),
    jnp.asarray(
        CENTRE - np.asarray(SO3.from_z_radians(jnp.pi / 2 * jnp.arange(1, 4)).as_matrix()) @ CENTRE
    ),
)


def known_poses(count, seed=0, offsets=None):
    """Positions ~ N(truth + bias (+ offsets), diag SIGMA_T^2), rotations
    exp(w) R_truth with w ~ N(0, diag SIGMA_R^2): known per-base-axis sigmas."""
    rng = np.random.default_rng(seed)
    t = np.asarray(TRUTH.translation()) + BIAS_T + rng.normal(size=(count, 3)) * SIGMA_T
    if offsets is not None:
        t = t + offsets
    w = rng.normal(size=(count, 3)) * SIGMA_R
    rotations = SO3.exp(jnp.asarray(w)) @ TRUTH.rotation()
    return SE3.from_rotation_and_translation(rotations, jnp.asarray(t, jnp.float32))


def test_statistics_of_a_known_distribution(dtype):
    poses = known_poses(500)
    poses = SE3(jnp.asarray(poses.wxyz_xyz, dtype))
    stats = pose_statistics(poses, reference=TRUTH)
    np.testing.assert_allclose(stats.translation_sigma, SIGMA_T, rtol=0.12)
    np.testing.assert_allclose(stats.rotation_sigma_deg, SIGMA_R * DEG, rtol=0.12)
    assert np.all(np.abs(stats.translation_bias - BIAS_T) < 3.5 * SIGMA_T / np.sqrt(500))
    assert np.all(np.abs(stats.rotation_bias_deg) < 3.5 * SIGMA_R * DEG / np.sqrt(500))
    assert float(stats.rotation_spread_deg) == pytest.approx(
        np.sqrt(np.sum(SIGMA_R**2)) * DEG, rel=0.1
    )
    # Karcher mean: the truth moved by the bias, up to sampling error.
    np.testing.assert_allclose(
        stats.mean.translation(),
        TRUTH.translation() + BIAS_T,
        atol=3.5 * SIGMA_T.max() / np.sqrt(500),
    )
    # Right-perturbation covariance: the base-frame spreads seen from the object frame.
    r = np.asarray(stats.mean.rotation().as_matrix(), np.float64)
    expected = np.zeros((6, 6))
    expected[:3, :3] = r.T @ np.diag(SIGMA_T**2) @ r
    expected[3:, 3:] = r.T @ np.diag(SIGMA_R**2) @ r
    np.testing.assert_allclose(
        np.sqrt(np.diag(stats.covariance)), np.sqrt(np.diag(expected)), rtol=0.15
    )
    assert stats.count == 500 and stats.groups is None


def test_symmetric_object_hopping_between_branches():
    """Raw poses hop between the square container's four branches (translations jump by
    centimetres because the origin is off the axis); canonicalised, they give the known
    statistics, while the raw statistics are fiction."""
    poses = known_poses(500, seed=1)  # as many as above: the raw statistics reuse its program
    rng = np.random.default_rng(5)
    group = SE3(jnp.concatenate([SE3.identity().wxyz_xyz[None], SQUARE.wxyz_xyz]))
    branch = rng.integers(0, 4, 500)
    raw = poses @ SE3(group.wxyz_xyz[branch])
    naive = pose_statistics(raw, reference=TRUTH)
    assert np.all(naive.translation_sigma > 0.01) and naive.rotation_spread_deg > 45

    stats = pose_statistics(raw, reference=TRUTH, symmetry=SQUARE)
    np.testing.assert_allclose(stats.translation_sigma, SIGMA_T, rtol=0.12)
    np.testing.assert_allclose(stats.rotation_sigma_deg, SIGMA_R * DEG, rtol=0.12)
    np.testing.assert_allclose(stats.canonical.as_matrix(), poses.as_matrix(), atol=1e-5)
    # Without a reference every pose lands on one common branch (the first pose's), which
    # fixes the rotation statistics; the origin's position spread then includes the rotation
    # noise times the lever arm to the axis, as it physically does for that corner.
    free = pose_statistics(raw, symmetry=SQUARE)
    offsets = np.asarray((poses.inverse() @ free.canonical).as_matrix())
    np.testing.assert_allclose(offsets, np.broadcast_to(offsets[0], offsets.shape), atol=1e-5)
    np.testing.assert_allclose(free.rotation_sigma_deg, SIGMA_R * DEG, rtol=0.12)
    # The reference may itself sit on another branch: the bias is measured to its nearest copy.
    stats = pose_statistics(raw, reference=TRUTH @ SE3(SQUARE.wxyz_xyz[1]), symmetry=SQUARE)
    assert np.all(np.abs(stats.translation_bias - BIAS_T) < 3.5 * SIGMA_T / np.sqrt(500))


def test_symmetry_description_is_the_metrics_one():
    """A container with its axis through the object origin: pose_statistics takes the
    jaxreg.Symmetry that ADD-S and the synthetic scenes use, and a continuous axis
    (a cylinder) is discretised into symmetry_steps turns, canonical to within half a step."""
    poses = known_poses(200, seed=3)
    rng = np.random.default_rng(6)
    quarter = Symmetry(np.asarray(SO3.from_z_radians(jnp.pi / 2 * jnp.arange(4)).as_matrix()))
    raw = poses @ SE3.from_rotation(SO3.from_z_radians(jnp.pi / 2 * rng.integers(0, 4, 200)))
    stats = pose_statistics(raw, reference=TRUTH, symmetry=quarter)
    np.testing.assert_allclose(stats.canonical.as_matrix(), poses.as_matrix(), atol=1e-5)
    np.testing.assert_allclose(stats.rotation_sigma_deg, SIGMA_R * DEG, rtol=0.15)

    cylinder = Symmetry(np.eye(3)[None], axis=np.array([0.0, 0.0, 1.0]))
    spun = poses @ SE3.from_rotation(SO3.from_z_radians(rng.uniform(-np.pi, np.pi, 200)))
    stats = pose_statistics(spun, reference=TRUTH, symmetry=cylinder, symmetry_steps=720)
    step_deg = 360 / 720
    assert np.all(np.asarray(stats.rotation_angles_deg) < 5 * np.max(SIGMA_R) * DEG + step_deg)
    with pytest.raises(ValueError, match="Symmetry or a jaxlie.SE3"):
        pose_statistics(raw, symmetry=np.eye(3)[None])


def test_viewpoint_groups_expose_a_hand_eye_bias():
    """Three viewpoints: tight clusters (sigmas 0.5-2 mm) offset by 2-6 mm from each other are
    flagged; the same poses without the offsets are not."""
    labels = np.repeat(np.arange(3), 60)
    offsets = np.array([[0.0, 0.0, 0.0], [6e-3, 0.0, 0.0], [0.0, -6e-3, 2e-3]])[labels]
    # With a reference (no symmetry: it changes nothing here but the bias fields), the same
    # compiled statistics as the unpadded poses of test_zero_weights_drop_padding.
    biased = pose_statistics(
        known_poses(180, seed=2, offsets=offsets), reference=TRUTH, groups=labels
    )
    g = biased.groups
    assert bool(g.bias_detected)
    assert g.offset_ratio[0] > 2 and g.p_value[0] < 1e-6
    np.testing.assert_array_equal(g.count, [60, 60, 60])
    expected = offsets[[0, 60, 120]] - offsets.mean(0)
    np.testing.assert_allclose(g.translation_offset, expected, atol=4 * SIGMA_T.max() / np.sqrt(60))
    np.testing.assert_allclose(g.translation_sigma, np.tile(SIGMA_T, (3, 1)), rtol=0.3)
    # Overall sigma is inflated by the offsets; within-group sigma is not.
    assert biased.translation_sigma[0] > 2 * SIGMA_T[0]

    fair = pose_statistics(known_poses(180, seed=2), reference=TRUTH, groups=labels).groups
    assert not bool(fair.bias_detected)
    assert np.all(fair.offset_ratio < 0.5) and np.all(fair.p_value > 1e-3)


def test_zero_weights_drop_padding():
    # 180 poses in 3 groups, as in test_viewpoint_groups_expose_a_hand_eye_bias: `a` reuses
    # its compiled statistics.
    poses = known_poses(180, seed=3)
    padded = SE3(jnp.concatenate([poses.wxyz_xyz, jnp.full((7, 7), jnp.nan)]))
    weights = np.r_[np.ones(180), np.zeros(7)]
    labels = np.r_[np.arange(180) % 3, np.zeros(7, int)]
    a = pose_statistics(poses, reference=TRUTH, groups=labels[:180])
    b = pose_statistics(padded, reference=TRUTH, groups=labels, weights=weights)
    for x, y in [
        (a.translation_sigma, b.translation_sigma),
        (a.covariance, b.covariance),
        (a.mean.wxyz_xyz, b.mean.wxyz_xyz),
        (a.translation_bias, b.translation_bias),
        (a.groups.p_value, b.groups.p_value),
        (a.groups.count, b.groups.count),
    ]:
        np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-9)
    assert b.count == 180
    with pytest.raises(ValueError, match="SE3 batch"):
        pose_statistics(TRUTH)
    with pytest.raises(ValueError, match="at least 2"):
        pose_statistics(poses, weights=np.r_[1.0, np.zeros(179)])
    with pytest.raises(ValueError, match="labels"):
        pose_statistics(poses, groups=np.arange(180), num_groups=3)


# --------------------------------------------------------------------------------------------
# Grasp success.


def test_grasp_success_probability_matches_the_normal_distribution():
    margin = grasp_margin(40.0, 25.0)
    assert float(margin) == 7.5
    assert float(grasp_margin(40.0, 25.0, friction_allowance=1.5)) == 6.0
    sigmas = np.array([0.5, 2.0, 3.0, 5.0])
    biases = np.array([0.0, 2.0, 5.0, 7.5])
    p = np.asarray(grasp_success_probability(sigmas[:, None], biases[None, :], margin))
    for i, s in enumerate(sigmas):
        for j, b in enumerate(biases):
            dist = NormalDist(b, s)
            assert p[i, j] == pytest.approx(dist.cdf(7.5) - dist.cdf(-7.5), abs=1e-6)
    # Bias eats the margin: monotone in |bias|, symmetric in its sign.
    assert np.all(np.diff(p, axis=1) <= 0) and np.all(p[:, -1] < p[:, 0])
    np.testing.assert_allclose(grasp_success_probability(2.0, -5.0, 7.5), p[1, 2], rtol=1e-6)
    # sigma = 0: the indicator; negative margin: 0.
    np.testing.assert_array_equal(
        grasp_success_probability(0.0, np.array([0.0, 7.0, 7.5, 8.0, -8.0]), 7.5),
        [1.0, 1.0, 0.5, 0.0, 0.0],
    )
    assert float(grasp_success_probability(1.0, 0.0, -1.0)) == 0.0
    grads = jax.grad(grasp_success_probability, argnums=(0, 1, 2))(0.0, 1.0, 7.5)
    assert all(np.isfinite(g) for g in grads)
    d_sigma = jax.grad(grasp_success_probability)(3.0, 0.0, 7.5)
    assert float(d_sigma) < 0  # more noise, fewer grasps


def test_grasp_prediction_across_the_narrowest_axis():
    """A 60 x 40 x 30 mm box turned about x by 30 degrees: the jaws close along its 30 mm
    side (the turned z axis); each number checked against one computed here."""
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    turn = np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    lattice = np.stack(np.meshgrid(*(np.linspace(-1, 1, 9),) * 3, indexing="ij"), -1)
    lattice = lattice.reshape(-1, 3)
    surface = lattice[np.abs(lattice).max(1) == 1]  # symmetric: the box's axes are principal
    points = (surface * [0.03, 0.02, 0.015]) @ turn.T
    jaw = turn[:, 2]
    block = np.array([[4.0, 1.0, 0.5], [1.0, 9.0, 2.0], [0.5, 2.0, 16.0]]) * 1e-5
    covariance = np.zeros((6, 6))
    covariance[:3, :3] = block
    covariance[3:, 3:] = np.eye(3) * 1e-4
    grasp = grasp_prediction(points, covariance, opening=0.045)
    assert isinstance(grasp, GraspPrediction)
    assert abs(grasp.axis @ jaw) == pytest.approx(1.0, abs=1e-6)
    assert grasp.width == pytest.approx(0.03, abs=1e-9)
    assert grasp.margin == pytest.approx(0.0075, abs=1e-8)
    sigma = math.sqrt(jaw @ block @ jaw)
    assert grasp.lateral_sigma == pytest.approx(sigma, rel=1e-9)
    normal = NormalDist(0.0, sigma)
    assert grasp.probability == pytest.approx(normal.cdf(0.0075) - normal.cdf(-0.0075), abs=1e-6)
    # A known error: its component along the jaws is the bias.
    offset = 0.004 * jaw + np.array([0.01, 0.0, 0.0])  # the x part is along the jaws' faces
    assert grasp.lateral_error(offset) == pytest.approx(0.004, abs=1e-9)
    biased = NormalDist(0.004, sigma)
    expected = biased.cdf(0.0075) - biased.cdf(-0.0075)
    assert grasp.probability_with_error(offset) == pytest.approx(expected, abs=1e-6)
    # A friction allowance takes from the margin; a budget gives its total's numbers.
    assert grasp_prediction(points, covariance, 0.045, 0.002).margin == pytest.approx(0.0055)
    terms = {name: np.zeros((6, 6)) for name in SOURCES}
    terms["depth"], terms["fit"] = 0.25 * covariance, 0.75 * covariance
    from_budget = grasp_prediction(points, combine(terms, np.zeros(6, bool), None), 0.045)
    assert from_budget.lateral_sigma == pytest.approx(sigma, rel=1e-9)
    # A free translation across the jaws: no finite sigma, no claimed probability.
    free = covariance.copy()
    free[2, :] = free[:, 2] = 0.0
    free[2, 2] = np.inf
    unknown = grasp_prediction(points, free, 0.045)
    assert unknown.lateral_sigma == np.inf and math.isnan(unknown.probability)
    assert math.isnan(unknown.probability_with_error(offset))
    for bad, match in (
        ((points[:2], covariance, 0.045), "shape"),
        ((points, covariance[:3, :3], 0.045), "shape"),
        ((points, covariance, 0.0), "opening"),
    ):
        with pytest.raises(ValueError, match=match):
            grasp_prediction(*bad)


def test_error_budget_root_sum_square():
    budget = error_budget({"intrinsics": 0.4, "depth": 3.5, "hand_eye": 3.5, "registration": 2.0})
    assert float(budget.total) == pytest.approx(math.sqrt(0.16 + 12.25 + 12.25 + 4.0))
    assert sum(float(s) for s in budget.shares.values()) == pytest.approx(1.0)
    assert float(budget.shares["depth"]) == pytest.approx(12.25 / 28.66)
    vectorised = error_budget({"a": np.array([3.0, 0.0]), "b": np.array([4.0, 0.0])})
    np.testing.assert_allclose(vectorised.total, [5.0, 0.0])
    np.testing.assert_allclose(vectorised.shares["a"], [0.36, 0.0])
    with pytest.raises(ValueError, match="negative"):
        error_budget({"depth": -1.0})
    with pytest.raises(ValueError, match="at least one"):
        error_budget({})
