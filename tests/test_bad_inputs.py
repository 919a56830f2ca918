"""A user's bad inputs to estimate_pose and `jaxreg pose`: each gets a clear ValueError (exit
status 2 on the command line) or a named failure, never a pose it did not earn. The cases that
run the pipeline on the whole frame live in test_pipeline.py (they share its compiled
programs); these stop before the registration."""

import json

import numpy as np
import pytest
from PIL import Image

from jaxreg.camera import Intrinsics, RGBDFrame
from jaxreg.cli import main
from jaxreg.pipeline import estimate_pose

H, W = 120, 160
INTRINSICS = Intrinsics(150.0, 150.0, 80.0, 60.0, W, H)


def _model(n=2000, seed=0):
    """Points on an 80 x 50 x 120 mm box's surface (metres)."""
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1, 1, (n, 3))
    face = rng.integers(0, 3, n)
    points[np.arange(n), face] = np.sign(points[np.arange(n), face])
    return (points * [0.04, 0.025, 0.06]).astype(np.float32)


def _frame(depth, intrinsics=INTRINSICS):
    return RGBDFrame(np.asarray(depth, np.float32), intrinsics)


def test_depth_without_a_finite_value_is_a_named_segment_failure():
    depth = np.full((H, W), np.nan)
    depth[::2] = np.inf
    depth[1::4] = -np.inf
    est = estimate_pose(_frame(depth), _model())
    assert est.pose is None and est.failed_stage == "segment"
    assert "valid depth" in est.reason and np.isnan(est.covariance).all()


def test_a_one_pixel_frame_is_a_named_segment_failure():
    est = estimate_pose(_frame([[0.6]], Intrinsics(1.0, 1.0, 0.0, 0.0, 1, 1)), _model())
    assert est.pose is None and est.failed_stage == "segment"


def test_bad_masks_raise_or_fail_by_name():
    frame, model = _frame(np.full((H, W), 0.6)), _model()
    with pytest.raises(ValueError, match=r"\(H, W\) = \(120, 160\)"):
        estimate_pose(frame, model, mask=np.ones((H, W + 1), bool))
    with pytest.raises(ValueError, match="mask is empty"):
        estimate_pose(frame, model, mask=np.zeros((H, W), bool))
    with pytest.raises(ValueError, match="bool or integer"):
        estimate_pose(frame, model, mask=np.ones((H, W)))
    with pytest.raises(ValueError, match="not both"):
        estimate_pose(frame, model, mask=np.ones((H, W), bool), pixel=(3, 4))
    holes = np.full((H, W), 0.6)
    mask = np.zeros((H, W), bool)
    mask[40:80, 60:100] = True
    holes[mask] = np.nan
    est = estimate_pose(_frame(holes), model, mask=mask)
    assert est.pose is None and est.failed_stage == "segment"
    assert "0 points with depth" in est.reason


def test_bad_models_and_units_raise_clear_errors():
    frame = _frame(np.full((H, W), 0.6))
    with pytest.raises(ValueError, match="at least a few hundred points"):
        estimate_pose(frame, _model(5))
    with pytest.raises(ValueError, match="millimetres"):
        estimate_pose(frame, 1000 * _model())
    with pytest.raises(ValueError, match="no finite point"):
        estimate_pose(frame, np.full((20, 3), np.nan))
    with pytest.raises(ValueError, match="depth must be metres"):
        estimate_pose(_frame(np.full((H, W), 600.0)), _model())


def test_mismatched_intrinsics_raise_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="intrinsics are for"):
        _frame(np.full((H, W), 0.6), Intrinsics(150.0, 150.0, 80.0, 60.0, W + 8, H))
    from jaxreg.io import read_frame, write_frame

    write_frame(tmp_path / "scene.png", _frame(np.full((H, W), 0.6)))
    meta = json.loads((tmp_path / "scene.json").read_text())
    (tmp_path / "scene.json").write_text(json.dumps(meta | {"width": W * 2}))
    with pytest.raises(ValueError, match="intrinsics are for"):
        read_frame(tmp_path / "scene.png")


def _pose(*args):
    return main(["pose", *map(str, args)])


def test_the_command_line_exits_2_with_one_line_on_bad_input(tmp_path, capsys):
    from jaxreg.io import write_frame, write_pcd

    write_frame(tmp_path / "scene.png", _frame(np.full((H, W), 0.6)))
    write_pcd(tmp_path / "model.pcd", _model())
    (tmp_path / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    (tmp_path / "broken.json").write_text("{ not json")
    Image.fromarray(np.zeros((H, W), np.uint8)).save(tmp_path / "empty_mask.png")
    Image.fromarray(np.zeros((H + 1, W), np.uint8)).save(tmp_path / "small_mask.png")
    write_pcd(tmp_path / "model_mm.pcd", 1000 * _model())
    scene, model = tmp_path / "scene.png", tmp_path / "model.pcd"
    json_path = scene.with_suffix(".json")
    cases = {
        "not a readable image": ("--scene", tmp_path / "broken.png", "--intrinsics", json_path),
        "not valid JSON": ("--scene", scene, "--intrinsics", tmp_path / "broken.json"),
        "the mask image is not a readable image": (
            "--scene", scene, "--mask", tmp_path / "broken.png"
        ),
        "mask is empty": ("--scene", scene, "--mask", tmp_path / "empty_mask.png"),
        "mask must be an (H, W)": ("--scene", scene, "--mask", tmp_path / "small_mask.png"),
        "unknown --symmetry": ("--scene", scene, "--symmetry", "turns:0"),
    }
    cases = {k: (*v, "--model", model) for k, v in cases.items()}
    cases["millimetres"] = ("--scene", scene, "--model", tmp_path / "model_mm.pcd")
    for expected, args in cases.items():
        assert _pose(*args) == 2, expected
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and err.startswith("jaxreg pose: "), err
        assert expected in err and "Traceback" not in err


def test_a_thin_mask_or_box_is_lifted_at_every_pixel_where_the_grid_holds_too_few():
    """A rod 3 pixels wide and 50 tall in the mask (a marker far from the camera) holds 12
    points on the 4-pixel grid, fewer than a registration needs: its candidate is every pixel
    of its surface (150), not a refusal. A box around it holds its cluster: 12 grid points are
    a candidate for a model this thin (half of its 10 x 10 mm silhouette covers less than a
    grid step at 0.5 m), and no candidate for the 80 x 50 x 120 mm box, which the frame shows
    nowhere."""
    import jax

    from jaxreg.pipeline._model import _prepare_model
    from jaxreg.pipeline._segment_stage import MIN_MASK_POINTS, segment_stage
    from jaxreg.pipeline._stages import _Failed
    from jaxreg.pipeline.settings import PipelineSettings
    from jaxreg.uncertainty import DepthNoise

    depth = np.full((H, W), 0.6)
    mask = np.zeros((H, W), bool)
    mask[30:80, 78:81] = True
    depth[mask] = 0.5
    assert (mask[::4, ::4]).sum() < MIN_MASK_POINTS
    rod = _model() * np.array([0.125, 0.2, 1.0], np.float32)  # 10 x 10 x 120 mm
    settings = PipelineSettings()
    noise = DepthNoise((0.0, 0.0, 2.5e-3))

    def segmented(points, **prompt):
        model = _prepare_model(points, None, settings.voxel_size, 0.04, 0.015)
        return segment_stage(
            _frame(depth), model, settings.segment, jax.random.PRNGKey(0), noise,
            lift=settings.lift, **prompt,
        )  # fmt: skip

    assert segmented(rod, mask=mask).record.mask_grid_points == mask.sum() == 150
    for prompt in ({"box": (76, 28, 82, 81)}, {}):
        boxed = segmented(rod, **prompt)
        assert boxed.clusters is not None and len(boxed.candidates) == 1
        assert len(boxed.candidates[0][1]) == mask[::4, ::4].sum()
    with pytest.raises(_Failed, match="nothing of the model's size stands on the table"):
        segmented(_model())


def test_a_box_on_the_bare_table_is_refused_naming_the_box():
    """A box that holds no cluster is read as a mask; on the bare table it holds no point
    above it, and the refusal names the box, not a mask."""
    frame = _frame(np.full((H, W), 0.6))
    est = estimate_pose(frame, _model(), box=(40, 30, 70, 60))
    assert est.pose is None and est.failed_stage == "segment"
    assert est.reason.startswith("the box's 961 pixels hold 0 points with depth"), est.reason
    assert "a box on a hole in the depth" in est.reason and "mask" not in est.reason
