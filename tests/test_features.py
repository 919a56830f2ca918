import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxreg.io import load_points
from jaxreg.search.features import fpfh, match_features


@pytest.fixture(scope="module")
def milk_with_normals(pcl_dir):
    """The milk carton scan at a 5 mm voxel with Open3D's normals (the inputs both share)."""
    o3d = pytest.importorskip("open3d", reason="open3d (peers extra, needs libusb) not importable")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(load_points(pcl_dir / "milk.pcd")))
    cloud = cloud.voxel_down_sample(0.005)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.015, max_nn=30))
    return o3d, cloud, np.asarray(cloud.points), np.asarray(cloud.normals)


@pytest.mark.parametrize("max_neighbors", [100, 20])
def test_fpfh_agrees_with_open3d_per_point(milk_with_normals, max_neighbors, x64):
    o3d, cloud, points, normals = milk_with_normals
    radius = 0.025
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_neighbors)
    expected = np.asarray(o3d.pipelines.registration.compute_fpfh_feature(cloud, search).data).T
    result = fpfh(points, normals, radius=radius, max_neighbors=max_neighbors)
    assert result.histograms.shape == expected.shape == (len(points), 33)
    np.testing.assert_allclose(result.histograms, expected, atol=1e-9)
    assert np.all(result.valid)
    # every defined histogram: three sub-histograms of 200 each
    np.testing.assert_allclose(result.histograms.reshape(-1, 3, 11).sum(-1), 200.0, rtol=1e-9)
    # the capped neighbourhoods are flagged (Open3D caps them silently)
    assert np.any(result.overflow) and np.all(result.num_neighbors <= max_neighbors - 1)


def test_fpfh_under_jit_matches_the_host_path(milk_with_normals, x64):
    _, _, points, normals = milk_with_normals
    points, normals = points[:600], normals[:600]
    host = fpfh(points, normals, radius=0.02, max_neighbors=30)
    traced = jax.jit(lambda p, n: fpfh(p, n, radius=0.02, max_neighbors=30))(
        points, normals
    )
    np.testing.assert_allclose(traced.histograms, host.histograms, atol=1e-9)
    np.testing.assert_array_equal(traced.overflow, host.overflow)


def test_fpfh_marks_unusable_points_and_rejects_bad_arguments():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(40, 3)) * 0.01
    normals = np.tile([0.0, 0.0, 1.0], (40, 1))
    normals[3] = 0.0  # undefined normal
    points[4] = np.nan
    points[5] = [1.0, 1.0, 1.0]  # isolated: no neighbour within the radius
    result = fpfh(points, normals, radius=0.05, max_neighbors=50)
    valid = np.asarray(result.valid)
    assert not np.any(valid[[3, 4, 5]]) and np.all(valid[6:])
    assert np.all(np.asarray(result.histograms)[[3, 4, 5]] == 0)
    assert fpfh(points, normals, radius=0.05).histograms.shape == (40, 33)
    with pytest.raises(ValueError, match="radius"):
        fpfh(points, normals, radius=0.0)
    with pytest.raises(ValueError, match="max_neighbors"):
        fpfh(points, normals, radius=0.05, max_neighbors=1)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        fpfh(points, normals[:, :2], radius=0.05)


def test_match_features_agrees_with_a_kd_tree():
    spatial = pytest.importorskip("scipy.spatial", reason="scipy (peers extra) not importable")
    rng = np.random.default_rng(1)
    a = rng.random((300, 33)).astype(np.float32)
    b = rng.random((400, 33)).astype(np.float32)
    a[5] = 0.0  # an undefined descriptor takes no part
    b[7] = np.nan
    valid_a, valid_b = np.arange(300) != 5, np.arange(400) != 7
    rows_b = np.flatnonzero(valid_b)
    dist, nearest = spatial.cKDTree(b[valid_b]).query(a, 2)
    nearest = rows_b[nearest]
    back = np.full(400, -1)
    back[valid_b] = np.flatnonzero(valid_a)[spatial.cKDTree(a[valid_a]).query(b[valid_b])[1]]

    plain = match_features(a, b, mutual=False)
    np.testing.assert_array_equal(plain.mask, valid_a)
    np.testing.assert_array_equal(np.asarray(plain.target_index)[valid_a], nearest[valid_a, 0])
    np.testing.assert_allclose(np.asarray(plain.distance)[valid_a], dist[valid_a, 0], rtol=1e-5)
    assert plain.target_index[5] == 400 and plain.distance[5] == np.inf

    mutual = match_features(a, b)
    expected = valid_a & (back[nearest[:, 0]] == np.arange(300))
    np.testing.assert_array_equal(mutual.mask, expected)
    assert 0 < expected.sum() < 300

    lowe = match_features(a, b, mutual=False, ratio=0.9)
    np.testing.assert_array_equal(lowe.mask, valid_a & (dist[:, 0] < 0.9 * dist[:, 1]))

    none = match_features(a, b, source_mask=np.zeros(300, bool))
    assert not np.any(none.mask)
    with pytest.raises(ValueError, match="same D"):
        match_features(a, b[:, :32])
    with pytest.raises(ValueError, match="ratio"):
        match_features(a, b, ratio=1.5)
    assert jnp.all(jax.jit(match_features)(a, b).mask == mutual.mask)


def test_hybrid_host_search_is_cKDTree_radius_capped_knn():
    """FPFH's neighbourhoods come from the compiled host kNN capped at the radius: the same
    neighbours, in the same order, as cKDTree's k nearest with the ones beyond the radius
    dropped, on a flat cloud where most neighbourhoods are cut by the radius."""
    from scipy.spatial import cKDTree

    from jaxreg.search._knn import self_knn

    x = np.random.default_rng(0).uniform(size=(4000, 3)) * [1.0, 1.0, 0.05]
    idx, sq = self_knn(x, 30, 0.04)
    dist, ref = cKDTree(x).query(x, 30)
    inside = dist < 0.04
    assert 0.2 < inside.mean() < 0.9
    np.testing.assert_array_equal(np.isfinite(sq), inside)
    np.testing.assert_allclose(np.sqrt(sq[inside]), dist[inside], rtol=1e-12)
    np.testing.assert_array_equal(idx[~inside], len(x))


def test_match_features_on_concrete_arrays_is_the_compiled_search_with_exact_ties():
    """Concrete arrays take the k-d tree; under ``jit`` the blocked brute force runs: the same
    matches, distances and masks on descriptors without ties (every filter). On small
    integer descriptors, full of exact ties (three or more rows equally near), the k-d tree
    gives each source row its nearest target row of lowest index, as a float64 reference
    does (the brute force's float32 screen may settle such ties either way)."""
    rng = np.random.default_rng(3)
    a = rng.random((500, 33)).astype(np.float32)
    b = rng.random((3000, 33)).astype(np.float32)
    b[11] = 0.0
    compiled = jax.jit(match_features, static_argnames=("mutual", "ratio"))
    for options in ({}, {"mutual": False}, {"ratio": 0.9}, {"mutual": False, "ratio": 0.9}):
        host, traced = match_features(a, b, **options), compiled(a, b, **options)
        for got, want in zip(jax.tree.leaves(host), jax.tree.leaves(traced), strict=True):
            np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    for _ in range(50):  # counts of one bucket (32 rows): one program serves every draw
        n, m = rng.integers(1, 33, 2)
        a = rng.integers(0, 3, (n, 4)).astype(np.float32)
        b = rng.integers(0, 3, (m, 4)).astype(np.float32)
        usable_a, usable_b = np.any(a != 0, 1), np.any(b != 0, 1)
        d2 = ((a[:, None].astype(np.float64) - b[None]) ** 2).sum(-1)
        d2[:, ~usable_b] = np.inf
        nearest = np.lexsort((np.broadcast_to(np.arange(m), d2.shape), d2), axis=-1)[:, :2]
        lowe = match_features(a, b, mutual=False, ratio=1.0)
        found = usable_a & usable_b.any()
        got = np.asarray(match_features(a, b, mutual=False).target_index)
        np.testing.assert_array_equal(got[found], nearest[found, 0])
        assert np.all(got[~found] == m)
        if m > 1:  # equally near first and second rows fail the ratio test
            ties = d2[np.arange(n), nearest[:, 0]] == d2[np.arange(n), nearest[:, 1]]
            np.testing.assert_array_equal(np.asarray(lowe.mask)[found], ~ties[found])


def test_match_features_compiles_once_for_counts_of_one_bucket():
    """Concrete descriptors are padded to bucketed row counts: clouds of 301 and 310 rows
    against 701 and 690 run the program compiled for 300 against 700 (a long-running process
    meets a few sizes per doubling), and each answer is the unpadded compiled search's."""
    from jaxreg.search.features import _exact_jit

    rng = np.random.default_rng(3)
    match_features(rng.random((300, 33)), rng.random((700, 33)), ratio=0.9)
    compiled = _exact_jit._cache_size()
    for n, m in ((301, 701), (310, 690)):
        a, b = rng.random((n, 33)), rng.random((m, 33))
        found = match_features(a, b, ratio=0.9)
        traced = jax.jit(lambda a, b: match_features(a, b, ratio=0.9))(a, b)
        assert found.target_index.shape == (n,) and int(found.target_index.max()) <= m
        np.testing.assert_array_equal(found.mask, traced.mask)
        np.testing.assert_array_equal(found.target_index, traced.target_index)
    assert _exact_jit._cache_size() == compiled
