import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxreg.geometry.kernels import L2, Cauchy, GemanMcClure, Huber, Tukey, Welsch, trim_mask

SCALED = [Huber, Tukey, Cauchy, GemanMcClure, Welsch]
KERNELS = [lambda: L2()] + [lambda cls=cls: cls(0.01) for cls in SCALED]
S = jnp.array([0.0, 1e-8, 2.5e-5, 9.9e-5, 1e-4, 1.01e-4, 4e-4, 1e-2, 1.0])


@pytest.mark.parametrize("make", KERNELS, ids=["L2"] + [c.__name__ for c in SCALED])
def test_weight_is_derivative_of_rho(make):
    k = make()
    grad = jax.vmap(jax.grad(k.rho))(S)
    np.testing.assert_allclose(grad, k.weight(S), rtol=1e-5, atol=1e-7)
    assert np.all(np.isfinite(grad))


@pytest.mark.parametrize("make", KERNELS, ids=["L2"] + [c.__name__ for c in SCALED])
def test_small_residuals_behave_like_least_squares(make):
    k = make()
    s = jnp.array([0.0, 1e-10, 1e-9])
    np.testing.assert_allclose(k.rho(s), s, rtol=1e-3, atol=1e-15)
    np.testing.assert_allclose(k.weight(s), 1.0, rtol=1e-3)


@pytest.mark.parametrize("cls", SCALED)
def test_weights_shrink_with_residual_and_scale_is_a_leaf(cls):
    s = jnp.linspace(0.0, 1e-3, 50)
    w = cls(0.01).weight(s)
    assert np.all(np.diff(np.asarray(w)) <= 1e-7)
    # vmapped over scales, differentiable in the scale
    scales = jnp.array([0.005, 0.01, 0.02])
    ws = jax.vmap(lambda c: cls(c).weight(jnp.float32(2e-4)))(scales)
    assert np.all(np.diff(np.asarray(ws)) >= 0)  # a wider kernel trusts a residual more
    d = jax.grad(lambda c: cls(c).rho(jnp.float32(2e-4)))(jnp.float32(0.01))
    assert np.isfinite(d)


def test_redescending_kernels_ignore_gross_outliers():
    assert float(Tukey(0.01).weight(1e-2)) == 0.0
    assert float(Welsch(0.01).weight(1.0)) < 1e-30
    assert float(Huber(0.01).weight(1.0)) == pytest.approx(0.01)


def test_trim_mask_keeps_the_best_fraction_with_static_shapes():
    s = jnp.array([5.0, 1.0, 3.0, 2.0, 4.0, 0.5, 9.0, 7.0])
    valid = jnp.array([True, True, True, True, True, True, False, True])
    keep = trim_mask(s, 0.5, valid)
    # 7 valid entries -> keep ceil(3.5) = 4: the four smallest valid ones
    np.testing.assert_array_equal(keep, [False, True, True, True, False, True, False, False])
    keep_all = trim_mask(s, 1.0, valid)
    np.testing.assert_array_equal(keep_all, valid)
    batched = jax.vmap(trim_mask, in_axes=(0, None))(jnp.stack([s, -s]), 0.25)
    assert batched.shape == (2, 8) and np.all(batched.sum(1) == 2)
    np.testing.assert_array_equal(
        trim_mask(jnp.array([1.0, jnp.nan, 0.0]), 1.0), [True, False, True]
    )
