import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxreg.camera import Intrinsics, RGBDFrame
from jaxreg.pipeline.segment import (
    SegmentStatus,
    choose_cluster,
    cluster_mask,
    euclidean_clusters,
    fit_plane,
    segment_frame,
)


@pytest.fixture(scope="module")
def scene():
    from jaxreg.synth import tabletop_scene

    return tabletop_scene(0, object="box", distractors=2)


def test_table_plane_and_target_cluster_on_a_rendered_scene(scene):
    seg = segment_frame(scene.frame)
    assert seg.status == SegmentStatus.success
    # the table top is z = 0 in the base frame, its normal +z (toward the camera above it)
    assert float(seg.plane.normal[2]) > np.cos(np.radians(0.5))
    assert abs(float(seg.plane.offset)) < 0.002
    labels = np.asarray(seg.clusters.labels)
    target = scene.mask[:: seg.stride, :: seg.stride]
    counts = np.bincount(labels[target & (labels >= 0)])
    # the target is one cluster that holds most of its grid points and nothing of the others
    k = int(counts.argmax())
    assert counts[k] > 0.7 * target.sum()
    other = scene.labels[:: seg.stride, :: seg.stride][labels == k]
    assert np.mean(other == 1) > 0.95
    assert int(seg.clusters.num_clusters) == 3 and not bool(seg.clusters.overflow)
    # the prompt under the target's centre pixel names that cluster; its mask covers the target
    rows, cols = np.nonzero(scene.mask)
    assert choose_cluster(seg, pixel=(cols.mean(), rows.mean())) == k
    # of the clusters a caller keeps (those of the model's size): none there when k is not
    kept = [j for j in range(int(seg.clusters.num_clusters)) if j != k]
    assert choose_cluster(seg, pixel=(cols.mean(), rows.mean()), among=kept) is None
    mask = cluster_mask(seg, k, scene.mask.shape)
    assert np.mean(mask[scene.mask]) > 0.8
    # several clusters: the union of their masks, and no pixel of a cluster not named
    others = [j for j in range(int(seg.clusters.num_clusters)) if j != k]
    union = cluster_mask(seg, [k, others[0]], scene.mask.shape)
    assert np.array_equal(union, mask | cluster_mask(seg, others[0], scene.mask.shape))
    assert not np.any(union & cluster_mask(seg, others[1], scene.mask.shape))


def test_plane_is_a_function_of_the_key(scene):
    a = segment_frame(scene.frame, key=jax.random.PRNGKey(3))
    b = segment_frame(scene.frame, key=jax.random.PRNGKey(3))
    assert np.array_equal(np.asarray(a.plane.normal), np.asarray(b.plane.normal))
    assert np.array_equal(np.asarray(a.clusters.labels), np.asarray(b.clusters.labels))


def test_fit_plane_ignores_outliers_and_masked_rows():
    rng = np.random.default_rng(0)
    table = np.c_[rng.uniform(-0.5, 0.5, (600, 2)), rng.normal(0, 0.002, 600)]
    clutter = rng.uniform(-0.5, 0.5, (400, 3))
    points = np.concatenate([table, clutter, np.full((50, 3), np.nan)]).astype(np.float32)
    valid = np.all(np.isfinite(points), 1)
    fit = jax.jit(lambda p, v, k: fit_plane(p, v, k, viewpoint=jnp.array([0.0, 0.0, 1.0])))
    plane = fit(jnp.asarray(points), jnp.asarray(valid), jax.random.PRNGKey(0))
    assert float(plane.normal[2]) > 0.999 and abs(float(plane.offset)) < 0.002
    assert 560 <= int(plane.num_inliers) <= 600 + 40  # the table and the clutter within 8 mm


def _grid_with_blobs():
    h, w = 24, 32
    points = np.full((h, w, 3), np.nan, np.float32)
    mask = np.zeros((h, w), bool)
    for r0, c0, size, x in ((2, 2, 6, 0.0), (10, 20, 8, 1.0), (20, 4, 2, 2.0)):
        rr, cc = np.mgrid[r0 : r0 + size, c0 : c0 + size]
        points[rr, cc] = np.stack([x + 0.005 * cc, 0.005 * rr, np.zeros_like(rr)], -1)
        mask[rr, cc] = True
    return jnp.asarray(points), jnp.asarray(mask)


def test_clusters_by_size_with_small_ones_dropped_and_overflow_flagged():
    points, mask = _grid_with_blobs()

    @functools.partial(jax.jit, static_argnames="max_clusters")
    def clusters(points, mask, distance, max_clusters):
        return euclidean_clusters(
            points, mask, distance=distance, max_clusters=max_clusters, min_size=10
        )

    out = clusters(points, mask, 0.012, 4)
    assert np.asarray(out.sizes).tolist() == [64, 36, 0, 0]
    labels = np.asarray(out.labels)
    assert (labels[10:18, 20:28] == 0).all() and (labels[2:8, 2:8] == 1).all()
    assert (labels[20:22, 4:6] == -1).all()  # 4 points < min_size
    assert not bool(out.overflow)
    one = clusters(points, mask, 0.012, 1)
    assert int(one.num_clusters) == 1 and bool(one.overflow)
    # points 5 mm apart are not joined within 4 mm: no component reaches 10 points
    assert int(clusters(points, mask, 0.004, 4).num_clusters) == 0


@pytest.mark.slow
def test_compact_and_whole_grid_propagation_find_the_same_clusters(scene):
    """The masked points alone (capacity above their count) and the whole grid (capacity
    below it) give identical clusters: on the objects (a few hundred points) and on the
    objects with the table (tens of thousands, where ties between equal sizes occur)."""
    from jaxreg.pipeline.segment import grid_points

    seg = segment_frame(scene.frame)
    points = grid_points(scene.frame, seg.stride)
    height = seg.plane.height(points)

    @functools.partial(jax.jit, static_argnames="capacity")
    def clusters(mask, capacity):
        return euclidean_clusters(
            points, mask, distance=0.015, max_clusters=16, min_size=15, capacity=capacity
        )

    for low in (0.01, -0.02):
        mask = (height > low) & (height < 0.5)
        count = int(mask.sum())
        compact, whole = clusters(mask, count + 1), clusters(mask, 17)
        for a, b in zip(jax.tree.leaves(compact), jax.tree.leaves(whole), strict=True):
            assert np.array_equal(np.asarray(a), np.asarray(b))
        assert int(whole.num_clusters) >= 2
    with pytest.raises(ValueError, match="capacity"):
        euclidean_clusters(points, mask, distance=0.015, max_clusters=16, capacity=16)


def _flat_frame(depth):
    intrinsics = Intrinsics(300.0, 300.0, 79.5, 59.5, 160, 120)
    return RGBDFrame(depth, intrinsics)


def test_statuses_name_what_the_frame_lacks():
    holes = segment_frame(_flat_frame(np.full((120, 160), np.nan, np.float32)))
    assert holes.status == SegmentStatus.too_few_points
    wall = segment_frame(_flat_frame(np.full((120, 160), 0.8, np.float32)), min_plane_inliers=50)
    assert wall.status == SegmentStatus.no_clusters
    assert "nothing stands on the table" in wall.status_message()
    rng = np.random.default_rng(0)
    fog = segment_frame(
        _flat_frame(rng.uniform(0.3, 3.0, (120, 160)).astype(np.float32)), min_plane_inliers=400
    )
    assert fog.status == SegmentStatus.no_plane
