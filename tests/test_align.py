import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jaxreg.geometry.alignment import Alignment, AlignmentStatus, align, kabsch, umeyama

try:
    from scipy.spatial.transform import Rotation
except ImportError:  # scipy is in the `peers` extra
    Rotation = None

BATCH_SHAPES = [(), (1,), (3, 2)]


def random_problem(seed, batch, n=50, noise=0.0, dtype=np.float64):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=batch + (4,))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    r = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
    t = rng.normal(size=batch + (3,))
    src = rng.normal(size=batch + (n, 3)) * np.array([0.05, 0.03, 0.02])
    dst = np.einsum("...ij,...nj->...ni", r, src) + t[..., None, :]
    dst = dst + noise * rng.normal(size=dst.shape)
    return src.astype(dtype), dst.astype(dtype), r, t


@pytest.mark.parametrize("batch", BATCH_SHAPES)
@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31))
def test_recovers_exact_pose_float32(batch, seed):
    src, dst, r, t = random_problem(seed, batch, dtype=np.float32)
    pose = kabsch(src, dst)
    assert pose.get_batch_axes() == batch
    np.testing.assert_allclose(pose.rotation().as_matrix(), r, atol=2e-5)
    np.testing.assert_allclose(pose.translation(), t, atol=2e-5)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31))
def test_recovers_exact_pose_float64(batch, seed):
    with jax.enable_x64(True):
        src, dst, r, t = random_problem(seed, batch)
        result = align(src, dst)
        assert result.pose.wxyz_xyz.dtype == jnp.float64
        np.testing.assert_allclose(result.pose.rotation().as_matrix(), r, atol=1e-11)
        np.testing.assert_allclose(result.pose.translation(), t, atol=1e-11)
        assert np.all(result.rms < 1e-11) and not np.any(result.degenerate)


@pytest.mark.skipif(Rotation is None, reason="scipy (peers extra) not installed")
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31))
def test_agrees_with_scipy_align_vectors_on_weighted_noisy_sets(seed):
    with jax.enable_x64(True):
        src, dst, _, _ = random_problem(seed, (), n=40, noise=0.01)
        w = np.random.default_rng(seed + 1).uniform(0.1, 2.0, 40)
        pose = kabsch(src, dst, w)
        mu_s = w @ src / w.sum()
        mu_d = w @ dst / w.sum()
        ref, _ = Rotation.align_vectors(dst - mu_d, src - mu_s, weights=w)
        np.testing.assert_allclose(pose.rotation().as_matrix(), ref.as_matrix(), atol=1e-9)
        np.testing.assert_allclose(pose.translation(), mu_d - ref.as_matrix() @ mu_s, atol=1e-9)


def test_padded_batch_equals_each_problem_alone():
    sizes = [3, 7, 20, 64]
    problems = [random_problem(i, (), n=n, noise=0.002) for i, n in enumerate(sizes)]
    n_max = max(sizes)
    src = np.full((len(sizes), n_max, 3), np.nan, np.float32)  # padding is garbage, even NaN
    dst = np.full_like(src, 1e6)
    w = np.zeros((len(sizes), n_max), np.float32)
    for i, (s, d, _, _) in enumerate(problems):
        src[i, : len(s)], dst[i, : len(s)], w[i, : len(s)] = s, d, 1.0
    batched = jax.jit(align)(src, dst, w)
    for i, (s, d, _, _) in enumerate(problems):
        alone = align(s.astype(np.float32), d.astype(np.float32))
        np.testing.assert_allclose(batched.pose.as_matrix()[i], alone.pose.as_matrix(), atol=1e-5)
        np.testing.assert_allclose(batched.rms[i], alone.rms, rtol=1e-3, atol=1e-6)
        assert batched.count[i] == len(s)


def test_never_returns_a_reflection():
    src, _, _, _ = random_problem(3, (), n=30)
    mirrored = src * np.array([1.0, 1.0, -1.0])
    pose = kabsch(src, mirrored)
    assert np.linalg.det(np.asarray(pose.rotation().as_matrix())) == pytest.approx(1.0, abs=1e-5)


def test_umeyama_recovers_scale():
    with jax.enable_x64(True):
        src, dst, r, t = random_problem(5, (4,))
        scale = np.array([0.5, 1.0, 2.0, 10.0])
        pose, c = umeyama(src, dst * scale[:, None, None])
        np.testing.assert_allclose(c, scale, rtol=1e-10)
        np.testing.assert_allclose(pose.rotation().as_matrix(), r, atol=1e-10)
        np.testing.assert_allclose(pose.translation(), t * scale[:, None], atol=1e-10)


def test_degeneracy_signals():
    line = np.outer(np.linspace(-1, 1, 10), [0.3, 0.2, 0.1]).astype(np.float32)
    res = align(line, line + 1.0)
    assert bool(res.collinear) and bool(res.degenerate)
    assert np.all(np.isfinite(res.pose.wxyz_xyz))

    src, dst, _, _ = random_problem(1, (), n=10, dtype=np.float32)
    two = np.array([1, 1, 0, 0, 0, 0, 0, 0, 0, 0], np.float32)
    assert bool(align(src, dst, two).degenerate)
    none = align(src, dst, np.zeros(10, np.float32))
    assert bool(none.degenerate) and float(none.weight_sum) == 0.0
    np.testing.assert_array_equal(none.pose.wxyz_xyz, [1, 0, 0, 0, 0, 0, 0])

    plane = src * np.array([1.0, 1.0, 0.0], np.float32)
    res = align(plane, dst)
    assert bool(res.planar) and not bool(res.degenerate)


def test_status_names_what_happened():
    src, dst, _, _ = random_problem(3, (), n=10, dtype=np.float32)
    ok = align(src, dst)
    assert ok.status == AlignmentStatus.success and bool(ok.converged)
    assert int(ok.iterations) == 0

    two = align(src, dst, np.array([1, 1] + [0] * 8, np.float32))
    assert two.status == AlignmentStatus.too_few_correspondences and not bool(two.converged)
    assert "fewer than 3" in two.status_message()

    line = np.outer(np.linspace(-1, 1, 10), [0.3, 0.2, 0.1]).astype(np.float32)
    assert align(line, line + 1.0).status == AlignmentStatus.degenerate

    # A mirror image of a cloud with two equal spreads: Horn's top eigenvalue is repeated,
    # so a whole circle of rotations fits equally well.
    axes = np.concatenate([np.eye(3), -np.eye(3)]) * np.array([3.0, 1.0, 1.0])
    mirrored = axes * np.array([-1.0, 1.0, 1.0])
    amb = align(axes.astype(np.float32), mirrored.astype(np.float32))
    assert amb.status == AlignmentStatus.ambiguous_rotation and not bool(amb.converged)


def test_kabsch_and_umeyama_give_nan_where_no_row_has_weight():
    """No weighted row (all weights zero, or every row NaN) determines no pose: kabsch and
    umeyama, which carry no status, say so with NaN (under jit too), the other problems of the
    batch untouched; align keeps its status and identity."""
    src, dst, r, t = random_problem(6, (3,), n=10, dtype=np.float32)
    weights = np.ones((3, 10), np.float32)
    weights[1] = 0.0
    src[2] = np.nan
    pose = jax.jit(kabsch)(src, dst, weights)
    similarity, scale = jax.jit(umeyama)(src, dst, weights)
    for q in (pose.wxyz_xyz, similarity.wxyz_xyz, scale):
        q = np.asarray(q)
        assert np.all(np.isnan(q[1:])) and np.all(np.isfinite(q[0]))
    np.testing.assert_allclose(pose.rotation().as_matrix()[0], r[0], atol=2e-5)
    flagged = align(src, dst, weights)
    assert all(m.startswith("fewer than 3") for m in flagged.status_message()[1:])
    np.testing.assert_array_equal(flagged.pose.wxyz_xyz[1:], [[1, 0, 0, 0, 0, 0, 0]] * 2)
    g = jax.grad(lambda s: jnp.sum(kabsch(s, dst[0], weights[0]).log()))(src[0])
    assert np.all(np.isfinite(g))


def test_batched_result_indexes_to_one_problem():
    src, dst, _, _ = random_problem(4, (3,), n=10, dtype=np.float32)
    weights = np.ones((3, 10), np.float32)
    weights[1, 2:] = 0.0
    batch = align(src, dst, weights)
    assert batch.batch_shape == (3,)
    one = batch[1]
    assert isinstance(one, Alignment) and one.batch_shape == ()
    assert one.status == AlignmentStatus.too_few_correspondences
    np.testing.assert_array_equal(one.pose.wxyz_xyz, batch.pose.wxyz_xyz[1])
    assert list(batch.status_message()) == [batch[i].status_message() for i in range(3)]
    with pytest.raises(IndexError, match="one problem"):
        one[0]


def test_nan_rows_are_masked_not_propagated():
    src, dst, r, t = random_problem(2, (), n=30, dtype=np.float32)
    holes = src.copy()
    holes[::5] = np.nan
    res = align(holes, dst)
    assert int(res.count) == 24
    np.testing.assert_allclose(res.pose.rotation().as_matrix(), r, atol=2e-5)
    g = jax.grad(lambda s: align(s, dst).pose.translation().sum())(holes)
    assert np.all(np.isfinite(g)) and np.all(g[::5] == 0)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="at least 3"):
        kabsch(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="matched"):
        kabsch(np.zeros((5, 3)), np.zeros((6, 3)))
    with pytest.raises(ValueError, match=r"\(\.\.\., N, 3\)"):
        kabsch(np.zeros((5, 2)), np.zeros((5, 2)))
    with pytest.raises(ValueError, match="weights"):
        kabsch(np.zeros((5, 3)), np.zeros((5, 3)), np.ones(4))


def _fd_jacobian(f, x, eps=1e-6):
    cols = []
    for i in np.ndindex(x.shape):
        e = np.zeros_like(x)
        e[i] = eps
        cols.append((f(x + e) - f(x - e)) / (2 * eps))
    return np.stack(cols, -1).reshape(-1, *x.shape)


@pytest.mark.parametrize("geometry", ["generic", "planar_square", "symmetric_cube"])
def test_gradient_matches_finite_differences(geometry):
    """Well-posed problems, including repeated singular values where the SVD gradient fails."""
    with jax.enable_x64(True):
        rng = np.random.default_rng(0)
        if geometry == "generic":
            src = rng.normal(size=(12, 3))
        elif geometry == "planar_square":
            src = np.array([[1, 1, 0], [1, -1, 0], [-1, 1, 0], [-1, -1, 0.0]]) * 0.02
        else:
            src = np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).reshape(3, -1).T * 0.03
        src = src.astype(np.float64)
        _, _, r, t = random_problem(7, ())
        dst = src @ r.T + t + 1e-3 * rng.normal(size=src.shape)
        w = rng.uniform(0.5, 1.5, len(src))

        # One compiled program for the values, one for both Jacobians (not one per operation).
        tangent = jax.jit(lambda s, ww: kabsch(s, dst, ww).log())
        jac, jac_w = (np.asarray(j) for j in jax.jit(jax.jacrev(tangent, (0, 1)))(src, w))
        assert np.all(np.isfinite(jac))
        np.testing.assert_allclose(
            jac, _fd_jacobian(lambda s: np.asarray(tangent(s, w)), src), rtol=1e-6, atol=1e-7
        )
        np.testing.assert_allclose(
            jac_w,
            _fd_jacobian(lambda ww: np.asarray(tangent(src, ww)), w),
            rtol=1e-6,
            atol=1e-8,
        )


def test_gradient_is_finite_on_exactly_symmetric_noise_free_clouds():
    square = np.array([[1, 1, 0], [1, -1, 0], [-1, 1, 0], [-1, -1, 0.0]], np.float32)
    gradient = jax.jit(jax.grad(lambda s, d: kabsch(s, d).log().sum()))
    for dst in (square, square + 0.5):  # identity relative rotation, repeated singular values
        g = gradient(square, dst)
        assert np.all(np.isfinite(g))
