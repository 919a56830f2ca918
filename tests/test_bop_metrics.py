"""BOP's pose errors against the BOP toolkit's own numbers (the fixture made by
``tests/fixtures/bop/make_bop_metric_fixtures.py`` with thodan/bop_toolkit), and the recall /
Average Recall aggregation against a hand-computed case."""

import base64
import hashlib
import importlib.util
import json
import zlib
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3

from jaxreg.geometry.bop_metrics import (
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    VSD_TAUS,
    VSD_THRESHOLDS,
    BopRecall,
    average_recall,
    bop_symmetry_transforms,
    correct,
    mspd,
    mssd,
    vsd,
)

FIXTURES = Path(__file__).parent / "fixtures" / "bop"
FIXTURE = FIXTURES / "bop_metric_fixtures.json"
SCRIPT = FIXTURES / "make_bop_metric_fixtures.py"
# The toolkit's own tolerance on its scores (eval_bop19_pose_test.py). In float64 the pixel counts
# agree exactly; in float32 a pixel whose distance between the renderings rounds across a tau
# (the depth maps are quantised like BOP's PNGs) can flip: 1/1000 of these unions or less.
VSD_TOLERANCE = 1e-3


@pytest.fixture(scope="module")
def fixture() -> dict:
    return json.loads(FIXTURE.read_text())


def test_fixture_is_the_scripts_output(fixture):
    """The fixture is the output of the script beside it (same hash), at the path read here."""
    spec = importlib.util.spec_from_file_location("make_bop_metric_fixtures", SCRIPT)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.OUTPUT == FIXTURE
    assert fixture["made_by"] == "tests/fixtures/bop/make_bop_metric_fixtures.py"
    assert fixture["script_sha256"] == hashlib.sha256(SCRIPT.read_bytes()).hexdigest(), (
        "the fixture script changed since it made the fixture: rerun it with --toolkit"
    )
    assert len(fixture["cases"]) == 9 * len(script.OBJECTS)
    np.testing.assert_array_equal(fixture["vsd_taus"], VSD_TAUS)


def transforms_m(info: dict) -> np.ndarray:
    """jaxreg's discretisation of a models_info entry (mm), in metres."""
    discrete = np.reshape(info.get("symmetries_discrete", np.zeros((0, 16))), (-1, 4, 4))
    continuous = [(s["axis"], s["offset"]) for s in info.get("symmetries_continuous", [])]
    transforms = bop_symmetry_transforms(discrete, continuous)
    transforms[:, :3, 3] /= 1000.0
    return transforms


def test_symmetry_transforms_are_the_toolkits(fixture):
    for name, obj in fixture["objects"].items():
        ours = transforms_m(obj["models_info"])
        ours[:, :3, 3] *= 1000.0
        theirs = np.reshape(obj["symmetry_transforms_mm"], (-1, 3, 4))
        assert ours.shape[0] == theirs.shape[0], name
        np.testing.assert_allclose(ours[:, :3], theirs, rtol=0, atol=1e-12, err_msg=name)
    # an offset axis: the turns move points about it, not about the origin
    turned = bop_symmetry_transforms(None, [((0, 0, 2.0), (0.01, 0, 0))], max_sym_disc_step=1.0)
    assert turned.shape == (4, 4, 4)
    np.testing.assert_allclose(turned[2] @ [0.01, 0, 0.3, 1], [0.01, 0, 0.3, 1], atol=1e-15)
    np.testing.assert_allclose(turned[2] @ [0, 0, 0, 1], [0.02, 0, 0, 1], atol=1e-15)


def poses_m(cases: list[dict], which: str) -> np.ndarray:
    """``(C, 4, 4)`` camera_T_object in metres of the cases' ``est`` or ``gt``."""
    T = np.tile(np.eye(4), (len(cases), 1, 1))
    T[:, :3, :3] = [c[f"R_{which}"] for c in cases]
    T[:, :3, 3] = np.array([c[f"t_{which}_mm"] for c in cases]) / 1000.0
    return T


def by_object(fixture: dict):
    for name, obj in fixture["objects"].items():
        cases = [c for c in fixture["cases"] if c["object"] == name]
        yield name, obj, cases


@pytest.mark.parametrize(
    "dtype, tolerance",
    [("float64", 1e-6), ("float32", 1e-4)],  # mm and pixels
)
def test_mssd_and_mspd_are_the_toolkits(fixture, dtype, tolerance):
    """Every case to 1e-6 mm / 1e-6 px in float64, 1e-4 in float32 (about 2e-5 measured)."""
    with jax.enable_x64(dtype == "float64"):
        K = np.asarray(fixture["K"])
        for name, obj, cases in by_object(fixture):
            points = np.asarray(obj["points_mm"]) / 1000.0
            syms = transforms_m(obj["models_info"])
            args = [jnp.asarray(a, dtype) for a in (points, poses_m(cases, "est"))]
            truth = jnp.asarray(poses_m(cases, "gt"), dtype)
            syms_d = jnp.asarray(syms, dtype)
            ours_mssd = np.asarray(jax.jit(mssd)(*args, truth, syms_d)) * 1000.0
            ours_mspd = np.asarray(jax.jit(mspd)(*args, truth, syms_d, jnp.asarray(K, dtype)))
            assert ours_mssd.dtype == dtype
            np.testing.assert_allclose(
                ours_mssd, [c["mssd_mm"] for c in cases], rtol=0, atol=tolerance, err_msg=name
            )
            np.testing.assert_allclose(
                ours_mspd, [c["mspd_px"] for c in cases], rtol=0, atol=tolerance, err_msg=name
            )


def test_mssd_takes_se3_and_rejects_bad_shapes(fixture):
    name, obj, cases = next(by_object(fixture))
    points = np.asarray(obj["points_mm"]) / 1000.0
    syms = transforms_m(obj["models_info"])
    est, gt = poses_m(cases, "est"), poses_m(cases, "gt")
    as_se3 = mssd(points, SE3.from_matrix(est), SE3.from_matrix(gt), syms)
    np.testing.assert_allclose(as_se3, mssd(points, est, gt, syms), atol=1e-6)
    with pytest.raises(ValueError, match="symmetry_transforms must be"):
        mssd(points, est, gt, syms[:, :3])
    with pytest.raises(ValueError, match="points must be"):
        mssd(points[:, :2], est, gt, syms)
    with pytest.raises(ValueError, match="est must be"):
        mspd(points, est[:, :3], gt, syms, np.asarray(fixture["K"]))


def depth_m(fixture: dict, key: str) -> np.ndarray:
    counts = np.frombuffer(zlib.decompress(base64.b64decode(fixture["depth_maps"][key])), "<u2")
    shape = (fixture["height"], fixture["width"])
    return counts.reshape(shape).astype(np.float64) * fixture["depth_scale_mm"] / 1000.0


@pytest.mark.parametrize("dtype, tolerance", [("float64", 1e-9), ("float32", VSD_TOLERANCE)])
def test_vsd_is_the_toolkits(fixture, dtype, tolerance):
    """All 27 cases in one vmapped program, normalised (BOP's taus) and in metres."""
    cases = fixture["cases"]
    maps = {
        k: np.stack([depth_m(fixture, c[k]) for c in cases])
        for k in ("depth_est", "depth_gt", "depth_test")
    }
    diameters = np.array(
        [fixture["objects"][c["object"]]["models_info"]["diameter"] for c in cases]
    )
    K = np.asarray(fixture["K"])

    def both(est, gt, test, diameter):
        normalised = vsd(est, gt, test, K, delta=0.015, taus=VSD_TAUS, diameter=diameter)
        metric = vsd(
            est, gt, test, K, delta=0.015, diameter=diameter, normalized_by_diameter=False,
            taus=np.asarray(fixture["vsd_unnormalised_taus_mm"]) / 1000.0,
        )  # fmt: skip
        return normalised, metric

    with jax.enable_x64(dtype == "float64"):
        inputs = [maps["depth_est"], maps["depth_gt"], maps["depth_test"], diameters / 1000.0]
        ours, ours_metric = jax.jit(jax.vmap(both))(*(jnp.asarray(a, dtype) for a in inputs))
        assert ours.dtype == dtype
    theirs = np.array([c["vsd"] for c in cases])
    theirs_metric = np.array([c["vsd_unnormalised"] for c in cases])
    np.testing.assert_allclose(ours, theirs, rtol=0, atol=tolerance)
    np.testing.assert_allclose(ours_metric, theirs_metric, rtol=0, atol=tolerance)
    assert 0 < theirs.mean() < 1 and (theirs == 1).any() and (theirs == 0).any()  # cases vary


def test_vsd_empty_union_and_missing_depth():
    K = np.array([[100.0, 0, 3.5], [0, 100.0, 2.5], [0, 0, 1]])
    nothing = np.zeros((6, 8))
    scene = np.full((6, 8), 0.5)
    np.testing.assert_array_equal(vsd(nothing, nothing, scene, K, diameter=0.1), np.ones(10))
    # NaN (the renderer's "nothing") counts as no depth, like 0
    model = np.where(np.arange(8) < 4, 0.5, np.nan)[None].repeat(6, 0)
    np.testing.assert_array_equal(vsd(model, model, scene, K, diameter=0.1), np.zeros(10))
    shifted = np.where(np.arange(8) >= 2, 0.5, np.nan)[None].repeat(6, 0)
    # the two visible surfaces share 2 of the union's 8 columns: 6/8 wrong at every tau
    np.testing.assert_allclose(vsd(shifted, model, scene, K, diameter=0.1), np.full(10, 0.75))
    with pytest.raises(ValueError, match="three \\(H, W\\) of one shape"):
        vsd(model, model[:, :4], scene, K, diameter=0.1)


def test_average_recall_by_hand():
    """Four targets: perfect, missing, and two partial ones; every count worked out below."""
    diameter = np.array([0.1, 0.1, 0.2, 0.2])
    width = np.array([640, 640, 640, 1280])
    vsd_errors = np.stack(
        [
            np.zeros(10),  # 100 of 100 (tau, threshold) pairs
            np.ones(10),  # missing: 0
            np.full(10, 0.27),  # thresholds 0.30..0.50: 5 per tau, 50
            np.linspace(0.61, 0.16, 10),  # 0.46 -> 1, 0.41 -> 2, ..., 0.16 -> 7: 28
        ]
    )
    mssd_errors = np.array([0.0, np.inf, 0.12 * 0.2, 0.33 * 0.2])  # 10, 0, 8, 4 of 10
    mspd_errors = np.array([0.0, np.inf, 22.0, 22.0])  # 10, 0, 6 (> 22), 8 (> 11) of 10
    scores = jax.jit(average_recall)(
        vsd_errors, mssd_errors, mspd_errors, diameter=diameter, image_width=width
    )
    np.testing.assert_allclose(scores.ar_vsd, 178 / 400, rtol=1e-6)
    np.testing.assert_allclose(scores.ar_mssd, 22 / 40, rtol=1e-6)
    np.testing.assert_allclose(scores.ar_mspd, 24 / 40, rtol=1e-6)
    np.testing.assert_allclose(scores.ar, (178 / 400 + 22 / 40 + 24 / 40) / 3, rtol=1e-6)
    np.testing.assert_allclose(
        np.asarray(scores.recall_mssd)[[0, 2, 6, 9]], [0.25, 0.5, 0.75, 0.75]
    )
    np.testing.assert_allclose(np.asarray(scores.recall_mspd)[[0, 2, 3, 4]], [0.25, 0.5, 0.5, 0.75])
    assert scores.recall_vsd.shape == (10, 10)
    np.testing.assert_allclose(scores.recall_vsd[9], [0.25] * 3 + [0.5] * 2 + [0.75] * 5)
    # strictly below: an error equal to its threshold is not correct
    for thresholds in (VSD_THRESHOLDS, MSSD_THRESHOLDS, MSPD_THRESHOLDS):
        hits = np.asarray(correct(thresholds, thresholds))
        assert not hits.diagonal().any() and hits[0, 1:].all()
    empty = BopRecall.from_hits(np.zeros((0, 10, 10), bool), np.zeros((0, 10)), np.zeros((0, 10)))
    assert float(empty.ar) == 0.0
