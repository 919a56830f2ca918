"""ICP's options as one type: ``options=ICPOptions(...)`` and the keyword form run the same
registration, keywords replace fields of ``options``, and a keyword that is no option is
refused by name."""

import dataclasses

import jax
import numpy as np
import pytest

import jaxreg
from jaxreg.geometry.kernels import Tukey
from jaxreg.registration.icp import (
    ICPOptions,
    icp,
    icp_covariance,
    init_spread,
    multistart_icp,
    rotation_inits,
)
from jaxreg.search.neighbors import build_grid
from jaxreg.search.normals import estimate_normals
from jaxreg.studies import lesson_cube


@pytest.fixture(scope="module")
def clouds():
    model, scene, truth = lesson_cube(n=300)
    return model, scene, truth


@pytest.fixture(scope="module")
def every_option(clouds):
    """A value other than the default for each of ICP's options, as keywords."""
    model, scene, _ = clouds
    weights = np.ones(len(model), np.float32)
    weights[::10] = 0.0
    return dict(
        method="point_to_plane",
        target_normals=np.asarray(estimate_normals(scene, k=10)),
        max_correspondence_distance=np.linspace(0.03, 0.01, 12).astype(np.float32),
        max_iterations=12,
        tolerance=1e-5,
        kernel=Tukey(0.02),
        trim_fraction=0.9,
        source_weights=weights,
        neighbors=build_grid(scene, 0.03),
    )


def assert_same(a, b):
    leaves_a, tree_a = jax.tree.flatten(a)
    leaves_b, tree_b = jax.tree.flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_icp_options_is_a_top_level_name():
    assert jaxreg.ICPOptions is ICPOptions
    assert "ICPOptions" in jaxreg.__all__
    from jaxreg.registration.solver import ICPOptions as from_solver

    assert from_solver is ICPOptions
    names = [field.name for field in dataclasses.fields(ICPOptions)]
    assert names == [
        "method", "target_normals", "max_correspondence_distance", "max_iterations",
        "tolerance", "kernel", "trim_fraction", "source_weights", "neighbors", "viewpoint",
        "viewpoint_rows", "association",
    ]  # fmt: skip
    with pytest.raises(dataclasses.FrozenInstanceError):
        ICPOptions().max_iterations = 3


def test_icp_keywords_and_options_give_the_same_result(clouds, every_option):
    model, scene, _ = clouds
    init = np.eye(4, dtype=np.float32)
    by_keyword = icp(model, scene, init, **every_option)
    by_options = icp(model, scene, init, options=ICPOptions(**every_option))
    assert_same(by_keyword, by_options)
    assert by_keyword.rmse_history.shape == (12,)  # the options took effect


def test_multistart_icp_keywords_and_options_give_the_same_result(clouds, every_option):
    model, scene, _ = clouds
    inits = rotation_inits(model, scene, 13)  # init_spread's count: one compiled program
    by_keyword = multistart_icp(model, scene, inits, **every_option)
    by_options = multistart_icp(model, scene, inits, options=ICPOptions(**every_option))
    assert_same(by_keyword, by_options)
    assert by_keyword.rmse_history.shape == (13, 12)


def test_covariances_take_the_options_too(clouds, every_option):
    model, scene, truth = clouds
    wide = ICPOptions(max_correspondence_distance=0.03)
    assert_same(
        icp_covariance(model, scene, truth, point_sigma=0.002, max_correspondence_distance=0.03),
        icp_covariance(model, scene, truth, point_sigma=0.002, options=wide),
    )
    spread = np.diag([1e-4, 1e-4, 1e-4, 1e-3, 1e-3, 1e-3]).astype(np.float32)
    by_keyword = init_spread(model, scene, truth, spread, **every_option)
    assert_same(
        by_keyword, init_spread(model, scene, truth, spread, options=ICPOptions(**every_option))
    )
    assert np.all(np.isfinite(np.asarray(by_keyword)))


def test_keywords_replace_fields_of_the_options(clouds, every_option):
    model, scene, _ = clouds
    base = ICPOptions(**every_option)
    merged = icp(model, scene, options=base, trim_fraction=0.5, tolerance=1e-4)
    assert_same(merged, icp(model, scene, **dict(every_option, trim_fraction=0.5, tolerance=1e-4)))
    assert int(merged.num_inliers) < int(icp(model, scene, options=base).num_inliers)
    assert base.trim_fraction == 0.9  # options are never changed in place


@pytest.mark.parametrize(
    "call",
    [
        lambda m, s, t, **kw: icp(m, s, **kw),
        lambda m, s, t, **kw: multistart_icp(m, s, rotation_inits(m, s, 2), **kw),
        lambda m, s, t, **kw: icp_covariance(m, s, t, point_sigma=0.001, **kw),
        lambda m, s, t, **kw: init_spread(m, s, t, np.eye(6, dtype=np.float32) * 1e-4, **kw),
    ],
    ids=["icp", "multistart_icp", "icp_covariance", "init_spread"],
)
def test_an_unknown_keyword_is_refused_by_name(clouds, call):
    model, scene, truth = clouds
    with pytest.raises(TypeError, match=r"'max_iter' \(did you mean 'max_iterations'\?\)"):
        call(model, scene, truth, max_iter=5)
    with pytest.raises(TypeError, match=r"'colour'; ICP's options are method, target_normals"):
        call(model, scene, truth, options=ICPOptions(), colour="red")
    with pytest.raises(TypeError, match="takes a jaxreg.ICPOptions, got dict"):
        call(model, scene, truth, options={"max_iterations": 5})
