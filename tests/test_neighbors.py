"""Nearest neighbours: the grid is exact within max_distance, brute force matches a kd-tree."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jaxreg.io import load_points
from jaxreg.search.neighbors import (
    build_grid,
    knn,
    pad_grid,
    query_nearest,
    radius_search,
    validate_grid,
    voxel_downsample,
)

# Compiled once per shape: eager calls dispatch the unrolled candidate scan op by op, which
# took ~6 s per grid shape (most of the surface test's time after numba's first compile).
nearest = jax.jit(query_nearest)


def brute_nearest(queries, points):
    """float64 numpy reference: index and squared distance of each query's nearest point."""
    d2 = ((queries[:, None, :].astype(np.float64) - points[None].astype(np.float64)) ** 2).sum(-1)
    return d2.argmin(1), d2.min(1)


def surface_cloud(rng, n):
    """Points on two crossing noisy planes and a sphere: edges, gaps, varying density."""
    a = rng.uniform(-0.1, 0.1, (n // 3, 2))
    plane1 = np.c_[a, 0.002 * rng.normal(size=n // 3)]
    plane2 = np.c_[0.002 * rng.normal(size=n // 3), a]
    s = rng.normal(size=(n - 2 * (n // 3), 3))
    sphere = 0.05 * s / np.linalg.norm(s, axis=1, keepdims=True) + [0.05, 0.05, 0.08]
    return np.concatenate([plane1, plane2, sphere]) + [0.1, -0.2, 0.8]


def check_exact(grid, queries, points, r, atol):
    idx, d2, valid = (np.asarray(a) for a in nearest(grid, queries))
    ref_idx, ref_d2 = brute_nearest(queries, points)
    expected = ref_d2 <= r * r
    # Queries within rounding of the radius may fall either way.
    edge = np.abs(np.sqrt(ref_d2) - r) < 1e-5
    assert np.array_equal(valid[~edge], expected[~edge])
    np.testing.assert_allclose(d2[valid], ref_d2[valid], rtol=1e-4, atol=atol)
    assert np.sum(idx[valid] != ref_idx[valid]) <= 0.01 * valid.sum()  # ties aside
    assert np.all(idx[~valid] == len(points)) and np.all(np.isinf(d2[~valid]))
    return valid


def check_distances(grid, queries, points, r):
    """Validity and distances exactly as brute force (no query near the radius); returns
    the grid's and the reference's indices and the validity, for tie-aware checks."""
    idx, d2, valid = (np.asarray(a) for a in nearest(grid, queries))
    ref_idx, ref_d2 = brute_nearest(queries, points)
    assert np.array_equal(valid, ref_d2 <= r * r)
    np.testing.assert_allclose(d2[valid], ref_d2[valid], rtol=1e-4, atol=1e-10)
    return idx, ref_idx, valid


@pytest.mark.parametrize("r", [0.01, 0.03])
def test_grid_nearest_is_exact_on_surfaces(dtype, r):
    rng = np.random.default_rng(0)
    points = surface_cloud(rng, 1500).astype(dtype)
    queries = points[rng.integers(0, len(points), 800)] + rng.normal(0, r / 2, (800, 3))
    queries = queries.astype(dtype)
    grid = build_grid(points, r)
    assert grid.candidate_points.dtype == dtype and not bool(grid.overflow)
    valid = check_exact(grid, queries, points, r, atol=1e-12 if dtype == np.float64 else 1e-9)
    assert 0.3 < valid.mean() < 1.0  # both outcomes are exercised


@settings(max_examples=5, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), r=st.sampled_from([0.05, 0.15, 0.4]))
def test_grid_nearest_is_exact_on_random_clouds(seed, r):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1, 1, (4, 3))
    points = (centres[rng.integers(0, 4, 300)] + rng.normal(0, 0.2, (300, 3))).astype(np.float32)
    near = points[:128] + rng.normal(0, r / 2, (128, 3))
    queries = np.concatenate([near, rng.uniform(-1.5, 1.5, (128, 3))]).astype(np.float32)
    grid = build_grid(points, r, max_depth=3)
    assert check_exact(grid, queries, points, r, atol=1e-7).any()


def test_grid_nearest_on_milk(pcl_dir):
    points = voxel_downsample(load_points(pcl_dir / "milk.pcd"), 0.004)
    rng = np.random.default_rng(1)
    pose_shift = np.array([0.004, -0.003, 0.006], np.float32)  # a nearly aligned ICP source
    queries = points + pose_shift + rng.normal(0, 0.003, points.shape).astype(np.float32)
    grid = build_grid(points, 0.02)
    assert grid.capacity <= 48 and not bool(grid.overflow)
    valid = check_exact(grid, queries, points, 0.02, atol=1e-9)
    assert valid.mean() > 0.95
    # The brute-force engine agrees with the grid.
    _, d2, ok = knn(queries, points, 1, max_distance=0.02)
    _, gd2, gok = nearest(grid, queries)
    assert np.array_equal(np.asarray(ok[:, 0]), np.asarray(gok))
    np.testing.assert_allclose(
        np.asarray(d2[:, 0])[gok], np.asarray(gd2)[gok], rtol=1e-5, atol=1e-10
    )


def test_similar_targets_share_shapes_and_one_compilation(pcl_dir):
    points = voxel_downsample(load_points(pcl_dir / "milk.pcd"), 0.004)
    rng = np.random.default_rng(0)
    a = np.radians(30.0)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    centre = points.mean(0)
    other = ((points - centre) @ rot.T + centre)[rng.random(len(points)) > 0.05]
    other = other.astype(np.float32)  # rotated 30 degrees, 5% of the points dropped
    grids = [build_grid(p, 0.02) for p in (points, other)]
    assert jax.tree.structure(grids[0]) == jax.tree.structure(grids[1])
    leaves = [[(x.shape, x.dtype) for x in jax.tree.leaves(g)] for g in grids]
    assert leaves[0] == leaves[1]
    traces = []

    @jax.jit
    def nearest(grid, queries):
        traces.append(None)  # runs once per trace
        return query_nearest(grid, queries)

    for grid, target in zip(grids, (points, other), strict=True):
        queries = target[:800] + rng.normal(0, 0.004, (800, 3)).astype(np.float32)
        idx, _, valid = nearest(grid, queries)
        check_exact(grid, queries, target, 0.02, atol=1e-9)
        assert np.all(np.asarray(idx)[~np.asarray(valid)] == len(target))  # its own sentinel
    assert len(traces) == 1


def test_deep_refinement_and_duplicate_points_stay_exact():
    rng = np.random.default_rng(11)
    base = surface_cloud(rng, 1200)
    # 30 exact copies of each of 4 points: equidistant candidates no half-space can separate.
    points = np.concatenate([base, np.repeat(base[:4], 30, axis=0)]).astype(np.float32)
    queries = (points[::3] + rng.normal(0, 0.01, (len(points[::3]), 3))).astype(np.float32)
    grid = build_grid(points, 0.03, capacity=40)
    assert grid.depth >= 2 and not bool(grid.overflow)
    idx, ref_idx, valid = check_distances(grid, queries, points, 0.03)
    # Ties among the copies go either way; the point returned is the same.
    np.testing.assert_allclose(points[idx[valid]], points[ref_idx[valid]], atol=1e-6)


@pytest.mark.parametrize("count", [1, 2, 5])
def test_tiny_targets_are_exact(count):
    rng = np.random.default_rng(count)
    points = rng.uniform(0, 0.05, (count, 3)).astype(np.float32)
    queries = (points[rng.integers(0, count, 200)] + rng.normal(0, 0.02, (200, 3))).astype(
        np.float32
    )
    check_exact(build_grid(points, 0.03), queries, points, 0.03, atol=1e-9)


def test_lattice_target_with_points_on_cell_boundaries_is_exact():
    # A 5 mm lattice whose planes coincide with octree cell faces: ties and boundary points.
    axis = np.arange(0.0, 0.08, 0.005)
    points = np.stack(np.meshgrid(axis, axis, [0.0, 0.005]), -1).reshape(-1, 3).astype(np.float32)
    rng = np.random.default_rng(3)
    queries = np.concatenate(
        [points[::7] + rng.normal(0, 0.004, (len(points[::7]), 3)), points[::11]]
    ).astype(np.float32)
    grid = build_grid(points, 0.02, capacity=16)
    assert grid.depth >= 1 and not bool(grid.overflow)
    check_distances(grid, queries, points, 0.02)


def test_nearest_max_distance_tightens_and_is_clipped():
    rng = np.random.default_rng(2)
    points = rng.uniform(0, 1, (400, 3)).astype(np.float32)
    queries = rng.uniform(0, 1, (300, 3)).astype(np.float32)
    grid = build_grid(points, 0.1)
    _, ref_d2 = brute_nearest(queries, points)
    query = jax.jit(query_nearest)  # the radius is traced: one compilation for both
    _, _, valid = query(grid, queries, 0.05)
    assert np.array_equal(np.asarray(valid), ref_d2 <= 0.05**2)
    _, _, valid = query(grid, queries, 10.0)  # clipped to the grid's 0.1
    assert np.array_equal(np.asarray(valid), ref_d2 <= 0.1**2)


def test_overflow_flag_when_capacity_too_small():
    points = surface_cloud(np.random.default_rng(3), 900).astype(np.float32)
    small = build_grid(points, 0.05, capacity=2, max_depth=0)
    assert bool(small.overflow) and small.capacity == 2
    sized = build_grid(points, 0.05, max_depth=0)  # host sizes the capacity: nothing dropped
    assert not bool(sized.overflow) and sized.capacity > 48  # the long-list (argmin) path
    queries = points[::3] + np.random.default_rng(4).normal(0, 0.02, (300, 3)).astype(np.float32)
    check_exact(sized, queries, points, 0.05, atol=1e-9)
    # The truncated grid is inexact somewhere (that is what the flag warns about).
    _, d2, valid = query_nearest(small, queries)
    _, ref_d2 = brute_nearest(queries, points)
    assert np.any(~np.asarray(valid) & (ref_d2 <= 0.05**2)) or np.any(
        np.asarray(d2) > ref_d2 * 1.01
    )


def test_out_of_range_and_non_finite_queries_are_invalid():
    rng = np.random.default_rng(4)
    points = rng.uniform(0, 1, (200, 3)).astype(np.float32)
    grid = build_grid(points, 0.1)
    queries = np.array(
        [[5.0, 5.0, 5.0], [-3.0, 0.5, 0.5], [0.5, 0.5, 1.2], [np.nan, 0.5, 0.5], [0.5, np.inf, 0]],
        np.float32,
    )
    idx, d2, valid = query_nearest(grid, queries)
    assert not np.asarray(valid).any()
    assert np.all(np.asarray(idx) == 200) and np.all(np.isinf(np.asarray(d2)))


def test_vmap_over_query_sets_matches_each_set():
    rng = np.random.default_rng(5)
    points = surface_cloud(rng, 600).astype(np.float32)
    sets = (points[None, :256] + rng.normal(0, 0.01, (6, 256, 3))).astype(np.float32)
    grid = build_grid(points, 0.02)
    batched = jax.jit(jax.vmap(query_nearest, in_axes=(None, 0)))(grid, sets)
    for s in range(len(sets)):
        idx, d2, valid = query_nearest(grid, sets[s])
        np.testing.assert_array_equal(np.asarray(batched[0][s]), np.asarray(idx))
        np.testing.assert_allclose(np.asarray(batched[1][s]), np.asarray(d2), rtol=1e-6)
        np.testing.assert_array_equal(np.asarray(batched[2][s]), np.asarray(valid))


def test_masked_and_non_finite_target_rows_are_never_returned():
    rng = np.random.default_rng(6)
    points = rng.uniform(0, 1, (300, 3)).astype(np.float32)
    points[10] = np.nan
    mask = np.ones(300, bool)
    mask[::3] = False
    queries = points[2::3] + 1e-4  # right next to kept rows and beside masked ones
    grid = build_grid(points, 0.2, mask=mask)
    idx, _, valid = query_nearest(grid, queries)
    keep = np.flatnonzero(mask & np.isfinite(points).all(1))
    ref, _ = brute_nearest(queries, points[keep])
    assert np.asarray(valid).all()
    np.testing.assert_array_equal(np.asarray(idx), keep[ref])
    empty = build_grid(points, 0.2, mask=np.zeros(300, bool))
    idx, _, valid = query_nearest(empty, queries)
    assert not np.asarray(valid).any() and np.all(np.asarray(idx) == 300)


def test_a_padded_grid_answers_as_the_grid_it_pads():
    """pad_grid's tables (cells, leaf map, candidate rows and slots) take the sizes asked
    for, and every query finds the same neighbour at the same distance as before."""
    rng = np.random.default_rng(11)
    points = surface_cloud(rng, 2000).astype(np.float32)
    grid = build_grid(points, 0.02)
    queries = (points[::7] + rng.normal(0, 0.01, (len(points[::7]), 3))).astype(np.float32)
    queries[:20] = rng.uniform(-1, 1, (20, 3))  # outside the grid: invalid either way
    big = pad_grid(grid, cells=4 * grid.cells.shape[0], entries=4 * grid.leaf_map.shape[0],
                   leaves=2 * grid.num_leaves, capacity=grid.capacity + 40)  # fmt: skip
    assert big.cells.shape[0] == 4 * grid.cells.shape[0]
    assert big.leaf_map.shape[0] == 4 * grid.leaf_map.shape[0]
    assert (big.num_leaves, big.capacity) == (2 * grid.num_leaves, grid.capacity + 40)
    assert pad_grid(grid).candidate_index.shape == grid.candidate_index.shape  # no shrinking
    for before, after in zip(nearest(grid, queries), nearest(big, queries), strict=True):
        np.testing.assert_array_equal(np.asarray(before), np.asarray(after))
    valid = np.asarray(nearest(big, queries)[2])
    assert valid.sum() > len(queries) // 2 and not valid[:20].any()


def test_knn_matches_ckdtree(dtype):
    spatial = pytest.importorskip("scipy.spatial")
    rng = np.random.default_rng(7)
    points = surface_cloud(rng, 900).astype(dtype)
    queries = (points[:300] + rng.normal(0, 0.005, (300, 3))).astype(dtype)
    tree = spatial.cKDTree(points.astype(np.float64))
    for k in (1, 8):
        idx, d2, valid = jax.jit(knn, static_argnums=2)(queries, points, k)
        ref_d, ref_i = tree.query(queries.astype(np.float64), k)
        ref_d, ref_i = ref_d.reshape(300, k), ref_i.reshape(300, k)
        assert np.asarray(valid).all() and idx.dtype == jnp.int32
        np.testing.assert_allclose(np.sqrt(np.asarray(d2)), ref_d, rtol=1e-5, atol=1e-9)
        assert np.mean(np.asarray(idx) == ref_i) > 0.99
    # Small blocks give the same answer (blocks only bound memory).
    a = knn(queries, points, 4, block=7)
    b = knn(queries, points, 4)
    np.testing.assert_array_equal(np.asarray(a[0]), np.asarray(b[0]))


def test_knn_pads_missing_neighbours_with_the_sentinel():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [9, 9, 9]], np.float32)
    mask = np.array([True, True, False, True])
    idx, d2, valid = knn(np.zeros((1, 3), np.float32), points, 6, mask=mask, max_distance=2.0)
    np.testing.assert_array_equal(np.asarray(idx[0]), [0, 1, 4, 4, 4, 4])
    np.testing.assert_array_equal(np.asarray(valid[0]), [True, True, False, False, False, False])
    assert np.all(np.isinf(np.asarray(d2[0, 2:])))


@pytest.mark.parametrize("max_depth", [0, 3])  # 3: refined leaves, pruned by the k-th bound
def test_grid_knn_matches_ckdtree_within_radius(max_depth):
    spatial = pytest.importorskip("scipy.spatial")
    rng = np.random.default_rng(8)
    points = surface_cloud(rng, 1500).astype(np.float32)
    queries = (points[:400] + rng.normal(0, 0.004, (400, 3))).astype(np.float32)
    grid = build_grid(points, 0.015, k=6, max_depth=max_depth, capacity=None)
    assert (grid.depth > 0) == (max_depth > 0)
    _, d2, valid = jax.jit(knn, static_argnums=2)(queries, grid, 6)
    ref_d, _ = spatial.cKDTree(points).query(queries, 6, distance_upper_bound=0.015)
    assert np.array_equal(np.asarray(valid), np.isfinite(ref_d))
    ok = np.isfinite(ref_d)
    np.testing.assert_allclose(np.sqrt(np.asarray(d2))[ok], ref_d[ok], rtol=1e-5, atol=1e-9)
    assert (~ok).any() and ok.any()
    with pytest.raises(ValueError, match="built for k <= 6"):
        knn(queries, grid, 7)


@pytest.mark.parametrize("engine", ["brute", "grid", "refined grid"])
def test_radius_search_matches_ckdtree(engine):
    spatial = pytest.importorskip("scipy.spatial")
    rng = np.random.default_rng(9)
    points = surface_cloud(rng, 1200).astype(np.float32)
    queries = (points[:300] + rng.normal(0, 0.003, (300, 3))).astype(np.float32)
    radius, capacity = 0.012, 8
    if engine == "brute":
        idx, d2, mask, overflow = radius_search(queries, points, radius, capacity)
    else:
        grid = build_grid(points, radius, k=None, max_depth=2 if engine == "refined grid" else 0)
        assert (grid.depth > 0) == (engine == "refined grid")
        search = jax.jit(radius_search, static_argnums=3)
        idx, d2, mask, overflow = search(queries, grid, radius, capacity)
    lists = spatial.cKDTree(points).query_ball_point(queries, radius)
    counts = np.array([len(x) for x in lists])
    assert (counts > capacity).any() and (counts <= capacity).any()
    np.testing.assert_array_equal(np.asarray(overflow), counts > capacity)
    idx, mask, d2 = np.asarray(idx), np.asarray(mask), np.asarray(d2)
    for i, expected in enumerate(lists):
        got = idx[i][mask[i]]
        assert np.all(np.diff(d2[i][mask[i]]) >= 0)  # nearest first
        if counts[i] <= capacity:
            assert set(got) == set(expected)
        else:  # the nearest `capacity` are kept
            true_d = np.sort(((points[expected] - queries[i]) ** 2).sum(1))[:capacity]
            np.testing.assert_allclose(np.sort(d2[i]), true_d, rtol=1e-5)
        assert np.all(idx[i][~mask[i]] == len(points))


def test_grid_searches_need_the_right_grid_and_no_point_options():
    points = np.random.default_rng(10).uniform(0, 1, (50, 3))
    pruned = build_grid(points, 0.3)
    with pytest.raises(ValueError, match="k=None"):
        radius_search(points, pruned, 0.3, 8)
    with pytest.raises(ValueError, match="grid holds the points"):
        knn(points, pruned, 1, mask=np.ones(50, bool))
    with pytest.raises(ValueError, match="grid holds the points"):
        radius_search(points, build_grid(points, 0.3, k=None), 0.3, 8, block=8)


def test_build_grid_rejects_bad_input():
    points = np.zeros((10, 3))
    with pytest.raises(ValueError, match="max_distance"):
        build_grid(points, 0.0)
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        build_grid(np.zeros((10, 2)), 0.1)
    with pytest.raises(ValueError, match="capacity"):
        build_grid(points, 0.1, k=4, capacity=2)
    with pytest.raises(ValueError, match="outside jit"):
        jax.jit(lambda p: build_grid(p, 0.1).origin)(points)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        query_nearest(build_grid(points, 0.1), np.zeros((2, 5, 3)))


def test_validate_grid_accepts_the_grid_of_this_target():
    points = surface_cloud(np.random.default_rng(11), 600).astype(np.float32)
    points[5] = np.nan  # a hole: never a candidate, so it never breaks the comparison
    grid = build_grid(points, 0.05)
    validate_grid(grid, points, 0.05)
    validate_grid(grid, points.astype(np.float64), np.array([0.05, 0.02, 0.01]))
    validate_grid(build_grid(np.float64(points), 0.02), points, 0.02)  # 0.02 is not a float32


def test_validate_grid_rejects_a_grid_of_another_target():
    rng = np.random.default_rng(12)
    points = surface_cloud(rng, 600).astype(np.float32)
    grid = build_grid(points, 0.05)
    with pytest.raises(ValueError, match="600 rows, not this one"):
        validate_grid(grid, points[:-1], 0.05)
    moved = points.copy()
    moved[rng.integers(0, 600)] += 1e-3  # same row count, one point moved
    with pytest.raises(ValueError, match="another target"):
        validate_grid(grid, moved, 0.05)
    with pytest.raises(ValueError, match="another target"):
        validate_grid(grid, points[::-1], 0.05)


def test_validate_grid_rejects_a_grid_smaller_than_the_queries():
    points = surface_cloud(np.random.default_rng(13), 600)
    grid = build_grid(points, 0.02)
    with pytest.raises(ValueError, match="max_distance=0.05"):
        validate_grid(grid, points, 0.05)
    with pytest.raises(ValueError, match="queries reach 0.03"):
        validate_grid(grid, points, np.array([0.03, 0.01]))


def test_validate_grid_rejects_an_overflowed_grid():
    points = surface_cloud(np.random.default_rng(14), 900)
    grid = build_grid(points, 0.05, capacity=2, max_depth=0)
    assert bool(grid.overflow)
    with pytest.raises(ValueError, match="overflowed"):
        validate_grid(grid, points, 0.05)


def test_voxel_downsample_centroids():
    points = np.array(
        [[0.0, 0, 0], [0.2, 0, 0], [1.05, 0, 0], [1.15, 0.1, 0], [np.nan, 0, 0]], np.float32
    )
    out = voxel_downsample(points, 0.5)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, [[0.1, 0, 0], [1.1, 0.05, 0]], atol=1e-6)


def test_voxel_downsample_matches_open3d(pcl_dir):
    o3d = pytest.importorskip(
        "open3d", reason="open3d (the `peers` extra) is not importable", exc_type=ImportError
    )
    points = load_points(pcl_dir / "milk.pcd")
    ours = voxel_downsample(points, 0.004)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    theirs = np.asarray(cloud.voxel_down_sample(0.004).points)
    assert len(ours) == len(theirs)
    _, d2, _ = knn(ours, theirs, 1)  # the same centroids, in another order
    assert float(np.sqrt(np.max(d2))) < 1e-6
