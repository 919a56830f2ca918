import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3

from jaxreg.geometry.lie import geodesic_angle
from jaxreg.geometry.metrics import (
    Symmetry,
    add,
    add_s,
    canonicalise,
    diameter,
    pose_error,
    rotation_error,
)

HALF_X = np.diag([1.0, -1.0, -1.0])
HALF_Y = np.diag([-1.0, 1.0, -1.0])
HALF_Z = np.diag([-1.0, -1.0, 1.0])
BOX = Symmetry(np.stack([np.eye(3), HALF_X, HALF_Y, HALF_Z]))
CYLINDER = Symmetry(np.stack([np.eye(3), HALF_X]), axis=np.array([0.0, 0.0, 1.0]))


def box_points(n=24):
    """Points on a regular grid over the faces of an 80 x 50 x 120 mm box (centred)."""
    half = np.array([0.04, 0.025, 0.06])
    u = (np.arange(n) + 0.5) / n * 2 - 1
    a, b = (g.ravel() for g in np.meshgrid(u, u))
    faces = []
    for axis in range(3):
        i, j = [k for k in range(3) if k != axis]
        for sign in (-1.0, 1.0):
            p = np.zeros((a.size, 3))
            p[:, axis], p[:, i], p[:, j] = sign * half[axis], a * half[i], b * half[j]
            faces.append(p)
    return np.concatenate(faces)


def cylinder_points(sections=90, rings=20):
    """A 70 mm diameter, 120 mm tall side wall sampled every 4 degrees around z."""
    angle = 2 * np.pi * np.arange(sections) / sections
    z = np.linspace(-0.06, 0.06, rings)
    a, zz = (g.ravel() for g in np.meshgrid(angle, z))
    return np.stack([0.035 * np.cos(a), 0.035 * np.sin(a), zz], -1)


TRUTH = SE3.from_rotation_and_translation(
    SO3.from_rpy_radians(0.4, -0.3, 1.1), jnp.array([0.3, -0.1, 0.8])
)


def turned(rotation: np.ndarray) -> SE3:
    return TRUTH @ SE3.from_rotation(SO3.from_matrix(jnp.asarray(rotation, jnp.float32)))


@jax.jit
def scores(points, rotation, symmetry):
    """ADD-S, ADD, ADD with ``symmetry``, and the rotation error without and with it, of the
    estimate ``turned(rotation)``: one compiled program serves every rotation of a test."""
    est = TRUTH @ SE3.from_rotation(SO3.from_matrix(rotation))
    return (
        add_s(points, est, TRUTH),
        add(points, est, TRUTH),
        add(points, est, TRUTH, symmetry=symmetry),
        rotation_error(est, TRUTH),
        rotation_error(est, TRUTH, symmetry),
    )


def test_add_s_forgives_box_flips_and_add_does_not():
    points = box_points()
    for flip in (HALF_X, HALF_Y, HALF_Z):
        add_s_, add_, add_sym, rot, rot_sym = (float(x) for x in scores(points, flip, BOX))
        assert add_s_ < 1e-6
        assert add_ > 0.03
        assert add_sym < 1e-6
        assert rot == pytest.approx(np.pi, abs=1e-3)
        assert rot_sym < 1e-3
    # a quarter turn about z is not a symmetry of a 80 x 50 box: ADD-S sees it
    quarter = np.asarray(SO3.from_z_radians(np.pi / 2).as_matrix())
    assert float(scores(points, quarter, BOX)[0]) > 0.005


def test_add_s_forgives_a_cylinder_turn_about_its_axis_and_add_does_not():
    points = cylinder_points()
    for angle in (np.deg2rad(36.0), 2.0):  # on the sampling lattice, and between its samples
        rotation = np.asarray(SO3.from_z_radians(angle).as_matrix()) @ HALF_X
        add_s_, add_, add_sym = (float(x) for x in scores(points, rotation, CYLINDER)[:3])
        assert add_ > 0.02
        assert add_s_ < 0.0013  # under half the 2.4 mm spacing
        assert add_sym < 1e-5
    tilted = np.asarray(SO3.from_x_radians(0.3).as_matrix())
    assert float(scores(points, tilted, CYLINDER)[0]) > 0.005


def test_canonicalise_is_exact_on_the_axis_and_beats_every_discretised_turn():
    key = jax.random.PRNGKey(0)
    rotations = SO3.sample_uniform(key, batch_axes=(64,))
    poses = SE3.from_rotation_and_translation(rotations, jnp.zeros((64, 3)))
    reference = SE3.identity()
    steps = CYLINDER.transforms(steps=720)  # quarter-degree turns

    @jax.jit  # one program, not one per operation
    def compare(poses, steps, points):
        canon = canonicalise(poses, reference, CYLINDER)
        exact = geodesic_angle(canon.rotation(), reference.rotation())
        candidates = SE3(poses.wxyz_xyz[:, None]) @ SE3(steps.wxyz_xyz[None])
        sampled = geodesic_angle(candidates.rotation(), reference.rotation()).min(axis=1)
        return canon, exact, sampled, add_s(points, canon, poses)

    canon, exact, sampled, moved = compare(poses, steps, cylinder_points())
    assert np.all(exact <= sampled + 1e-5)
    assert np.all(sampled - exact < np.deg2rad(0.25))
    # canonicalising leaves the translation and the fitted surface alone
    np.testing.assert_allclose(canon.translation(), poses.translation())
    assert float(jnp.max(moved)) < 0.0013


def test_pose_error_broadcasts_and_has_finite_gradients_at_the_truth():
    est = SE3(jnp.stack([TRUTH.wxyz_xyz] * 3))
    shifted = SE3.from_translation(jnp.array([0.003, 0.0, -0.004])) @ est
    t_err, r_err = jax.jit(pose_error)(shifted, TRUTH, symmetry=CYLINDER)
    assert t_err.shape == r_err.shape == (3,)
    np.testing.assert_allclose(t_err, 0.005, rtol=1e-4)
    np.testing.assert_allclose(r_err, 0.0, atol=1e-3)

    def total(tangent):
        pose = TRUTH @ SE3.exp(tangent)
        t, r = pose_error(pose, TRUTH, symmetry=CYLINDER)
        return t + r + add(box_points(4), pose, TRUTH) + add_s(box_points(4), pose, TRUTH)

    grad = jax.jit(jax.grad(total))(jnp.zeros(6))
    assert np.all(np.isfinite(grad))


def test_symmetry_discretises_on_request_and_rejects_bad_descriptions():
    assert not Symmetry(np.eye(3)[None]).is_symmetric
    assert CYLINDER.is_symmetric and BOX.is_symmetric
    turns = CYLINDER.discretised(4)
    assert turns.axis is None and turns.rotations.shape == (8, 3, 3)
    np.testing.assert_allclose(turns.rotations[0], np.eye(3))
    np.testing.assert_allclose(
        turns.rotations[1], SO3.from_z_radians(np.pi / 2).as_matrix(), atol=1e-12
    )
    assert BOX.transforms().get_batch_axes() == (4,)
    with pytest.raises(ValueError, match="pass steps"):
        CYLINDER.transforms()
    with pytest.raises(ValueError, match="identity"):
        Symmetry(np.stack([HALF_X, np.eye(3)]))
    with pytest.raises(ValueError, match="proper rotation"):
        Symmetry(np.stack([np.eye(3), np.diag([1.0, 1.0, -1.0])]))
    with pytest.raises(ValueError, match="unit"):
        Symmetry(np.eye(3)[None], axis=np.array([0.0, 0.0, 2.0]))
    with pytest.raises(ValueError, match="model_points"):
        add(np.zeros((5, 2)), TRUTH, TRUTH)


def test_diameter_is_the_largest_pairwise_distance():
    """Over the hull, over every point when the hull is flat (in blocks past 512 rows), 0 for
    fewer than two points: brute force's answer on a box's faces and random clouds."""
    rng = np.random.default_rng(0)
    flat = np.c_[rng.normal(size=(700, 2)), np.zeros(700)]
    for cloud in (box_points(), rng.normal(size=(300, 3)), flat):
        brute = np.sqrt(((cloud[:, None] - cloud[None]) ** 2).sum(-1).max())
        assert diameter(cloud) == pytest.approx(brute, rel=1e-12)
    assert diameter(np.zeros((1, 3))) == 0.0 and diameter(np.zeros((0, 3))) == 0.0
