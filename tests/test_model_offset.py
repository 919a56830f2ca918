"""Measures of a prepared model: its plane offset (``_model._plane_offset``: how far its tangent
planes miss its own neighbouring points, the scale of the error budget's mismatch term) and its
self-misfits (``_model._self_misfits``: how far it lies from itself turned about each principal
axis by each probe's angle)."""

import numpy as np

import jaxreg as jr
from jaxreg.pipeline._error_sources import mismatch_sigma
from jaxreg.pipeline._model import (
    PROBE_ANGLES_DEG,
    _plane_offset,
    _prepare_model,
    _self_misfits,
)


def _sphere(count: int, radius: float):
    """``count`` points spread evenly on a sphere (a Fibonacci lattice) and their normals."""
    k = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * k / count)
    azimuth = np.pi * (1 + 5**0.5) * k
    normals = np.stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1
    )
    return radius * normals, normals


def test_a_flat_model_has_no_offset():
    u, v = np.meshgrid(np.linspace(0, 0.1, 30), np.linspace(0, 0.08, 25))
    points = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], 1)
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    assert _plane_offset(points, normals) < 1e-12


def test_a_sphere_offsets_by_its_curvature_over_the_spacing():
    """A neighbour ``d`` away on a sphere of radius ``R`` lies ``d^2 / 2R`` off the plane."""
    radius = 0.05
    for count in (500, 2000):
        points, normals = _sphere(count, radius)
        spacing = np.sqrt(4 * np.pi * radius**2 / count)
        expected = spacing**2 / (2 * radius)
        assert 0.7 * expected < _plane_offset(points, normals) < 1.3 * expected, count
    coarse, fine = (_plane_offset(*_sphere(count, radius)) for count in (500, 2000))
    assert fine < 0.3 * coarse  # four times the points: a quarter of the offset


def test_the_mismatch_term_is_the_prepared_models_offset():
    points, normals = _sphere(4000, 0.05)
    model = _prepare_model(
        points.astype(np.float32), normals.astype(np.float32), 0.004, 0.04, 0.015
    )
    assert mismatch_sigma(model) == model.plane_offset
    usable = np.linalg.norm(model.normals, axis=1) > 0.5
    offset = _plane_offset(model.points[usable], model.normals[usable])
    assert abs(model.plane_offset - offset) < 1e-9
    assert 0 < model.plane_offset < 0.001


def test_a_box_matches_itself_half_turned_a_can_spun_and_a_handle_does_not():
    """A box sampled unevenly (its + faces three times denser) lies within its sampling of
    itself turned half round each principal axis, and a can of itself spun by any angle about
    its axis; the mug's handle moves a centimetre or more under the half turns that carry it
    across."""
    half_turn = PROBE_ANGLES_DEG.index(180.0)
    rng = np.random.default_rng(0)
    half = np.array([0.045, 0.038, 0.015])
    faces = []
    for axis in range(3):
        for side, count in ((-1, 1500), (1, 4500)):
            face = rng.uniform(-half, half, (count, 3))
            face[:, axis] = side * half[axis]
            faces.append(face)
    box = np.concatenate(faces) + [0.2, -0.1, 0.05]
    model = _prepare_model(box.astype(np.float32), None, 0.004, 0.04, 0.015)
    rms, _ = model.sampling
    assert model.self_misfits.shape == (3, len(PROBE_ANGLES_DEG))
    assert np.all(model.self_misfits[:, half_turn] < 1.5 * rms), (model.self_misfits, rms)
    assert np.all(model.self_misfits[:, 2] > 2 * rms)  # its quarter turns swap unequal faces
    # about a point 5 mm off the box's centre, the turned box misses itself by about 1 cm
    points = model.points[np.all(np.isfinite(model.points), axis=1)]
    off = _self_misfits(points, model.centre + [0.0, 0.0, 0.005], model.axes)[:, half_turn]
    assert np.sort(off)[-2] > 0.006, off

    can = jr.synth.surface_points(jr.synth.object_mesh("cylinder")[0])
    model = _prepare_model(np.asarray(can, np.float32), None, 0.004, 0.04, 0.015)
    spin = int(np.argmin(model.self_misfits.max(axis=1)))  # the can's axis
    assert model.self_misfits[spin].max() < 1.5 * model.sampling[0], model.self_misfits

    mug = jr.synth.surface_points(jr.synth.object_mesh("mug")[0])
    model = _prepare_model(np.asarray(mug, np.float32), None, 0.004, 0.04, 0.015)
    assert np.sort(model.self_misfits[:, half_turn])[-2] > 0.008, model.self_misfits
