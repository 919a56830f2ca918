import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3

from jaxreg.geometry.kernels import Tukey
from jaxreg.io import load_points
from jaxreg.registration.icp import (
    ICPStatus,
    best_index,
    icp,
    multistart_icp,
    pca_inits,
    perturbed_inits,
    rotation_inits,
    select_best,
)
from jaxreg.search.neighbors import build_grid, voxel_downsample
from jaxreg.search.normals import estimate_normals

try:
    import open3d as o3d
except ImportError:  # open3d is in the `peers` extra and needs libusb
    o3d = None
needs_open3d = pytest.mark.skipif(o3d is None, reason="open3d not importable (peers extra)")

# PCL's test/registration/test_registration.cpp (IterativeClosestPoint): bun0 -> bun4.
PCL_BUNNY_TRANSFORM = np.array(
    [
        [0.8806, 0.03648, -0.4724, 0.03453],
        [-0.02354, 0.9992, 0.03326, -0.001519],
        [0.4732, -0.01817, 0.8808, 0.04116],
    ]
)


def rotation_error_deg(pose, rotation_matrix):
    r = np.asarray(pose.rotation().as_matrix())
    return np.degrees(np.arccos(np.clip((np.trace(r.T @ rotation_matrix) - 1) / 2, -1, 1)))


def lesson_cube(angle_deg, seed=0):
    """The lesson's experiment: 800 points in a 6 cm cube, a z rotation, 2 mm noise."""
    rng = np.random.default_rng(seed)
    model = rng.uniform(-0.03, 0.03, size=(800, 3))
    a = np.deg2rad(angle_deg)
    r = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    scene = model @ r.T + np.array([0.01, -0.02, 0.005]) + rng.normal(0, 0.002, model.shape)
    return model.astype(np.float32), scene.astype(np.float32), r


def o3d_cloud(points):
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))


def test_reproduces_pcl_icp_unit_test(pcl_dir):
    source = load_points(pcl_dir / "bun0.pcd")
    target = load_points(pcl_dir / "bun4.pcd")
    result = icp(
        source, target, max_correspondence_distance=0.05, max_iterations=50, tolerance=1e-8
    )
    matrix = np.asarray(result.pose.as_matrix())
    np.testing.assert_allclose(matrix[:3], PCL_BUNNY_TRANSFORM, atol=1e-3)
    assert bool(result.converged) and result.status == ICPStatus.success
    if o3d is not None:
        ref = o3d.pipelines.registration.registration_icp(
            o3d_cloud(source),
            o3d_cloud(target),
            0.05,
            np.eye(4),
            o3d.pipelines.registration.TransformationEstimationPointToPoint(),
            o3d.pipelines.registration.ICPConvergenceCriteria(1e-8, 1e-8, 50),
        )
        np.testing.assert_allclose(matrix, ref.transformation, atol=1e-4)
        assert float(result.inlier_rmse) == pytest.approx(ref.inlier_rmse, rel=1e-3)
        assert float(result.inlier_fraction) == pytest.approx(ref.fitness, rel=1e-3)


def test_lesson_cube_inside_and_outside_the_basin():
    model, scene, r = lesson_cube(15.0)
    inside = icp(model, scene, max_correspondence_distance=0.02, max_iterations=40)
    assert rotation_error_deg(inside.pose, r) < 0.5  # the lesson: about 0.3 degrees
    assert inside.status == ICPStatus.success

    model, scene, r = lesson_cube(60.0)
    outside = icp(model, scene, max_correspondence_distance=0.02, max_iterations=40)
    # Confidently wrong: > 80 degrees off, yet every point matched at a ~4 mm residual.
    assert rotation_error_deg(outside.pose, r) > 80.0
    assert 0.003 < float(outside.inlier_rmse) < 0.005
    assert float(outside.inlier_fraction) > 0.95
    np.testing.assert_array_equal(np.isnan(outside.rmse_history), False)  # all 40 ran


def test_multistart_escapes_the_wrong_basin_and_keeps_per_start_status():
    model, scene, r = lesson_cube(60.0)
    angles = np.deg2rad(np.arange(0, 360, 30))
    starts = SE3.from_rotation(SO3.from_z_radians(jnp.asarray(angles, jnp.float32)))
    far = SE3.from_translation(jnp.array([[5.0, 0.0, 0.0]], jnp.float32))
    inits = SE3(jnp.concatenate([starts.wxyz_xyz, far.wxyz_xyz]))
    results = multistart_icp(model, scene, inits, max_correspondence_distance=0.02)
    assert results.pose.get_batch_axes() == (13,)
    failed = np.asarray(results.status == ICPStatus.too_few_correspondences)
    np.testing.assert_array_equal(failed, [False] * 12 + [True])
    assert "fewer than 3 correspondences" in results.status_message()[12]
    assert not bool(results.converged[12])
    best = select_best(results)
    assert best.batch_shape == () and best.status == ICPStatus.success
    assert rotation_error_deg(best.pose, r) < 1.0
    index = int(best_index(results))
    np.testing.assert_array_equal(best.pose.wxyz_xyz, results.pose.wxyz_xyz[index])
    single = icp(model, scene, SE3(inits.wxyz_xyz[2]), max_correspondence_distance=0.02)
    np.testing.assert_allclose(results[2].pose.as_matrix(), single.pose.as_matrix(), atol=1e-5)


def test_init_as_matrix_and_distance_schedule():
    """A 4x4 start and a distance per iteration, tightening from 2 to 1 cm: 40 of them, so
    the program compiled for the lesson cube (a scalar distance is a schedule of 40, its grid
    sized by 2 cm) runs it."""
    model, scene, r = lesson_cube(15.0)
    schedule = np.geomspace(0.02, 0.01, 40)
    result = icp(model, scene, np.eye(4), max_correspondence_distance=schedule, max_iterations=40)
    assert rotation_error_deg(result.pose, r) < 0.5
    with pytest.raises(ValueError, match="one distance per iteration"):
        icp(model, scene, max_correspondence_distance=schedule[:5], max_iterations=40)


def test_partial_view_needs_trimming_or_a_robust_kernel():
    """A full box model against a scan that sees half of it (the lesson's partial view):
    unmatched model points bias plain ICP; trimming to the overlap or a redescending
    kernel removes the bias."""
    rng = np.random.default_rng(3)
    f = rng.uniform(-0.03, 0.03, (1500, 3))
    f[np.arange(1500), rng.integers(0, 3, 1500)] = np.sign(rng.normal(size=1500)) * 0.03
    f *= np.array([1.5, 1.0, 0.7])  # surface of a 9 x 6 x 4.2 cm box
    model = f.astype(np.float32)
    a = np.deg2rad(5.0)
    r = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]])
    t = np.array([0.01, -0.02, 0.005])
    seen = (f[:, 0] < 0.044) & (f[:, 1] < 0.029) & (f[:, 2] > -0.02)
    scene = model[seen] @ r.T + t + rng.normal(0, 0.001, (seen.sum(), 3))
    init = SE3.from_translation(jnp.asarray(t, jnp.float32))

    def errors(**options):
        res = icp(
            model, scene.astype(np.float32), init, max_correspondence_distance=0.02, **options
        )
        assert res.status == ICPStatus.success
        t_err = np.linalg.norm(np.asarray(res.pose.translation()) - t)
        return rotation_error_deg(res.pose, r), t_err

    plain_r, plain_t = errors()
    assert plain_r > 3.0 and plain_t > 0.004  # biased by the unseen half
    for options in (dict(trim_fraction=0.55), dict(kernel=Tukey(0.005))):
        rot, trans = errors(**options)
        assert rot < 0.6 and trans < 0.001, options


def test_bad_input_gives_a_clear_error_or_status():
    model, scene, _ = lesson_cube(5.0)
    with pytest.raises(ValueError, match="empty"):
        icp(np.zeros((0, 3), np.float32), scene)
    with pytest.raises(ValueError, match="empty"):
        icp(model, np.zeros((0, 3), np.float32))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        icp(model[:, :2], scene)
    with pytest.raises(ValueError, match="target_normals"):
        icp(model, scene, method="point_to_plane")
    with pytest.raises(ValueError, match="at least 3"):
        icp(model[:2], scene)

    nan_source = np.full_like(model, np.nan)
    result = icp(nan_source, scene)
    assert result.status == ICPStatus.too_few_correspondences
    assert np.all(np.isfinite(result.pose.wxyz_xyz))

    far = icp(model, scene, SE3.from_translation(jnp.array([3.0, 0.0, 0.0])))
    assert far.status == ICPStatus.too_few_correspondences and not bool(far.converged)
    np.testing.assert_allclose(far.pose.translation(), [3.0, 0.0, 0.0])  # kept, flagged

    holes = model.copy()
    holes[::3] = np.nan  # depth holes are masked, not propagated
    ok = icp(holes, scene, max_correspondence_distance=0.02)
    assert ok.status == ICPStatus.success and np.isfinite(float(ok.inlier_rmse))

    line = np.outer(np.linspace(-0.05, 0.05, 50), [1.0, 0.5, 0.2]).astype(np.float32)
    degenerate = icp(line, line + 0.001, max_correspondence_distance=0.02)
    assert degenerate.status == ICPStatus.degenerate
    assert not bool(degenerate.converged)  # the loop stopped, but the pose is not unique
    assert np.all(np.isfinite(degenerate.pose.wxyz_xyz))

    # No update falls below a zero tolerance: the loop runs out of iterations (the compiled
    # loop of the calls above; a new max_iterations would compile another).
    bounded = icp(model, scene, max_correspondence_distance=0.02, tolerance=0.0)
    assert bounded.status == ICPStatus.max_iterations and not bool(bounded.converged)
    assert int(bounded.iterations) == 40


def test_a_kernel_that_weighs_every_pair_zero_is_named_not_called_degenerate():
    """Tukey's weight is 0 beyond its scale: on a 2 cm lattice moved by 6 mm per axis every
    point's match is its twin, 10.4 mm away: within the correspondence distance, but past a
    1 mm scale, so no pair has weight."""
    axis = np.arange(4, dtype=np.float32) * 0.02
    model = np.stack(np.meshgrid(axis, axis, axis), -1).reshape(-1, 3)
    result = icp(model, model + 0.006, kernel=Tukey(0.001))
    assert result.status == ICPStatus.too_few_weighted_pairs
    assert "kernel" in result.status_message()
    assert not bool(result.converged) and int(result.iterations) == 0
    np.testing.assert_array_equal(result.pose.wxyz_xyz, SE3.identity().wxyz_xyz)
    assert float(result.inlier_fraction) == 1.0  # every pair is within the distance
    plain = icp(model, model + 0.006, kernel=Tukey(0.05))  # a scale that fits the residuals
    assert plain.status == ICPStatus.success
    np.testing.assert_allclose(plain.pose.translation(), [0.006] * 3, atol=1e-5)


def _box_faces(seed: int, count: int):
    """``count`` points on the faces of a 6 x 4 x 3 cm box, their outward unit normals, and
    the generator that drew them (for further draws)."""
    rng = np.random.default_rng(seed)
    half = np.array([0.03, 0.02, 0.015])
    target = rng.uniform(-half, half, (count, 3))
    axis = rng.integers(0, 3, count)
    target[np.arange(count), axis] = np.sign(rng.normal(size=count)) * half[axis]
    normals = np.zeros_like(target)
    normals[np.arange(count), axis] = np.sign(target[np.arange(count), axis])
    return target, normals, rng


def test_points_without_a_unit_normal_are_neither_matched_nor_counted():
    """Point-to-plane against a box whose normals are zero (what estimate_normals returns where
    a normal is undefined), unnormalised or NaN on three rows in four: only the fourth row
    can be a match. With the source equal to the target and a distance below the point
    spacing, each source point can match only its own twin."""
    target, normals, rng = _box_faces(0, 800)
    normals[0::4] = 0.0
    normals[1::4] *= 2.0
    normals[2::4] = np.nan
    target, normals = target.astype(np.float32), normals.astype(np.float32)
    result = icp(
        target,
        target,
        method="point_to_plane",
        target_normals=normals,
        max_correspondence_distance=1e-5,
    )
    assert result.status == ICPStatus.success
    assert float(result.inlier_fraction) == 0.25 and int(result.num_inliers) == 200
    matched = np.asarray(result.correspondences) < 800
    np.testing.assert_array_equal(np.flatnonzero(matched), np.arange(3, 800, 4))
    everything = icp(
        target,
        target,
        method="point_to_plane",
        target_normals=np.zeros_like(normals),
        max_correspondence_distance=0.01,
    )
    assert everything.status == ICPStatus.too_few_correspondences
    assert "unit normals" in everything.status_message()


def test_a_given_grid_that_indexes_points_without_a_normal_raises():
    """Half the target's normals zero, and a grid built on every target point: a source
    point whose nearest target point has no normal went unmatched, though a valid target
    point lay within the distance (about half the points, where the same ICP without the
    grid finds a match for every one). Such a grid is refused; one built without those rows
    agrees with ICP's own."""
    target, normals, rng = _box_faces(1, 2000)
    normals[::2] = 0.0
    target, normals = target.astype(np.float32), normals.astype(np.float32)
    source = target + rng.normal(0, 0.002, target.shape).astype(np.float32)
    options = dict(
        method="point_to_plane", target_normals=normals, max_correspondence_distance=0.02
    )
    with pytest.raises(ValueError, match="1000 target points .* without a finite unit normal"):
        icp(source, target, neighbors=build_grid(target, 0.02), **options)
    usable = np.any(normals != 0, axis=1)
    masked = icp(source, target, neighbors=build_grid(target, 0.02, mask=usable), **options)
    alone = icp(source, target, **options)
    assert float(masked.inlier_fraction) == float(alone.inlier_fraction) == 1.0
    np.testing.assert_allclose(masked.pose.wxyz_xyz, alone.pose.wxyz_xyz, atol=1e-6)


def test_a_grid_checked_once_is_checked_again_for_other_inputs():
    """A given grid's checks are remembered for the inputs they passed on, not for the grid:
    the same grid then raises for another target (also one edited in place), a larger
    distance, or a point-to-plane call whose normals leave indexed rows unusable."""
    model, scene, _ = lesson_cube(5.0)
    grid = build_grid(scene, 0.02)
    assert icp(model, scene, neighbors=grid).status == ICPStatus.success
    assert icp(model, scene, neighbors=grid).status == ICPStatus.success
    with pytest.raises(ValueError, match="another target"):
        icp(model, scene + np.float32(0.001), neighbors=grid)
    edited = scene.copy()
    assert icp(model, edited, neighbors=grid).status == ICPStatus.success
    edited[0] += 0.001
    with pytest.raises(ValueError, match="another target"):
        icp(model, edited, neighbors=grid)
    with pytest.raises(ValueError, match="queries reach 0.03"):
        icp(model, scene, max_correspondence_distance=0.03, neighbors=grid)
    normals = np.zeros_like(scene)
    normals[:, 2] = 1.0
    normals[::2] = 0.0
    with pytest.raises(ValueError, match="without a finite unit normal"):
        icp(model, scene, method="point_to_plane", target_normals=normals, neighbors=grid)


def test_a_grid_that_cannot_answer_for_this_target_raises():
    model, scene, _ = lesson_cube(5.0)
    with pytest.raises(ValueError, match="another target"):
        icp(model, scene, neighbors=build_grid(scene + np.float32(0.001), 0.02))
    with pytest.raises(ValueError, match="exact within 0.005 but queries reach 0.02"):
        icp(model, scene, max_correspondence_distance=0.02, neighbors=build_grid(scene, 0.005))
    schedule = np.geomspace(0.05, 0.01, 10)
    with pytest.raises(ValueError, match="queries reach 0.05"):
        icp(
            model,
            scene,
            max_correspondence_distance=schedule,
            max_iterations=10,
            neighbors=build_grid(scene, 0.02),
        )
    overflowed = build_grid(scene, 0.02, capacity=1)
    assert bool(overflowed.overflow)
    with pytest.raises(ValueError, match="overflowed"):
        icp(model, scene, neighbors=overflowed)
    good = icp(model, scene, neighbors=build_grid(scene, 0.02))
    assert good.status == ICPStatus.success


def test_start_batch_is_sharded_over_devices():
    """Two host devices: the start axis is split between them and results agree."""
    code = (
        "import numpy as np, jax, jax.numpy as jnp\n"
        "from jaxlie import SE3, SO3\n"
        "from jaxreg.registration.icp import multistart_icp\n"
        "assert len(jax.devices()) == 2\n"
        "rng = np.random.default_rng(0)\n"
        "m = rng.uniform(-0.03, 0.03, (300, 3)).astype(np.float32)\n"
        "s = m + np.float32([0.005, 0, 0])\n"
        "inits = SE3.from_rotation(SO3.from_z_radians(jnp.linspace(-0.2, 0.2, 6)))\n"
        "r = multistart_icp(m, s, inits)\n"
        "assert len(r.pose.wxyz_xyz.sharding.device_set) == 2, r.pose.wxyz_xyz.sharding\n"
        "np.testing.assert_allclose(r.pose.translation(), [[0.005, 0, 0]] * 6, atol=1e-4)\n"
        "print('ok')\n"
    )
    env = dict(
        os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0 and "ok" in out.stdout, out.stderr[-2000:]


def test_point_to_plane_on_a_cluttered_real_scan_matches_open3d(pcl_dir):
    """milk.pcd at 4 mm voxels moved by a known pose, 1 mm noise, 15% uniform outliers."""
    model = voxel_downsample(load_points(pcl_dir / "milk.pcd"), 0.004).astype(np.float32)
    rng = np.random.default_rng(0)
    truth = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(0.06, -0.04, 0.08), jnp.array([0.012, -0.008, 0.01])
    )
    scene = np.asarray(truth @ model) + rng.normal(0, 0.001, model.shape)
    lo, hi = scene.min(0) - 0.02, scene.max(0) + 0.02
    scene = np.concatenate([scene, rng.uniform(lo, hi, (len(scene) * 15 // 100, 3))])
    scene = scene.astype(np.float32)
    normals = np.asarray(estimate_normals(scene, k=20))
    r_true = np.asarray(truth.rotation().as_matrix())
    t_true = np.asarray(truth.translation())

    result = icp(
        model,
        scene,
        method="point_to_plane",
        target_normals=normals,
        max_correspondence_distance=0.02,
        max_iterations=60,
    )
    assert result.status == ICPStatus.success
    rot_err = rotation_error_deg(result.pose, r_true)
    trans_err = np.linalg.norm(np.asarray(result.pose.translation()) - t_true)
    assert rot_err < 0.2 and trans_err < 0.002
    if o3d is None:
        pytest.skip("open3d not importable: accuracy checked against the truth only")
    target = o3d_cloud(scene)
    target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    ref = o3d.pipelines.registration.registration_icp(
        o3d_cloud(model),
        target,
        0.02,
        np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(1e-6, 1e-6, 60),
    ).transformation
    ref_rot = np.degrees(np.arccos(np.clip((np.trace(ref[:3, :3].T @ r_true) - 1) / 2, -1, 1)))
    ref_trans = np.linalg.norm(ref[:3, 3] - t_true)
    assert rot_err <= 1.2 * ref_rot + 0.02
    assert trans_err <= 1.2 * ref_trans + 2e-4


def test_point_to_plane_on_a_plane_is_degenerate():
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-0.05, 0.05, (400, 2)), np.zeros(400)].astype(np.float32)
    normals = np.tile(np.float32([0, 0, 1]), (400, 1))
    result = icp(
        plane,
        plane + np.float32([0.002, 0.001, 0.003]),
        method="point_to_plane",
        target_normals=normals,
    )
    assert result.status == ICPStatus.degenerate
    np.testing.assert_allclose(result.pose.translation()[2], 0.003, atol=1e-5)  # observable


def test_initial_pose_generators():
    rng = np.random.default_rng(1)
    box = (rng.uniform(-1, 1, (600, 3)) * np.array([0.06, 0.03, 0.01])).astype(np.float32)
    truth = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(0.7, -1.2, 2.5), jnp.array([0.3, -0.1, 0.5])
    )
    scene = np.asarray(truth @ box)
    starts = pca_inits(box, scene)
    assert starts.get_batch_axes() == (4,)
    np.testing.assert_allclose(
        np.linalg.det(np.asarray(starts.rotation().as_matrix())), 1, atol=1e-5
    )
    errors = [
        rotation_error_deg(SE3(p), np.asarray(truth.rotation().as_matrix()))
        for p in np.asarray(starts.wxyz_xyz)
    ]
    assert min(errors) < 2.0  # one sign choice is the truth (up to sampling noise)

    grid = rotation_inits(box, scene, 50)
    centroids = np.asarray(jax.vmap(lambda p: p @ jnp.asarray(box.mean(0)))(grid))
    np.testing.assert_allclose(centroids, np.tile(scene.mean(0), (50, 1)), atol=1e-5)

    around = rotation_inits(box, scene, 10, around=truth, max_angle=0.2)
    np.testing.assert_allclose(around.wxyz_xyz[0], truth.wxyz_xyz, atol=1e-6)
    angles = np.asarray(
        jnp.linalg.norm((truth.rotation().inverse() @ around.rotation()).log(), axis=-1)
    )
    assert np.all(angles <= 0.2 + 1e-5)

    jitter = perturbed_inits(
        truth, jax.random.key(0), 8, rotation_sigma=0.05, translation_sigma=0.01
    )
    assert jitter.get_batch_axes() == (8,)
    np.testing.assert_allclose(jitter.wxyz_xyz[0], truth.wxyz_xyz, atol=1e-6)
    assert np.all(np.linalg.norm(np.asarray((truth.inverse() @ jitter).log())[1:], axis=-1) > 0)


def _central_difference(f, x, index, eps=1e-6):
    e = np.zeros_like(x)
    e[index] = eps
    return (np.asarray(f(x + e)) - np.asarray(f(x - e))) / (2 * eps)


@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
def test_implicit_gradient_matches_finite_differences(method, x64):
    """d pose / d source by the implicit function theorem, against differences of whole
    ICP runs (float64, tight tolerance, correspondences stable under the perturbation)."""
    model, scene, _ = lesson_cube(5.0)
    model, scene = model[:150].astype(np.float64), scene[:150].astype(np.float64)
    normals = np.asarray(estimate_normals(scene, k=12)) if method == "point_to_plane" else None

    def solve(src):
        return icp(
            src,
            scene,
            method=method,
            target_normals=normals,
            max_correspondence_distance=0.03,
            max_iterations=200,
            tolerance=1e-13,
        ).pose.log()

    jac = np.asarray(jax.jacrev(solve)(jnp.asarray(model)))
    assert np.all(np.isfinite(jac))
    for index in [(0, 0), (7, 1), (42, 2), (149, 0)]:
        fd = _central_difference(solve, model, index)
        err = np.abs(fd - jac[(slice(None),) + index]).max()
        assert err <= 1e-3 * np.abs(jac[(slice(None),) + index]).max() + 1e-9


def test_results_are_unpadded_and_similar_clouds_share_one_compilation():
    from jaxreg.registration.solver import ICPOptions, prepare

    model, scene, _ = lesson_cube(5.0)
    result = icp(model[:787], scene, max_correspondence_distance=0.02)
    assert result.correspondences.shape == (787,) and result.weights.shape == (787,)
    assert int(result.correspondences.max()) < len(scene)
    far = icp(model[:787], scene, SE3.from_translation(jnp.array([3.0, 0.0, 0.0])))
    np.testing.assert_array_equal(far.correspondences, len(scene))  # the sentinel is M

    def signature(source, target):
        problem, opts, _ = prepare(source, target, ICPOptions())
        leaves = jax.tree.leaves((problem, opts))
        return jax.tree.structure((problem, opts)), [(x.shape, x.dtype) for x in leaves]

    rotated = np.asarray(SO3.from_z_radians(0.5) @ jnp.asarray(scene[:770]))
    assert signature(model[:800], scene) == signature(model[:790], rotated)


def test_point_to_point_step_is_align_of_the_pairs():
    """The loop's Kabsch step skips align()'s input checks and solves Horn's eigenproblem by
    Jacobi sweeps; on pairs as the loop forms them (weights, zero-weight rows, rows matched
    to nothing or to target padding) it gives align()'s pose and degeneracy flag, and in the
    degenerate and weightless cases (no unique minimiser) a pose of align()'s cost."""
    import equinox as eqx

    from jaxreg.geometry.alignment import align
    from jaxreg.registration._icp_core import Pairs, _increment, fill_gather
    from jaxreg.registration.solver import ICPOptions, prepare

    increment = eqx.filter_jit(_increment)  # one program (eagerly, each primitive compiles)

    rng = np.random.default_rng(3)
    source = rng.normal(size=(37, 3)).astype(np.float32) * [0.05, 0.03, 0.02]
    target = rng.normal(size=(50, 3)).astype(np.float32) * 0.04 + [0.3, -0.1, 0.8]
    problem, opts, (n, m) = prepare(source, target, ICPOptions())
    moved = problem.source  # a step is taken from whatever pose moved the source
    m_pad = problem.target.shape[0]
    line = np.outer(np.linspace(-0.05, 0.05, m), [1.0, 0.5, 0.2]).astype(np.float32)
    problem_line, _, _ = prepare(source, line, ICPOptions())

    index = rng.integers(0, m, moved.shape[0])
    index[::7] = m_pad  # no match: the sentinel one past the last row
    index[3::11] = m  # a grid built on the unpadded target returns m: a padding row
    weight = rng.uniform(0.1, 2.0, moved.shape[0]).astype(np.float32)
    weight[index >= m] = 0.0
    weight[n:] = 0.0  # source padding rows
    weight[5::9] = 0.0  # e.g. a robust kernel's zero weight
    cases = {
        "general": (problem, weight),
        "fewer than 3 pairs": (problem, np.where(np.arange(len(weight)) < 3, weight, 0.0)),
        "no weight": (problem, np.zeros_like(weight)),
        "collinear targets": (problem_line, weight),
    }
    for name, (prob, w) in cases.items():
        index_ = jnp.asarray(index, jnp.int32)
        pairs = Pairs(index_, jnp.asarray(w), jnp.asarray(w > 0), 0, 0, 0.0, 0.0)
        step, degenerate = increment(prob, opts, moved, pairs)
        ref = align(moved, fill_gather(prob.target, index_), w)
        if name == "general":
            np.testing.assert_allclose(
                step.as_matrix(), ref.pose.as_matrix(), atol=2e-6, err_msg=name
            )
        else:  # the minimiser is not unique: the step need only be one of them
            dst = np.asarray(fill_gather(prob.target, index_))

            def cost(pose, dst=dst, w=w):
                used = w > 0  # padding rows lie at float32's largest values
                diff = np.asarray(pose @ moved)[used] - dst[used]
                return float(np.sum(w[used] * np.sum(diff**2, -1)))

            np.testing.assert_allclose(cost(step), cost(ref.pose), rtol=1e-4, atol=1e-7)
        assert bool(degenerate) == bool(ref.degenerate), name
        assert bool(degenerate) == (name != "general"), name


@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
def test_the_loop_calls_no_lapack_kernel(method):
    """jaxlib's batched LAPACK eigh splits a large batch over XLA's intra-op pool and waits
    on a thread of it, which deadlocked a 1,280-start sweep on 2 forced host devices: the
    compiled multi-start loop must contain no LAPACK custom call (jaxreg.geometry.eigen instead)."""
    from jaxreg.registration.solver import ICPOptions, as_pose, prepare, run

    rng = np.random.default_rng(0)
    cloud = rng.uniform(-0.03, 0.03, (64, 3)).astype(np.float32)
    normals = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (64, 1))
    options = ICPOptions(method=method, target_normals=normals, max_iterations=3)
    problem, opts, _ = prepare(cloud, cloud, options)
    inits = as_pose(np.tile(np.eye(4, dtype=np.float32), (4, 1, 1)), jnp.float32)
    many = jax.jit(jax.vmap(run, in_axes=(None, None, 0)))
    hlo = many.lower(problem, opts, inits).compile().as_text()
    assert 'custom_call_target="lapack' not in hlo
