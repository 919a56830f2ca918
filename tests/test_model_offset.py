"""The model's plane offset (``_model._plane_offset``): how far its tangent planes miss its own
neighbouring points, the scale of the error budget's mismatch term."""

import numpy as np

from jaxreg.pipeline._error_sources import mismatch_sigma
from jaxreg.pipeline._model import _plane_offset, _prepare_model


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
