"""The register stage's evidence tests (jaxreg.pipeline._evidence) on hand-made geometry: a
surface that runs on past the model's edge against a neighbour's face meeting it at a crease,
and heights against the table judged by the pose's uncertainty."""

from types import SimpleNamespace

import numpy as np
import pytest
from jaxlie import SE3, SO3

import jaxreg as jr
from jaxreg.pipeline._evidence import (
    axis_noise,
    carried_past,
    continuing,
    height_tests,
    z_score,
)
from jaxreg.pipeline._model import _prepare_model
from jaxreg.pipeline.segment import TablePlane
from jaxreg.uncertainty.noise import DepthNoise

IDENTITY = np.array([1.0, 0, 0, 0, 0, 0, 0])
HALF = np.array([0.04, 0.025, 0.06])  # an 80 x 50 x 120 mm box, centred at the origin


def _face_grid(u_range, v_range, step, place):
    """Points ``place(u, v) -> (3,)`` on a ``step`` grid over the two ranges (metres)."""
    u, v = np.meshgrid(np.arange(*u_range, step), np.arange(*v_range, step), indexing="ij")
    return np.stack([place(a, b) for a, b in zip(u.ravel(), v.ravel(), strict=True)])


def _box_surface(step=0.004):
    """Points on the box's six faces (metres)."""
    faces = []
    for axis in range(3):
        others = [k for k in range(3) if k != axis]
        for sign in (-1.0, 1.0):

            def place(a, b, axis=axis, others=others, sign=sign):
                p = np.zeros(3)
                p[axis] = sign * HALF[axis]
                p[others[0]], p[others[1]] = a, b
                return p

            faces.append(
                _face_grid(
                    (-HALF[others[0]], HALF[others[0]] + 1e-9),
                    (-HALF[others[1]], HALF[others[1]] + 1e-9),
                    step,
                    place,
                )
            )
    return np.concatenate(faces).astype(np.float32)


@pytest.fixture(scope="module")
def box():
    return _prepare_model(_box_surface(), None, 0.004, 0.04, 0.015)


def _top(x_range, step=0.004):
    """Points on the plane of the box's top face (z = +60 mm) over ``x_range``, y across it."""
    return _face_grid(
        x_range, (-HALF[1], HALF[1] + 1e-9), step, lambda a, b: np.array([a, b, HALF[2]])
    )


def test_a_face_running_on_past_the_edge_is_counted_and_its_own_points_are_explained(box):
    """The box's top face carried on 30 mm past its +x edge (a longer box): the points beyond
    the 6 mm gate run on; those on the face are explained; none of the face's own points
    runs on."""
    points = _top((-HALF[0], HALF[0] + 0.03))
    allowed = np.full(len(points), 0.003)
    explained, runs_on = continuing(box, IDENTITY, points, 0.006, allowed)
    beyond = points[:, 0] > HALF[0] + 0.006 + 1e-6
    assert not runs_on[points[:, 0] <= HALF[0]].any()
    assert explained[points[:, 0] <= HALF[0]].all()
    assert runs_on[beyond].mean() > 0.8
    assert not explained[beyond].any()


def _wall(x: float):
    """A face in the plane ``x`` (metres) rising from 8 to 50 mm above the box's top."""
    return _face_grid(
        (HALF[2] + 0.008, HALF[2] + 0.05),
        (-HALF[1], HALF[1] + 1e-9),
        0.004,
        lambda a, b: np.array([x, b, a]),
    )


def test_a_neighbour_meeting_the_model_at_a_crease_is_explained_away(box):
    """A face standing on the middle of the box's top (an object on it, the plane x = 0: a
    crease along the top face), and a neighbour's top 30 mm above the box's: neither is the
    model's surface running on, so neither counts against it. A face flush with the box's
    side (x = +40 mm) rising above its top is: depth cannot tell it from a taller box."""
    higher = _top((HALF[0] + 0.002, HALF[0] + 0.04)) + np.array([0.0, 0.0, 0.03])
    for points in (_wall(0.0), higher):
        explained, runs_on = continuing(box, IDENTITY, points, 0.006, np.full(len(points), 0.003))
        assert not runs_on.any()
        assert not explained.any()
    side = _face_grid(
        (0.0, HALF[2] + 1e-9), (-HALF[1], HALF[1] + 1e-9), 0.004,
        lambda a, b: np.array([HALF[0], b, a]),
    )  # fmt: skip
    flush = np.concatenate([side, _wall(HALF[0])])
    _, runs_on = continuing(box, IDENTITY, flush, 0.006, np.full(len(flush), 0.003))
    assert not runs_on[: len(side)].any() and runs_on[len(side) :].mean() > 0.8


def test_heights_are_judged_against_the_poses_uncertainty(box):
    """The box resting on the table z = 0 (its centre 60 mm up) sinks nothing; lowered 20 mm
    it sinks 20 mm, refused with a millimetre's uncertainty, allowed when the pose's height
    is uncertain by 10 mm (3.1 sigma = 31 mm); the points below the model likewise."""
    plane = TablePlane(np.array([0.0, 0.0, 1.0]), np.float32(0.0), np.int32(1000), np.float32(1.0))
    z = z_score(0.001)
    assert z == pytest.approx(3.09, abs=0.01)
    pose = np.eye(4)
    pose[2, 3] = HALF[2]
    tight = np.eye(6) * 1e-6  # 1 mm, 1 mrad
    face = _top((-HALF[0], HALF[0])) - np.array([0, 0, 2 * HALF[2]])  # its bottom, on z = 0
    resting = height_tests(box, plane, pose, tight, face + pose[:3, 3], 0.001, 0.001, z)
    assert abs(resting.sunk) < 1e-3 and resting.sunk <= resting.sunk_allowed
    assert resting.under <= resting.under_allowed
    lowered = pose.copy()
    lowered[2, 3] -= 0.02
    sunk = height_tests(box, plane, lowered, tight, face + pose[:3, 3], 0.001, 0.001, z)
    assert sunk.sunk == pytest.approx(0.02, abs=1e-3) and sunk.sunk > sunk.sunk_allowed
    loose = np.diag([1e-4, 1e-4, 1e-4, 0, 0, 0])  # 10 mm per axis
    allowed = height_tests(box, plane, lowered, loose, face + pose[:3, 3], 0.001, 0.001, z)
    assert allowed.sunk <= allowed.sunk_allowed
    raised = pose.copy()
    raised[2, 3] += 0.02  # the segment's points now reach 20 mm below the model
    under = height_tests(box, plane, raised, tight, face + pose[:3, 3], 0.001, 0.001, z)
    assert under.under == pytest.approx(0.02, abs=1e-3) and under.under > under.under_allowed


def _cuboid(low, high, step=0.004):
    """Points on the six faces of the box from ``low`` to ``high`` ``(3,)`` (metres)."""
    low, high = np.asarray(low, float), np.asarray(high, float)
    faces = []
    for axis in range(3):
        u, v = [k for k in range(3) if k != axis]
        for side in (low[axis], high[axis]):

            def place(a, b, axis=axis, u=u, v=v, side=side):
                p = np.empty(3)
                p[axis], p[u], p[v] = side, a, b
                return p

            faces.append(
                _face_grid((low[u], high[u] + 1e-9), (low[v], high[v] + 1e-9), step, place)
            )
    return np.concatenate(faces)


def test_depth_across_a_concavity_is_explained_away_and_past_the_outline_runs_on():
    """A U of two 20 mm prongs on a bar (a clamp's jaws, 40 mm apart): depth smeared across
    the gap between the prongs, 2 mm behind their front faces (within the 3 mm the faces'
    planes allow, so it would carry them on), lies within the model's convex hull and does not
    make the object larger; the front face carried 30 mm past a prong's outer side does."""
    prongs = [_cuboid((x, -0.01, -0.02), (x + 0.02, 0.01, 0.08)) for x in (-0.04, 0.02)]
    bar = _cuboid((-0.04, -0.01, -0.04), (0.04, 0.01, -0.02))
    u = _prepare_model(np.concatenate([*prongs, bar]).astype(np.float32), None, 0.004, 0.04, 0.015)

    def front(x_range, y):
        return _face_grid(x_range, (0.0, 0.072 + 1e-9), 0.004, lambda a, b: np.array([a, y, b]))

    across = front((-0.02, 0.02 + 1e-9), 0.008)
    explained, runs_on = continuing(u, IDENTITY, across, 0.006, np.full(len(across), 0.003))
    gap = np.abs(across[:, 0]) < 0.014  # farther than the gate from both prongs
    assert not runs_on.any() and not explained[gap].any()
    beside = front((0.04, 0.07 + 1e-9), 0.01)
    explained, runs_on = continuing(u, IDENTITY, beside, 0.006, np.full(len(beside), 0.003))
    past = beside[:, 0] > 0.04 + 0.006 + 1e-6
    assert runs_on[past].mean() > 0.8 and not explained[past].any()


def test_the_span_allows_the_depth_noise_only_along_the_cameras_rays(box):
    """A camera 1 m above the box looking straight down (its rays along the box's 120 mm
    axis, the model's longest): that axis spreads by the structured-light camera's depth
    noise at 1 m (1.9 mm), the two across the view by one pixel's width at 1 m (0.8 mm at
    fx 1200); turned so the camera looks along the 50 mm axis (the shortest), the depth
    noise moves with it."""
    fx = 1200.0
    camera = SE3.from_translation(np.array([0.0, 0.0, 1.0 + HALF[2]])) @ SE3.from_rotation(
        SO3.from_x_radians(np.pi)
    )
    frame = SimpleNamespace(base_T_camera=camera, intrinsics=SimpleNamespace(fx=fx))
    noise = DepthNoise.structured_light(np.array([fx, fx]))
    points = _top((-0.01, 0.01))[:20]
    axial = float(noise.axial_sigma(1.0))
    lateral = 1.0 / fx
    along = axis_noise(frame, box, IDENTITY, points, noise)
    assert np.argmax(np.abs(box.axes[2])) == 0  # the 120 mm axis (z) is the longest
    np.testing.assert_allclose(along, [axial, lateral, lateral], rtol=0.02)
    assert axial > 2 * lateral
    quarter = np.concatenate([SO3.from_x_radians(np.pi / 2).wxyz, np.zeros(3)])
    turned = axis_noise(frame, box, quarter, points, noise)
    np.testing.assert_allclose(turned, [lateral, lateral, axial], rtol=0.02)


def test_a_neighbours_edge_the_masks_border_holds_carries_on_outside_it():
    """A plate 0.8 m from the camera (columns 20-49) and a neighbour flush with it (columns
    50-69) in front of a wall at 1 m; the mask holds the plate and 4 columns of the neighbour.
    Those 4 columns' surface carries on outside the mask; the plate's left edge steps to the
    wall, and a pixel farther inside than the border is not judged."""
    fx, size = 500.0, 80
    depth = np.full((size, size), 1.0)
    depth[10:70, 20:70] = 0.8
    mask = np.zeros((size, size), bool)
    mask[10:70, 20:54] = True
    frame = jr.RGBDFrame(depth, jr.Intrinsics(fx, fx, 40.0, 40.0, size, size))
    noise = DepthNoise.structured_light(np.array([fx, fx]))
    rows, cols = np.full(8, 40), np.array([50, 51, 52, 53, 20, 21, 30, 44])
    z = depth[rows, cols]
    points = np.stack([(cols - 40.0) * z / fx, (rows - 40.0) * z / fx, z], 1)
    carried = carried_past(frame, mask, points, noise, border=5)
    np.testing.assert_array_equal(carried, [True] * 4 + [False] * 4)
    assert not carried_past(frame, mask, points, noise, border=0).any()
