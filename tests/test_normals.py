"""PCA normals: correct and oriented on analytic surfaces, flagged (never NaN) when undefined,
and in agreement with Open3D on a real scan."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxreg.io import load_points
from jaxreg.search.neighbors import build_grid, knn, voxel_downsample
from jaxreg.search.normals import NormalStatus, estimate_normals, estimate_normals_with_curvature

# One compiled function per shape (eager dispatch would compile every primitive instead).
estimate = jax.jit(estimate_normals_with_curvature, static_argnums=1)


def normals_of(points, k=20, viewpoint=None, **kw):
    return estimate(points, k, viewpoint, **kw).normals


def plane_cloud(rng, n=400):
    """A noise-free tilted plane patch 0.5 m in front of a camera at the origin."""
    uv = rng.uniform(-0.05, 0.05, (n, 2))
    normal = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
    e1 = np.cross(normal, [1.0, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    return np.array([0.02, 0.01, 0.5]) + uv[:, :1] * e1 + uv[:, 1:] * e2, normal


def test_plane_normals_face_the_camera(dtype):
    points, normal = plane_cloud(np.random.default_rng(0))
    est = estimate(points.astype(dtype), 12)
    assert est.normals.dtype == dtype and bool(est.valid.all())
    assert bool((est.status == NormalStatus.success).all())
    # The camera at the origin sees the plane's side facing -z: normals point back to it.
    cos = np.asarray(est.normals) @ normal
    np.testing.assert_allclose(cos, -1.0, atol=1e-5)
    assert float(est.curvature.max()) < 1e-5
    np.testing.assert_array_equal(np.asarray(est.num_neighbors), 12)


def test_sphere_normals_are_radial_and_follow_the_viewpoint():
    rng = np.random.default_rng(1)
    d = rng.normal(size=(1500, 3))
    centre = np.array([0.0, 0.1, 0.6])
    radial = d / np.linalg.norm(d, axis=1, keepdims=True)
    points = (centre + 0.08 * radial).astype(np.float32)
    inward = np.asarray(normals_of(points, 15, viewpoint=centre))
    np.testing.assert_allclose((inward * radial).sum(1), -1.0, atol=5e-3)
    outside = centre + [0.0, 0.0, 5.0]  # a far viewpoint: only the rule's sign matters
    normals = np.asarray(normals_of(points, 15, viewpoint=outside))
    assert np.all((normals * (outside - points)).sum(1) >= 0)
    est = estimate(points, 15)
    curvature = np.asarray(est.curvature)
    assert np.all((curvature > 1e-4) & (curvature < 0.05))  # curved, though far from 1/3


def test_masked_and_nan_points_are_flagged_and_do_not_leak():
    rng = np.random.default_rng(2)
    points, _ = plane_cloud(rng, 300)
    points = points.astype(np.float32)
    dirty = points.copy()
    dirty[5] = np.nan
    dirty[7, 2] = np.inf
    mask = np.ones(300, bool)
    mask[[11, 12]] = False
    dirty[11] = [0.0, 0.0, 3.0]  # masked: far off-plane, would wreck neighbours if used
    est = estimate(dirty, 10, mask=mask)
    bad = [5, 7, 11, 12]
    assert np.all(np.isfinite(np.asarray(est.normals))) and np.all(np.isfinite(est.curvature))
    assert np.asarray(est.status == NormalStatus.invalid_point)[bad].all()
    np.testing.assert_array_equal(np.asarray(est.normals)[bad], 0.0)
    keep = np.setdiff1d(np.arange(300), bad)
    clean = normals_of(points[keep], 10)
    np.testing.assert_allclose(np.asarray(est.normals)[keep], np.asarray(clean), atol=1e-5)


def test_degenerate_neighbourhoods_are_flagged_never_nan():
    line = np.c_[np.linspace(0, 0.1, 30), np.zeros(30), np.full(30, 0.5)].astype(np.float32)
    est = estimate(line, 8)
    assert bool((est.status == NormalStatus.degenerate).all()) and not bool(est.valid.any())
    np.testing.assert_array_equal(np.asarray(est.normals), 0.0)
    same = np.tile([[0.1, 0.2, 0.5]], (10, 1)).astype(np.float32)
    est = estimate(same, 5)
    assert bool((est.status == NormalStatus.degenerate).all())
    assert np.all(np.isfinite(np.asarray(est.normals))) and np.all(np.isfinite(est.curvature))
    pair = np.array([[0, 0, 1.0], [0.01, 0, 1.0]], np.float32)
    est = estimate(pair, 5)
    assert bool((est.status == NormalStatus.too_few_neighbors).all())
    np.testing.assert_array_equal(np.asarray(est.num_neighbors), 2)


def test_grid_neighbours_give_the_same_normals():
    points, _ = plane_cloud(np.random.default_rng(3), 500)
    points = points.astype(np.float32)
    grid = build_grid(points, 0.02, k=10, max_depth=1)
    idx, _, ok = knn(points, grid, 10)
    assert bool(ok.all())
    a = normals_of(points, neighbors=(idx, ok))  # k is then unused
    b = normals_of(points, 10)
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)
    with pytest.raises(ValueError, match="neighbors"):
        normals_of(points, neighbors=(idx[:5], ok[:5]))


def test_concrete_clouds_use_host_knn_with_the_same_result():
    rng = np.random.default_rng(5)
    d = rng.normal(size=(800, 3))
    points = np.array([0.0, 0.1, 0.6]) + 0.08 * d / np.linalg.norm(d, axis=1, keepdims=True)
    points[:2] += [0.5, 0.0, 0.0]  # outliers: their neighbours lie beyond the grid's radius
    points = points.astype(np.float32)
    points[7] = np.nan
    mask = np.ones(800, bool)
    mask[[3, 4]] = False
    eager = estimate_normals_with_curvature(points, 12, mask=mask)  # kNN on the host
    traced = estimate(points, 12, mask=mask)  # brute force under jit
    for a, b in zip(jax.tree.leaves(eager), jax.tree.leaves(traced), strict=True):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)
    assert not np.asarray(eager.valid)[[3, 4, 7]].any()


def test_concrete_clouds_compile_no_program():
    """A command line process pays for every JAX program it compiles or loads: the host path
    answers a concrete cloud by compiled host loops, with no JAX program, whatever its size,
    and gives the traced path's normals."""
    compiled = []

    def listen(event, duration, **kwargs):
        if event.endswith("backend_compile_duration"):
            compiled.append(kwargs.get("fun_name"))

    d = np.random.default_rng(6).normal(size=(3170, 3))
    points = 0.08 * d / np.linalg.norm(d, axis=1, keepdims=True)  # float64: converted on the host
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        est = estimate_normals_with_curvature(points, 9, viewpoint=(0.0, 0.0, 5.0))
        first = list(compiled)
        other = estimate_normals_with_curvature(points[:2500], 9, viewpoint=(0.0, 0.0, 5.0))
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert first == [] and compiled == [], compiled
    assert other.normals.shape == (2500, 3) and bool(other.valid.all())
    assert est.normals.dtype == jnp.float32 and bool(est.valid.all())
    reference = estimate(points.astype(np.float32), 9, viewpoint=jnp.array([0.0, 0.0, 5.0]))
    np.testing.assert_allclose(np.asarray(est.normals), np.asarray(reference.normals), atol=1e-5)


def test_concrete_bad_clouds_are_flagged_on_the_host_path():
    nan = np.full((6, 3), np.nan, np.float32)
    est = estimate_normals_with_curvature(nan, 4)
    assert bool((est.status == NormalStatus.invalid_point).all())
    np.testing.assert_array_equal(np.asarray(est.normals), 0.0)
    pair = np.array([[0, 0, 1.0], [0.01, 0, 1.0]], np.float32)  # fewer points than k
    est = estimate_normals_with_curvature(pair, 5)
    assert bool((est.status == NormalStatus.too_few_neighbors).all())
    np.testing.assert_array_equal(np.asarray(est.num_neighbors), 2)
    with pytest.raises(ValueError, match="mask must be"):
        estimate_normals_with_curvature(pair, 5, mask=np.ones(3, bool))


def test_vmap_over_clouds():
    rng = np.random.default_rng(4)
    clouds = np.stack([plane_cloud(rng, 200)[0] for _ in range(3)]).astype(np.float32)
    batched = jax.jit(jax.vmap(lambda p: estimate_normals(p, 8)))(clouds)
    for i in range(3):
        np.testing.assert_allclose(
            np.asarray(batched[i]), np.asarray(normals_of(clouds[i], 8)), atol=1e-6
        )


def test_agrees_with_open3d_on_milk(pcl_dir):
    o3d = pytest.importorskip(
        "open3d", reason="open3d (the `peers` extra) is not importable", exc_type=ImportError
    )
    points = voxel_downsample(load_points(pcl_dir / "milk.pcd"), 0.004)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    cloud.orient_normals_towards_camera_location(np.zeros(3))
    theirs = np.asarray(cloud.normals)
    est = estimate(points, 20)
    ours = np.asarray(est.normals)
    assert bool(est.valid.all())
    cos = (ours * theirs).sum(1)
    assert np.mean(cos > np.cos(np.radians(1.0))) > 0.99  # same axis and same orientation
    assert np.median(cos) > np.cos(np.radians(0.1))


def test_closed_form_eigensolver_matches_eigh_and_differentiates(x64):
    """The closed-form 3x3 solver against LAPACK on random, planar, collinear, isotropic and
    zero matrices; the normal's derivative is the eigenvector perturbation formula, finite
    where the two larger eigenvalues repeat (a round patch of a plane)."""
    from jax.test_util import check_grads

    from jaxreg.geometry.eigen import eigh3
    from jaxreg.search.normals import _smallest_eigenpair

    rng = np.random.default_rng(6)
    rot = np.linalg.qr(rng.normal(size=(4, 3, 3)))[0]
    spectra = [[0.0, 1.0, 2.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]
    m = rng.normal(size=(6, 3, 3))
    a = np.concatenate([m @ m.transpose(0, 2, 1), rot @ (np.array(spectra)[..., None] * rot.mT)])
    six = a[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    evals, vecs = (np.asarray(v) for v in jax.jit(eigh3)(six))
    ref = np.linalg.eigvalsh(a)
    np.testing.assert_allclose(evals, ref, atol=1e-12 * np.abs(ref).max())
    np.testing.assert_allclose(vecs.mT @ vecs, np.broadcast_to(np.eye(3), a.shape), atol=1e-12)
    np.testing.assert_allclose(a @ vecs, vecs * evals[:, None, :], atol=1e-12)
    assert np.all(np.isfinite(vecs))

    @jax.jit  # one program per derivative (eagerly, every primitive compiles on its own)
    def loss(c):
        evals, normal = _smallest_eigenpair(c)
        return jnp.sum(evals**2) + jnp.sum(normal[..., 2] ** 2 + normal[..., 0] * normal[..., 1])

    check_grads(loss, (jnp.asarray(six[:6]),), order=1, modes=["fwd", "rev"])
    disc = jnp.array([[1.0, 0.0, 0.0, 1.0, 0.0, 1e-3]])  # l1 == l2: the normal is still unique
    assert np.all(np.isfinite(np.asarray(jax.grad(loss)(disc))))


def test_host_eigensolver_is_the_closed_form_one(x64):
    """The host loops' per-point solver (`_host_normals`) gives the eigenvalues and the
    smallest eigenvector's axis of `eigh3`, the traced path's, on random, planar, collinear,
    isotropic, zero and nearly planar matrices (a unit vector in the eigenspace where the
    smallest eigenvalue repeats)."""
    from jaxreg.geometry.eigen import eigh3
    from jaxreg.search._host_normals import _eigh3_smallest

    rng = np.random.default_rng(7)
    rot = np.linalg.qr(rng.normal(size=(5, 3, 3)))[0]
    spectra = [[0.0, 1.0, 2.0], [0.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1e-4, 1, 1]]
    m = rng.normal(size=(64, 3, 3))
    a = np.concatenate([m @ m.transpose(0, 2, 1), rot @ (np.array(spectra)[..., None] * rot.mT)])
    six = a[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    evals, vecs = (np.asarray(v) for v in jax.jit(eigh3)(six))
    host = np.array([_eigh3_smallest.py_func(c) for c in six])
    np.testing.assert_allclose(host[:, :3], evals, atol=1e-12 * np.abs(evals).max())
    # The same axis; its sign is arbitrary (a rounding of the cubic's determinant can pick the
    # other branch) until the normal is turned toward the viewpoint.
    repeated = np.isclose(evals[:, 0], evals[:, 1])
    cos = np.abs(np.sum(host[:, 3:] * vecs[:, :, 0], axis=-1))
    np.testing.assert_allclose(cos[~repeated], 1.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(host[:, 3:], axis=-1), 1.0, atol=1e-12)
    assert repeated.sum() == 3  # collinear, isotropic, zero


def test_host_path_equals_the_jax_rules_on_milk(pcl_dir):
    """On a real scan (milk.pcd, in full and at 4 mm voxels) the host path's answer is what
    the jitted rules (`_from_moments`, the traced path's eigen solver, orientation and status)
    give on the same neighbourhood moments: same normals, orientation included, curvature,
    status and counts."""
    from jaxreg.search._knn import knn_moments
    from jaxreg.search.normals import _from_moments

    full = np.asarray(load_points(pcl_dir / "milk.pcd"))
    for points in (np.asarray(voxel_downsample(full, 0.004)), full):
        host = estimate_normals_with_curvature(points, 20)
        cov, count = knn_moments(np.ascontiguousarray(points, np.float64), 20)
        ok = np.ones(len(points), bool)
        rules = jax.jit(_from_moments)(points, ok, cov.astype(points.dtype), count, np.zeros(3))
        assert np.array_equal(host.status._value, rules.status._value)
        np.testing.assert_allclose(np.asarray(host.normals), np.asarray(rules.normals), atol=1e-5)
        np.testing.assert_allclose(host.curvature, rules.curvature, rtol=1e-5, atol=1e-7)
        np.testing.assert_array_equal(host.num_neighbors, rules.num_neighbors)


def test_host_knn_is_exact_with_ties_and_outliers():
    """The host kNN (whose ring searches skip the cells beyond the current k-th distance)
    finds the exact k nearest distances on a lattice full of equal distances, with duplicated
    points and far outliers whose neighbours lie many cells away, with and without a radius."""
    from jaxreg.search._knn import self_knn

    rng = np.random.default_rng(8)
    grid = np.stack(np.meshgrid(*[np.arange(12)] * 2, np.arange(3), indexing="ij"), -1)
    lattice = grid.reshape(-1, 3) * 0.01
    x = np.concatenate([lattice, lattice[:100], rng.normal(size=(30, 3)) + 2.0])
    d2 = np.sum((x[:, None] - x[None]) ** 2, axis=-1)
    for k, radius in ((9, np.inf), (20, np.inf), (20, 0.025)):
        idx, sq = self_knn(x, k, radius)
        expect = np.sort(np.where(d2 < radius**2, d2, np.inf), axis=1)[:, :k]
        np.testing.assert_array_equal(sq, expect)
        found = np.isfinite(sq)
        np.testing.assert_array_equal(
            np.take_along_axis(d2, np.where(found, idx, 0), 1)[found], sq[found]
        )
