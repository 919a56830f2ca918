import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3

from jaxreg.geometry.alignment import AlignmentStatus, align, kabsch
from jaxreg.geometry.metrics import pose_error
from jaxreg.registration.robust import RobustStatus, robust_kabsch

TRUTH = SE3.from_rotation_and_translation(
    SO3.from_rpy_radians(2.0, -0.7, 1.2), jnp.array([0.4, -0.3, 0.9])
)


def correspondences(outliers, n=200, seed=0):
    """20 cm clouds matched under TRUTH with 1 mm noise; an ``outliers`` fraction of the
    targets replaced by points drawn from the same volume (the hardest place for them)."""
    rng = np.random.default_rng(seed)
    source = rng.uniform(-0.1, 0.1, (n, 3))
    target = np.asarray(TRUTH.apply(jnp.asarray(source, jnp.float32)))
    target = target + rng.normal(0, 0.001, (n, 3))
    wrong = rng.random(n) < outliers
    target[wrong] = rng.uniform(-0.1, 0.1, (wrong.sum(), 3)) + np.array([0.4, -0.3, 0.9])
    return source.astype(np.float32), target.astype(np.float32), ~wrong


@pytest.mark.parametrize("outliers", [0.5, 0.8, 0.9])
def test_recovers_the_pose_among_outliers(outliers):
    source, target, good = correspondences(outliers, seed=int(outliers * 10))
    result = robust_kabsch(source, target, noise_bound=0.005)
    assert result.status == RobustStatus.success and bool(result.converged)
    t_err, r_err = pose_error(result.pose, TRUTH)
    assert float(t_err) < 0.001 and float(r_err) < np.deg2rad(0.5)
    np.testing.assert_array_equal(result.inliers, good)
    # plain least squares is far off on the same set
    assert float(pose_error(kabsch(source, target), TRUTH)[0]) > 0.003


def test_gradient_at_the_solution_is_kabsch_on_the_inliers():
    source, target, good = correspondences(0.5, n=60, seed=2)

    def robust_translation(t):
        return robust_kabsch(source, t, noise_bound=0.005).pose.translation().sum()

    def inlier_translation(t):
        return kabsch(source, t, weights=good.astype(np.float32)).translation().sum()

    # Compiled gradients: eagerly, every primitive of the backward passes compiles on its own.
    grad = jax.jit(jax.grad(robust_translation))(jnp.asarray(target))
    expected = jax.jit(jax.grad(inlier_translation))(jnp.asarray(target))
    np.testing.assert_allclose(grad, expected, atol=1e-5)
    assert np.all(np.asarray(grad)[~good] == 0) and np.any(np.asarray(grad)[good] != 0)


def test_all_outliers_and_padding_give_a_status_not_a_pose():
    rng = np.random.default_rng(3)
    source = rng.uniform(-0.1, 0.1, (200, 3)).astype(np.float32)
    target = rng.uniform(-0.1, 0.1, (200, 3)).astype(np.float32)
    result = robust_kabsch(source, target, noise_bound=0.005)
    assert result.status == RobustStatus.too_few_inliers and not bool(result.converged)
    np.testing.assert_array_equal(result.pose.wxyz_xyz, SE3.identity().wxyz_xyz)
    assert int(result.num_inliers) == 0 and not np.any(result.inliers)

    source, target, good = correspondences(0.5, n=60, seed=4)
    target[0] = np.nan
    masked = robust_kabsch(source, target, noise_bound=0.005, weights=good.astype(np.float32))
    assert masked.status == RobustStatus.success and not bool(masked.inliers[0])
    with pytest.raises(ValueError, match="noise_bound"):
        robust_kabsch(source, target, noise_bound=0.0)


def test_a_reflected_set_reports_the_ambiguous_rotation_align_reports():
    """A mirror image of a cloud with two equal spreads, every pair within a noise bound
    wider than the cloud: no rotation fits better than a whole circle of others, so the
    status is align's ambiguous_rotation, not success."""
    axes = np.concatenate([np.eye(3), -np.eye(3)] * 2) * np.array([0.03, 0.01, 0.01])
    mirrored = axes * np.array([-1.0, 1.0, 1.0])
    source, target = axes.astype(np.float32), mirrored.astype(np.float32)
    assert align(source, target).status == AlignmentStatus.ambiguous_rotation
    result = robust_kabsch(source, target, noise_bound=0.1)
    assert int(result.num_inliers) == 12
    assert "not unique" in result.status_message() and not bool(result.converged)
    assert result.status == RobustStatus.ambiguous_rotation
