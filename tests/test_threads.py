"""The host thread pool and the concurrent run of a batch's lanes in pieces."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxreg.core import _threads


@jax.jit
def _lanes(x):
    """A vmapped computation whose lanes are independent: each row's own answer."""
    return {"sum": jnp.sum(jnp.sin(x), axis=1), "rows": x * 2.0}


@pytest.mark.parametrize("count", [1, 2, 19, 64])
def test_split_lanes_returns_every_lane_in_order(count):
    x = np.random.default_rng(count).normal(size=(count, 5)).astype(np.float32)
    whole = _lanes(x)
    split = _threads.split_lanes(_lanes, x, 2)
    assert split["rows"].shape == (count, 5)
    np.testing.assert_array_equal(np.asarray(split["rows"]), np.asarray(whole["rows"]))
    np.testing.assert_allclose(np.asarray(split["sum"]), np.asarray(whole["sum"]), rtol=1e-6)


def test_pool_work_that_uses_the_pool_runs_inline():
    """A piece that cuts its own work into pieces runs them on its own thread: with both
    pool threads busy, a nested wait would never end."""
    inner = lambda i: _threads.in_pieces(lambda j: (i, j), [(0,), (1,)])  # noqa: E731
    assert _threads.in_pieces(inner, [(0,), (1,)]) == [[(0, 0), (0, 1)], [(1, 0), (1, 1)]]


def test_lanes_are_split_only_on_one_cpu_device():
    assert _threads.lane_pieces(7) == 1  # fewer than 8 lanes a piece
    expected = min(_threads.CORES, 8) if len(jax.local_devices()) == 1 else 1
    assert _threads.lane_pieces(64) == expected


def test_multistart_in_pieces_answers_as_each_start_alone():
    """16 starts (two pieces of 8 on a 2-core host): each start's pose, status and
    correspondences are those of ICP from that start alone."""
    import jaxreg as jr

    rng = np.random.default_rng(0)
    model = rng.uniform(-0.03, 0.03, (800, 3)).astype(np.float32)
    truth = jr.SE3.from_rotation_and_translation(
        jr.SO3.from_z_radians(0.3), jnp.array([0.01, -0.02, 0.005])
    )
    scene = (np.asarray(truth @ model) + rng.normal(0, 0.002, model.shape)).astype(np.float32)
    inits = jr.rotation_inits(model, scene, 16, around=jr.SE3.identity(), max_angle=0.6)
    many = jr.multistart_icp(model, scene, inits, max_correspondence_distance=0.02)
    for i in range(16):
        alone = jr.icp(model, scene, jr.SE3(inits.wxyz_xyz[i]), max_correspondence_distance=0.02)
        assert many[i].status == alone.status
        np.testing.assert_array_equal(many.correspondences[i], alone.correspondences)
        np.testing.assert_allclose(many.pose.wxyz_xyz[i], alone.pose.wxyz_xyz, atol=1e-5)
