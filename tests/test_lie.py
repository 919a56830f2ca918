"""Tests for jaxreg.geometry.lie: group axioms, exp/log, Jacobians, means, sampling, grids, adjoint,
conversions and Open3D's twist order."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from jaxreg.geometry.lie import (
    SE3,
    SO3,
    adjoint_transport,
    covariance_from_open3d,
    covariance_to_open3d,
    geodesic_angle,
    random_rotations,
    rotation_angle,
    rotation_grid,
    rotation_grid_around,
    se3_exp,
    se3_from_matrix,
    se3_to_matrix,
    so3_from_matrix,
    tangent_from_open3d,
    tangent_to_open3d,
)
from jaxreg.geometry.means import chordal_mean, karcher_mean

EXP = {SO3: SO3.exp, SE3: se3_exp}
SHAPES = [(), (1,), (3, 2)]
REGIMES = ["generic", "near_zero", "near_pi"]
ANGLE = {"near_zero": 1e-7, "near_pi": np.pi - 1e-6}

property_test = settings(
    max_examples=6,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
seeds = st.integers(0, 2**31 - 1)


def _tol(dtype) -> float:
    return 2e-5 if dtype == np.float32 else 1e-10


def _rotation_vectors(rng, shape, regime) -> np.ndarray:
    axis = rng.normal(size=(*shape, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    if regime == "generic":
        angle = rng.uniform(0.0, 3.0, size=(*shape, 1))
    else:
        angle = np.full((*shape, 1), ANGLE[regime])
    return axis * angle


def _tangent(group, rng, shape, regime, dtype):
    w = _rotation_vectors(rng, shape, regime)
    if group is SO3:
        return jnp.asarray(w, dtype)
    return jnp.asarray(np.concatenate([rng.normal(size=(*shape, 3)), w], axis=-1), dtype)


def _element(group, rng, shape, dtype, regime="generic"):
    return EXP[group](_tangent(group, rng, shape, regime, dtype))


def _rotation(x):
    return x if isinstance(x, SO3) else x.rotation()


def _assert_same(a, b, atol):
    """Same rotation (any quaternion sign) and, for SE3, same translation."""
    np.testing.assert_array_less(np.asarray(geodesic_angle(_rotation(a), _rotation(b))), atol)
    if isinstance(a, SE3):
        np.testing.assert_allclose(a.translation(), b.translation(), atol=atol)


def _batch_of(x, params):
    return type(x)(params)


# --------------------------------------------------------------------------------------------
# Group axioms and exp / log.


@pytest.mark.parametrize("group", [SO3, SE3])
@property_test
@given(seed=seeds, shape=st.sampled_from(SHAPES))
def test_group_axioms(dtype, group, seed, shape):
    rng = np.random.default_rng(seed)
    a, b, c = (_element(group, rng, shape, dtype) for _ in range(3))
    identity = group.identity(shape)
    tol = 10 * _tol(dtype)
    _assert_same(a @ identity, a, tol)
    _assert_same(identity @ a, a, tol)
    _assert_same(a @ a.inverse(), identity, tol)
    _assert_same(a.inverse() @ a, identity, tol)
    _assert_same((a @ b) @ c, a @ (b @ c), tol)
    assert (a @ b).parameters().dtype == dtype


@pytest.mark.parametrize("group", [SO3, SE3])
@property_test
@given(seed=seeds, shape=st.sampled_from(SHAPES), regime=st.sampled_from(REGIMES))
def test_exp_log_round_trip(dtype, group, seed, shape, regime):
    rng = np.random.default_rng(seed)
    v = _tangent(group, rng, shape, regime, dtype)
    x = EXP[group](v)
    # Near pi, float32 can only place the angle to ~1e-6 (the quaternion's w is ~5e-7).
    tol = (1e-4 if regime == "near_pi" else 2e-5) if dtype == np.float32 else 1e-8
    np.testing.assert_allclose(x.log(), v, atol=tol * max(1.0, float(jnp.abs(v).max())))
    _assert_same(EXP[group](x.log()), x, tol)
    angle = rotation_angle(_rotation(x))
    np.testing.assert_allclose(
        angle, np.linalg.norm(np.asarray(v)[..., -3:], axis=-1), rtol=tol, atol=tol
    )


def _composed_log(v, a, b):
    return (a @ EXP[type(a)](v) @ b).log()


def _angle_to(v, a, b):
    return geodesic_angle(_rotation(a), _rotation(EXP[type(a)](v) @ b))


@jax.jit
def _jacobians(v, a, b):
    """Forward- and reverse-mode Jacobians of both test functions, compiled once per group,
    dtype and shape."""
    return [(jax.jacfwd(f)(v, a, b), jax.jacrev(f)(v, a, b)) for f in (_composed_log, _angle_to)]


@pytest.mark.parametrize("group", [SO3, SE3])
def test_jacobians_forward_reverse_numerical(dtype, group):
    rng = np.random.default_rng(7)
    for regime in REGIMES:
        a, b = _element(group, rng, (), dtype), _element(group, rng, (), dtype)
        v0 = _tangent(group, rng, (), regime, dtype)
        # b^-1 puts the angle's argument near the identity in the "near_zero" regime.
        for f, (forward, reverse) in zip(
            (_composed_log, _angle_to), _jacobians(v0, a, b.inverse()), strict=True
        ):
            assert np.all(np.isfinite(forward)) and np.all(np.isfinite(reverse))
            np.testing.assert_allclose(
                forward, reverse, atol=1e-4 if dtype == np.float32 else 1e-10
            )
            if dtype == np.float64 and not (f is _angle_to and regime == "near_zero"):
                # Central differences; skipped only where the angle's cone point lies within a step.
                h, eye = 1e-6, np.eye(v0.shape[-1])
                numerical = np.stack(
                    [
                        (f(v0 + h * e, a, b.inverse()) - f(v0 - h * e, a, b.inverse())) / (2 * h)
                        for e in eye
                    ],
                    axis=-1,
                )
                np.testing.assert_allclose(forward, numerical, atol=1e-6)


def test_angle_nan_regression_at_exactly_pi_and_zero(dtype):
    half_turn = jnp.array([0.0, 1.0, 0.0, 0.0], dtype)
    identity = jnp.array([1.0, 0.0, 0.0, 0.0], dtype)
    for q in (half_turn, identity):
        grads = [
            jax.grad(lambda q: rotation_angle(SO3(q)))(q),
            jax.jacfwd(lambda q: rotation_angle(SO3(q)))(q),
            jax.grad(lambda q: geodesic_angle(SO3(identity), SO3(q)))(q),
            jax.grad(lambda q: geodesic_angle(SO3(q), SO3(half_turn)))(q),
        ]
        assert all(np.all(np.isfinite(g)) for g in grads)
    assert rotation_angle(SO3(half_turn)) == pytest.approx(np.pi, abs=1e-6)
    assert rotation_angle(SO3(-half_turn)) == pytest.approx(np.pi, abs=1e-6)
    assert rotation_angle(SO3(identity)) == 0.0
    v = jnp.array([np.pi, 0.0, 0.0], dtype)  # exp at exactly pi, then the angle
    g = jax.grad(lambda v: geodesic_angle(SO3.identity(), SO3.exp(v)))(v)
    assert np.all(np.isfinite(g))
    # Away from the ridge the angle grows at unit rate along the rotation axis.
    g = jax.grad(lambda v: rotation_angle(SO3.exp(v)))(jnp.array([2.0, 0.0, 0.0], dtype))
    np.testing.assert_allclose(g, [1.0, 0.0, 0.0], atol=1e-5)


def _series_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 matrix exponential of a twist by its power series, in float64."""
    v, w = xi[:3], xi[3:]
    m = np.zeros((4, 4))
    m[:3, :3] = [[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]
    m[:3, 3] = v
    out, term = np.eye(4), np.eye(4)
    for k in range(1, 40):
        term = term @ m / k
        out = out + term
    return out


@pytest.mark.parametrize("angle", [0.0, 1e-7, 1e-4, 1e-3, 3e-3, 1e-2, 1.0, np.pi - 1e-6])
def test_se3_exp_matches_the_power_series(dtype, angle):
    """Across jaxlie's small-angle branch point (sqrt(1e-5) = 3.2e-3 rad in float32), where
    jaxlie's own SE3.exp is off by angle / 2 relative in translation."""
    rng = np.random.default_rng(int(angle * 1e6))
    axis = rng.normal(size=3)
    xi = np.concatenate([rng.normal(size=3), axis / np.linalg.norm(axis) * angle])
    reference = _series_exp(xi)
    got = se3_to_matrix(se3_exp(jnp.asarray(xi, dtype)))
    np.testing.assert_allclose(got, reference, atol=1e-6 if dtype == np.float32 else 1e-13)
    jacobian = jax.jacfwd(lambda x: se3_exp(x).translation())(jnp.asarray(xi, dtype))
    assert np.all(np.isfinite(jacobian))
    if dtype == np.float64:
        h = 1e-6
        numerical = np.stack(
            [
                (_series_exp(xi + h * e)[:3, 3] - _series_exp(xi - h * e)[:3, 3]) / (2 * h)
                for e in np.eye(6)
            ],
            axis=-1,
        )
        np.testing.assert_allclose(jacobian, numerical, atol=1e-8)


@property_test
@given(seed=seeds, regime=st.sampled_from(REGIMES))
def test_geodesic_angle_is_the_log_norm(dtype, seed, regime):
    rng = np.random.default_rng(seed)
    a = _element(SO3, rng, (4,), dtype)
    w = _tangent(SO3, rng, (4,), regime, dtype)
    b = a @ SO3.exp(w)
    tol = 2e-6 if dtype == np.float32 else 1e-12
    np.testing.assert_allclose(
        geodesic_angle(a, b), jnp.linalg.norm(w, axis=-1), rtol=tol, atol=tol
    )
    np.testing.assert_allclose(geodesic_angle(b, a), geodesic_angle(a, b), atol=tol)
    # Bi-invariance: d(c a, c b) = d(a c, b c) = d(a, b).
    c = _element(SO3, rng, (), dtype)
    np.testing.assert_allclose(geodesic_angle(c @ a, c @ b), geodesic_angle(a, b), atol=10 * tol)
    np.testing.assert_allclose(geodesic_angle(a @ c, b @ c), geodesic_angle(a, b), atol=10 * tol)


# --------------------------------------------------------------------------------------------
# Means.


# Every Karcher call below uses batches of shape (2, 6) or (2, 8) so that the compiled mean and
# its gradient are shared between tests.


def _symmetric_set(group, rng, dtype, spread):
    """`center @ exp(+-d_k)` for three d_k per row: sets whose chordal and Karcher means are
    `center` (batch (2,); the set has batch (2, 6))."""
    center = _element(group, rng, (2,), dtype)
    d = _tangent(group, rng, (2, 3), "generic", dtype) * spread
    d = jnp.concatenate([d, -d], axis=-2)
    return center, _batch_of(center, center.parameters()[:, None, :]) @ EXP[group](d)


def _karcher_loss(x, weights, anchor, probe):
    return jnp.sum(
        probe * (_batch_of(anchor, anchor.parameters()).inverse() @ karcher_mean(x, weights)).log()
    )


_karcher_loss_grad = jax.jit(jax.grad(_karcher_loss, argnums=(0, 1)))


@pytest.mark.parametrize("group", [SO3, SE3])
@property_test
@given(seed=seeds)
def test_means_recover_the_center_of_a_symmetric_set(dtype, group, seed):
    rng = np.random.default_rng(seed)
    center, x = _symmetric_set(group, rng, dtype, spread=0.4)
    weights = jnp.ones((2, 6), dtype)
    tol = 5e-6 if dtype == np.float32 else 1e-10
    mean = karcher_mean(x, weights)
    assert mean.get_batch_axes() == (2,)
    _assert_same(mean, center, tol)
    if group is SO3:
        _assert_same(chordal_mean(x), center, tol)


@pytest.mark.parametrize("group", [SO3, SE3])
def test_zero_weight_ignores_an_element_even_nan_padding(dtype, group):
    rng = np.random.default_rng(3)
    _, x = _symmetric_set(group, rng, dtype, spread=0.6)
    weights = jnp.asarray(rng.uniform(0.5, 2.0, size=(2, 6)), dtype)
    padding = jnp.full((2, 2, x.parameters().shape[-1]), jnp.nan, dtype)
    padded = type(x)(jnp.concatenate([x.parameters(), padding], axis=-2))
    padded_weights = jnp.concatenate([weights, jnp.zeros((2, 2), dtype)], axis=-1)
    tol = 1e-5 if dtype == np.float32 else 1e-10
    _assert_same(karcher_mean(padded, padded_weights), karcher_mean(x, weights), tol)
    if group is SO3:
        _assert_same(chordal_mean(padded, padded_weights), chordal_mean(x, weights), tol)
    anchor, probe = group.identity((2,)), jnp.ones((2, group.tangent_dim), dtype)
    grad_x, grad_w = _karcher_loss_grad(padded, padded_weights, anchor, probe)
    assert np.all(np.isfinite(grad_x.parameters())) and np.all(np.isfinite(grad_w))
    np.testing.assert_array_equal(grad_x.parameters()[:, 6:], 0.0)


@pytest.mark.parametrize("group", [SO3, SE3])
def test_integer_weights_equal_duplication(dtype, group):
    rng = np.random.default_rng(4)
    center = _element(group, rng, (2,), dtype)
    d = _tangent(group, rng, (2, 6), "generic", dtype) * 0.3
    x = _batch_of(center, center.parameters()[:, None, :]) @ EXP[group](d)
    counts = np.array([2, 1, 1, 2, 0, 0])  # expand the first four elements into six
    duplicated = type(x)(jnp.repeat(x.parameters(), counts, axis=1, total_repeat_length=6))
    weights = jnp.broadcast_to(jnp.asarray(counts, dtype), (2, 6))
    ones = jnp.ones((2, 6), dtype)
    tol = 1e-5 if dtype == np.float32 else 1e-10
    _assert_same(karcher_mean(x, weights), karcher_mean(duplicated, ones), tol)
    if group is SO3:
        _assert_same(chordal_mean(x, weights), chordal_mean(duplicated, ones), tol)


@pytest.mark.parametrize("group", [SO3, SE3])
@property_test
@given(seed=seeds)
def test_karcher_fixed_point_and_bi_invariance(dtype, group, seed):
    rng = np.random.default_rng(seed)
    center = _element(group, rng, (2,), dtype)
    d = _tangent(group, rng, (2, 6), "generic", dtype) * 0.3
    x = _batch_of(center, center.parameters()[:, None]) @ EXP[group](d)
    weights = jnp.asarray(rng.uniform(0.1, 1.0, size=(2, 6)), dtype)
    mean = karcher_mean(x, weights)
    residual = ((_batch_of(mean, mean.parameters()[:, None])).inverse() @ x).log()
    residual = jnp.einsum("bk,bkd->bd", weights, residual)
    tol = 2e-5 if dtype == np.float32 else 1e-10
    np.testing.assert_allclose(residual, 0.0, atol=tol)
    a, b = _element(group, rng, (), dtype), _element(group, rng, (), dtype)
    _assert_same(karcher_mean(a @ x @ b, weights), a @ mean @ b, 10 * tol)


def test_se3_karcher_mean_of_a_gaussian_cloud(x64):
    """`M exp(delta)` with delta ~ N(0, diag(0.02 m, 0.1 rad)): the mean is M within the
    standard error (about 5e-4 m and 2.5e-3 rad for 1,600 draws)."""
    rng = np.random.default_rng(5)
    center = _element(SE3, rng, (), np.float64)
    delta = rng.normal(size=(1600, 6)) * np.array([0.02, 0.02, 0.02, 0.1, 0.1, 0.1])
    x = center @ se3_exp(jnp.asarray(delta))
    error = (center.inverse() @ karcher_mean(x)).log()
    np.testing.assert_array_less(np.abs(error), 4 * np.array([5e-4] * 3 + [2.5e-3] * 3))


def test_chordal_mean_is_the_projected_matrix_sum(dtype):
    rng = np.random.default_rng(6)
    x = _element(SO3, rng, (3, 5), dtype)
    weights = jnp.asarray(rng.uniform(0.0, 1.0, size=(3, 5)), dtype)
    # Flip some quaternion signs: the mean must not care.
    flipped = SO3(x.wxyz * jnp.asarray(rng.choice([-1.0, 1.0], size=(3, 5, 1)), dtype))
    summed = jnp.einsum("bk,bkij->bij", weights, x.as_matrix())
    tol = 1e-5 if dtype == np.float32 else 1e-10
    _assert_same(chordal_mean(flipped, weights), so3_from_matrix(summed), tol)
    assert np.all(np.asarray(chordal_mean(x, weights).wxyz[..., 0]) >= 0)


@pytest.mark.parametrize("group", [SO3, SE3])
def test_karcher_gradient_matches_finite_differences(x64, group):
    """Implicit-function-theorem gradient against central differences, in parameter space
    (quaternions are normalised inside, so off-manifold directions are fine)."""
    rng = np.random.default_rng(8)
    center = _element(group, rng, (2,), np.float64)
    d = _tangent(group, rng, (2, 8), "generic", np.float64) * 0.3
    x = _batch_of(center, center.parameters()[:, None]) @ EXP[group](d)
    w = jnp.asarray(rng.uniform(0.2, 1.0, size=(2, 8)))
    probe = jnp.asarray(rng.normal(size=(2, group.tangent_dim)))
    grad_x, grad_w = _karcher_loss_grad(x, w, center, probe)
    h = 1e-6
    for _ in range(3):
        dx, dw = (
            jnp.asarray(rng.normal(size=x.parameters().shape)),
            jnp.asarray(rng.normal(size=w.shape)),
        )
        plus = _karcher_loss(group(x.parameters() + h * dx), w + h * dw, center, probe)
        minus = _karcher_loss(group(x.parameters() - h * dx), w - h * dw, center, probe)
        analytic = jnp.sum(grad_x.parameters() * dx) + jnp.sum(grad_w * dw)
        np.testing.assert_allclose(analytic, (plus - minus) / (2 * h), rtol=1e-6, atol=1e-8)


def test_karcher_at_a_half_turn_and_with_zero_spread(dtype):
    """An element exactly pi from the starting mean (log's branch cut) with a small weight:
    the mean moves off towards it by eps = pi w / (2 + w) and gradients stay finite. A set of
    identical elements (log at its Taylor branch) has finite gradients too."""
    half_turn = jnp.array([0.0, 1.0, 0.0, 0.0], dtype)
    identity = jnp.array([1.0, 0.0, 0.0, 0.0], dtype)
    x = SO3(
        jnp.broadcast_to(jnp.stack([identity, identity, half_turn] + [identity] * 5), (2, 8, 4))
    )
    w = jnp.broadcast_to(jnp.array([1.0, 1.0, 1e-2, 0, 0, 0, 0, 0], dtype), (2, 8))
    mean = karcher_mean(x, w)
    np.testing.assert_allclose(rotation_angle(mean), np.pi * 1e-2 / 2.01, rtol=1e-4)
    np.testing.assert_allclose(jnp.abs(mean.log()[:, 0]), rotation_angle(mean), rtol=1e-5)
    probe = jnp.ones((2, 3), dtype)
    grads = _karcher_loss_grad(x, w, SO3.identity((2,)), probe)
    assert np.all(np.isfinite(grads[0].parameters())) and np.all(np.isfinite(grads[1]))
    same = SE3(jnp.broadcast_to(jnp.array([1.0, 0, 0, 0, 0.1, 0.2, 0.3], dtype), (2, 8, 7)))
    grads = _karcher_loss_grad(
        same, jnp.ones((2, 8), dtype), SE3.identity((2,)), jnp.ones((2, 6), dtype)
    )
    assert np.all(np.isfinite(grads[0].parameters())) and np.all(np.isfinite(grads[1]))
    g = jax.grad(lambda q: chordal_mean(SO3(q)).wxyz.sum())(x.wxyz[0, :2])
    assert np.all(np.isfinite(g))


@pytest.mark.parametrize("group", [SO3, SE3])
def test_non_finite_elements_are_ignored_like_zero_weight(group):
    rng = np.random.default_rng(5)
    _, x = _symmetric_set(group, rng, np.float32, spread=0.6)
    holes = type(x)(x.parameters().at[:, 1].set(jnp.nan))  # weight 1, NaN parameters
    weights = jnp.ones((2, 6)).at[:, 1].set(0.0)
    _assert_same(karcher_mean(holes), karcher_mean(x, weights), 1e-5)
    if group is SO3:
        _assert_same(chordal_mean(holes), chordal_mean(x, weights), 1e-5)


@pytest.mark.parametrize("group", [SO3, SE3])
def test_means_of_sets_with_no_usable_element_raise_or_are_nan_under_jit(group):
    rng = np.random.default_rng(6)
    _, x = _symmetric_set(group, rng, np.float32, spread=0.6)
    weights = jnp.ones((2, 6)).at[1].set(0.0)  # the second set has no positive weight
    all_nan = type(x)(jnp.full_like(x.parameters(), jnp.nan))
    means = [karcher_mean, chordal_mean] if group is SO3 else [karcher_mean]
    for mean in means:
        with pytest.raises(
            ValueError, match=r"1 of 2 averaged sets \(first at batch index \(1,\)\)"
        ):
            mean(x, weights)
        with pytest.raises(ValueError, match="2 of 2 averaged sets"):
            mean(all_nan)
        traced = jax.jit(mean)(x, weights)  # nothing can raise: the empty set's mean is NaN
        assert np.all(np.isnan(traced.parameters()[1]))
        assert np.all(np.isfinite(traced.parameters()[0]))


def test_karcher_mean_stops_at_max_iterations_or_tolerance():
    rng = np.random.default_rng(7)
    _, x = _symmetric_set(SO3, rng, np.float32, spread=1.0)
    x = SO3(x.wxyz.at[:, 0].set(SO3.exp(jnp.array([1.2, 0.0, 0.0])).wxyz))  # asymmetric now
    converged = karcher_mean(x)
    one_step = karcher_mean(x, max_iterations=1)
    loose = karcher_mean(x, tolerance=10.0)  # the first step is already below it
    assert float(geodesic_angle(one_step, converged).max()) > 1e-5
    _assert_same(loose, one_step, 1e-6)


def test_means_reject_unbatched_input():
    with pytest.raises(ValueError, match="last batch axis"):
        karcher_mean(SO3.identity())
    with pytest.raises(ValueError, match="last batch axis"):
        chordal_mean(SO3.identity())
    with pytest.raises(ValueError, match="do not match"):
        chordal_mean(SO3.identity((4,)), jnp.ones(3))
    with pytest.raises(TypeError):
        karcher_mean(jnp.ones((4, 4)))


# --------------------------------------------------------------------------------------------
# Sampling and grids.


def test_random_rotations_are_haar_uniform(dtype):
    n = 20_000
    r = random_rotations(jax.random.PRNGKey(0), n)
    assert r.wxyz.shape == (n, 4) and r.wxyz.dtype == dtype
    np.testing.assert_allclose(jnp.linalg.norm(r.wxyz, axis=-1), 1.0, atol=1e-6)
    # E[R] = 0 under the Haar measure; each entry has standard deviation 1/sqrt(3 n) ~ 0.004.
    np.testing.assert_array_less(np.abs(np.asarray(r.as_matrix()).mean(axis=0)), 0.03)
    # Kolmogorov-Smirnov against the Haar angle law, CDF (theta - sin theta) / pi.
    theta = np.sort(np.asarray(rotation_angle(r), np.float64))
    cdf = (theta - np.sin(theta)) / np.pi
    ks = max(np.max(np.arange(1, n + 1) / n - cdf), np.max(cdf - np.arange(n) / n))
    assert ks < 1.63 / np.sqrt(n)  # the 1% critical value
    # Uniform Euler angles (a classic mistake) fail the same test.
    wrong = SO3.from_rpy_radians(*np.random.default_rng(0).uniform(-np.pi, np.pi, size=(3, n)))
    theta = np.sort(np.asarray(rotation_angle(wrong), np.float64))
    cdf = (theta - np.sin(theta)) / np.pi
    assert max(
        np.max(np.arange(1, n + 1) / n - cdf), np.max(cdf - np.arange(n) / n)
    ) > 1.63 / np.sqrt(n)
    assert random_rotations(jax.random.PRNGKey(1), (2, 3)).get_batch_axes() == (2, 3)


def _covering_radius(grid: np.ndarray, probes: np.ndarray) -> float:
    """max over probes of the angle to the nearest grid rotation (a lower estimate)."""
    closest = np.abs(probes @ grid.T).max(axis=1)
    return float(2 * np.arccos(np.clip(closest.min(), -1.0, 1.0)))


def _uniform_quaternions(rng, n) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def test_rotation_grid_is_unit_distinct_and_covers_better_than_random():
    rng = np.random.default_rng(42)
    probes = _uniform_quaternions(rng, 20_000)
    for n in (1, 7, 24, 100, 300):
        grid = rotation_grid(n)
        assert grid.wxyz.shape == (n, 4)
        np.testing.assert_array_equal(grid.wxyz, rotation_grid(n).wxyz)
        q = np.asarray(grid.wxyz, np.float64)
        np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-6)
        if n > 1:
            overlap = np.abs(q @ q.T) - 2 * np.eye(n)
            separation = 2 * np.arccos(min(overlap.max(), 1.0))
            assert separation > np.radians(5.0)  # distinct even modulo q ~ -q
        if n >= 24:
            grid_radius = _covering_radius(q, probes)
            random_radii = [
                _covering_radius(_uniform_quaternions(rng, n), probes) for _ in range(3)
            ]
            assert grid_radius < min(random_radii)
            assert grid_radius < 2.0 * (6 * np.pi / n) ** (1 / 3)  # within 2x of the ideal bound
    with pytest.raises(ValueError, match="positive integer"):
        rotation_grid(0)
    with jax.enable_x64(True):
        assert rotation_grid(5).wxyz.dtype == np.float64


def test_rotation_grid_around_a_center(dtype):
    centers = SO3(jnp.asarray(_uniform_quaternions(np.random.default_rng(3), 2), dtype))
    max_angle = 0.3
    grid = rotation_grid_around(centers, 50, max_angle)
    assert grid.get_batch_axes() == (2, 50)
    angles = geodesic_angle(SO3(centers.wxyz[:, None]), grid)
    np.testing.assert_array_less(np.asarray(angles), max_angle * (1 + 1e-5))
    np.testing.assert_allclose(angles[:, 0], 0.0, atol=1e-6)
    np.testing.assert_array_equal(grid.wxyz, rotation_grid_around(centers, 50, max_angle).wxyz)
    pairwise = geodesic_angle(SO3(grid.wxyz[0, :, None]), SO3(grid.wxyz[0, None])) + 10 * jnp.eye(
        50
    )
    assert float(pairwise.min()) > 0.02
    jitted = jax.jit(lambda c, a: rotation_grid_around(c, 50, a))(
        centers, jnp.asarray(max_angle, dtype)
    )
    np.testing.assert_allclose(jitted.wxyz, grid.wxyz, atol=1e-6)


# --------------------------------------------------------------------------------------------
# Adjoint transport.


@property_test
@given(seed=seeds, shape=st.sampled_from([(), (3, 2)]), regime=st.sampled_from(REGIMES))
def test_adjoint_moves_a_right_perturbation_to_the_left(dtype, seed, shape, regime):
    rng = np.random.default_rng(seed)
    pose = _element(SE3, rng, shape, dtype)
    delta = _tangent(SE3, rng, shape, regime, dtype)
    ad = pose.adjoint()
    left = jnp.einsum("...ij,...j->...i", ad, delta)
    # Exact identity T exp(d) = exp(Ad_T d) T.
    _assert_same(pose @ se3_exp(delta), se3_exp(left) @ pose, 50 * _tol(dtype))
    root = jnp.asarray(rng.normal(size=(*shape, 6, 6)), dtype)
    cov = root @ jnp.swapaxes(root, -1, -2)
    moved = adjoint_transport(pose, cov)
    back = adjoint_transport(pose.inverse(), moved)
    np.testing.assert_allclose(
        back,
        cov,
        rtol=1e-3 if dtype == np.float32 else 1e-9,
        atol=1e-3 if dtype == np.float32 else 1e-9,
    )


def test_adjoint_transport_is_the_linearised_covariance(x64):
    """Sigma_left = J Sigma J^T with J = d log(T exp(d) T^-1) / dd at 0 (first-order propagation),
    and a Monte Carlo estimate of the left perturbations' covariance agrees."""
    rng = np.random.default_rng(9)
    pose = _element(SE3, rng, (), np.float64)
    root = rng.normal(size=(6, 6)) * 0.05
    cov = jnp.asarray(root @ root.T)
    jac = jax.jacfwd(lambda d: (pose @ se3_exp(d) @ pose.inverse()).log())(jnp.zeros(6))
    np.testing.assert_allclose(adjoint_transport(pose, cov), jac @ cov @ jac.T, atol=1e-12)
    samples = jnp.asarray(rng.multivariate_normal(np.zeros(6), np.asarray(cov), size=20_000))
    left = (pose @ se3_exp(samples) @ pose.inverse()).log()
    empirical = np.cov(np.asarray(left).T)
    moved = np.asarray(adjoint_transport(pose, cov))
    scale = np.sqrt(np.outer(np.diag(moved), np.diag(moved)))
    np.testing.assert_array_less(np.abs(empirical - moved) / scale, 0.05)


# --------------------------------------------------------------------------------------------
# Conversions.


@property_test
@given(seed=seeds, shape=st.sampled_from([(), (3, 2)]))
def test_matrix_round_trips(dtype, seed, shape):
    rng = np.random.default_rng(seed)
    pose = _element(SE3, rng, shape, dtype)
    m = se3_to_matrix(pose)
    assert m.shape == (*shape, 4, 4) and m.dtype == dtype
    np.testing.assert_allclose(m, pose.as_matrix(), atol=1e-6)
    _assert_same(se3_from_matrix(m), pose, 5 * _tol(dtype))
    np.testing.assert_allclose(se3_to_matrix(se3_from_matrix(m)), m, atol=10 * _tol(dtype))


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt


def test_from_matrix_projects_a_drifted_block_to_the_nearest_rotation(dtype):
    rng = np.random.default_rng(10)
    pose = _element(SE3, rng, (8,), np.float64)
    m = np.array(se3_to_matrix(pose), np.float64)
    m[:, :3, :3] += rng.normal(size=(8, 3, 3)) * 0.02  # non-orthonormal
    m[0, :3, :3] = np.diag([1.0, 1.0, -1.0]) + 0.01  # a near-reflection: det < 0
    out = se3_from_matrix(jnp.asarray(m, dtype))
    rotation = np.asarray(out.rotation().as_matrix(), np.float64)
    np.testing.assert_allclose(
        rotation, np.stack([_nearest_rotation(b) for b in m[:, :3, :3]]), atol=1e-5
    )
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-5)
    np.testing.assert_allclose(out.translation(), m[:, :3, 3], atol=1e-6)
    with pytest.raises(ValueError, match=r"\(\.\.\., 4, 4\)"):
        se3_from_matrix(jnp.eye(3))


def test_so3_from_matrix_gradient(dtype):
    for m0 in (jnp.eye(3, dtype=dtype), jnp.diag(jnp.array([1.0, -1.0, -1.0], dtype))):
        g = jax.jacrev(lambda m: so3_from_matrix(m).wxyz)(m0)
        assert np.all(np.isfinite(g))
    if dtype == np.float64:
        rng = np.random.default_rng(11)
        m0 = jnp.asarray(
            np.asarray(SO3.exp(jnp.asarray(rng.normal(size=3))).as_matrix())
            + 0.05 * rng.normal(size=(3, 3))
        )

        def f(m):
            return so3_from_matrix(m).log()

        h, e = 1e-6, jnp.asarray(rng.normal(size=(3, 3)))
        numerical = (f(m0 + h * e) - f(m0 - h * e)) / (2 * h)
        np.testing.assert_allclose(jax.jvp(f, (m0,), (e,))[1], numerical, atol=1e-8)
        np.testing.assert_allclose(jax.jacrev(f)(m0), jax.jacfwd(f)(m0), atol=1e-12)


def test_open3d_order_permutations(dtype):
    rng = np.random.default_rng(12)
    v = jnp.asarray(rng.normal(size=(3, 6)), dtype)
    o3d = tangent_to_open3d(v)
    np.testing.assert_array_equal(o3d[:, :3], v[:, 3:])  # rotation first
    np.testing.assert_array_equal(o3d[:, 3:], v[:, :3])
    np.testing.assert_array_equal(tangent_from_open3d(o3d), v)
    root = jnp.asarray(rng.normal(size=(2, 6, 6)), dtype)
    cov = root @ jnp.swapaxes(root, -1, -2)
    perm = jax.jacfwd(tangent_to_open3d)(jnp.zeros(6, dtype))
    np.testing.assert_allclose(covariance_to_open3d(cov), perm @ cov @ perm.T, atol=1e-5)
    np.testing.assert_array_equal(covariance_from_open3d(covariance_to_open3d(cov)), cov)


def test_open3d_information_matrix_order_and_side(x64):
    """Open3D's `get_information_matrix_from_point_clouds` is J^T J of point-to-point residuals
    for a left perturbation, rows ordered (w, t): equal to our (v, w)-order J^T J permuted with
    `covariance_to_open3d`; the right-perturbation version is `Ad^T I Ad`."""
    o3d = pytest.importorskip(
        "open3d", reason="open3d (the `peers` extra) is not importable", exc_type=ImportError
    )
    rng = np.random.default_rng(13)
    source = rng.uniform(-0.1, 0.1, size=(60, 3))
    pose = se3_exp(jnp.asarray([0.3, -0.2, 0.5, 0.4, -0.7, 0.9]))
    target = np.array(pose @ jnp.asarray(source))

    def cloud(p):
        return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))

    info_o3d = o3d.pipelines.registration.get_information_matrix_from_point_clouds(
        cloud(source), cloud(target), 1e-3, np.array(se3_to_matrix(pose))
    )
    src = jnp.asarray(source)

    def left_residuals(xi):
        return (se3_exp(xi) @ pose @ src - jnp.asarray(target)).ravel()

    def right_residuals(delta):
        return (pose @ se3_exp(delta) @ src - jnp.asarray(target)).ravel()

    j_left = jax.jacfwd(left_residuals)(jnp.zeros(6))
    info_left = j_left.T @ j_left
    np.testing.assert_allclose(covariance_to_open3d(info_left), info_o3d, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(covariance_from_open3d(info_o3d), info_left, rtol=1e-9, atol=1e-9)
    j_right = jax.jacfwd(right_residuals)(jnp.zeros(6))
    ad = pose.adjoint()
    np.testing.assert_allclose(j_right.T @ j_right, ad.T @ info_left @ ad, rtol=1e-9, atol=1e-9)
    # As covariances: inverse information on the right, transported, is the left one.
    cov_right = jnp.linalg.inv(j_right.T @ j_right)
    np.testing.assert_allclose(
        adjoint_transport(pose, cov_right), jnp.linalg.inv(info_left), rtol=1e-6
    )
