import json
import urllib.request

import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3
from PIL import Image

import jaxreg as jr
from jaxreg.cli import main

KEYS = (
    "pose",
    "failed_stage",
    "reason",
    "stages",
    "inlier_rmse_mm",
    "inlier_fraction",
    "predicted_grasp_success",
)


def test_demo_reports_stages_error_vs_truth_error_bars_grasp_and_pictures(capsys, tmp_path):
    assert main(["demo", "--json", "--out", str(tmp_path), "--seed", "4", "--object", "box"]) == 0
    report = json.loads(capsys.readouterr().out)
    for key in (*KEYS, "translation_error_mm", "rotation_error_deg", "add_s_mm"):
        assert key in report
    pose = np.array(report["pose"])
    assert pose.shape == (4, 4) and np.allclose(pose[3], [0, 0, 0, 1])
    assert report["failed_stage"] is None
    assert report["add_s_mm"] < 5.0
    assert set(report["stages"]) == {"segment", "lift", "register"}
    assert all(report["stages"][s]["ms"] > 0 for s in report["stages"])
    assert len(report["error_bars"]["translation_sigma_mm"]) == 3
    grasp = report["grasp"]
    assert grasp["object_width_mm"] == pytest.approx(50, abs=3)  # the box's narrow side
    assert 0 <= report["predicted_grasp_success"] <= 1
    # The measured error enters as a bias along the jaws, which can only lower the chance.
    assert 0 <= grasp["measured_lateral_error_mm"] <= report["translation_error_mm"] + 1e-6
    assert grasp["probability_with_measured_error"] <= grasp["probability"] + 1e-9
    assert json.loads((tmp_path / "report.json").read_text())["pose"] == report["pose"]
    for name in ("depth.png", "segmentation.png", "model_overlay.png"):
        assert (tmp_path / name).stat().st_size > 1000


def _patch_view(monkeypatch):
    """The 3D view's scenes and served pages, recorded; serving ends once the page is fetched
    instead of at Ctrl-C."""
    from jaxreg.cli import _view

    scenes, pages = [], []
    view_scene = _view.view_scene

    def record(*args, **kwargs):
        scenes.append(view_scene(*args, **kwargs))
        return scenes[-1]

    def visit(url):
        with urllib.request.urlopen(url, timeout=30) as response:
            pages.append(response.read())

    monkeypatch.setattr(_view, "view_scene", record)
    monkeypatch.setattr(_view, "_until_interrupted", visit)
    return scenes, pages


def test_demo_track_finds_then_follows_the_object_frame_by_frame(capsys):
    assert main(["demo", "--track", "3", "--seed", "12", "--object", "cylinder", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    rows = report["frames"]
    assert [row["method"] for row in rows] == ["estimate_pose", "track", "track"]
    diameter_mm = np.hypot(70.0, 120.0)  # the synthetic can: 70 mm across, 120 mm tall
    assert all(row["found"] and row["add_s_mm"] < 0.1 * diameter_mm for row in rows)
    assert all(10.0 <= row["step_mm"] <= 50.0 for row in rows[1:])
    assert rows[0]["view_terms"] == "measured"  # estimate_pose measures the view
    assert rows[1]["view_terms"] == "measured"  # and so does the first step, on its own pixels
    assert rows[2]["view_terms"] in ("carried", "measured")
    assert main(["demo", "--track", "1"]) == 2
    assert "at least 2 frames" in capsys.readouterr().err


def test_demo_view_serves_the_scene_after_the_report(capsys, monkeypatch):
    scenes, pages = _patch_view(monkeypatch)
    args = ["demo", "--json", "--seed", "4", "--object", "box", "--view", "--view-port", "0"]
    assert main(args) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["failed_stage"] is None  # stdout is still the one JSON report
    assert "3D view at http://127.0.0.1:" in err
    assert pages and b"<title>Viser</title>" in pages[0]
    (scene,) = scenes
    assert scene.model is not None and scene.truth is not None and len(scene.jaws) == 2
    assert len(scene.points["object"]) > 100 and len(scene.points["table"]) > 10_000


@pytest.mark.slow
def test_pose_finds_the_carton_and_makes_no_claim_where_it_is_not(pcl_dir, tmp_path, capsys):
    from jaxreg.io import load_points, write_pcd

    handed = SE3.from_rotation_and_translation(
        SO3.from_rpy_radians(1.0, -2.0, 0.5), jnp.array([0.3, -0.2, 0.5])
    )
    model = np.asarray(handed @ jnp.asarray(load_points(pcl_dir / "milk.pcd")))
    write_pcd(tmp_path / "model.pcd", model.astype(np.float32))
    truth = np.asarray(handed.inverse().as_matrix())  # milk.pcd was cut from this capture
    scene = pcl_dir / "milk_cartoon_all_small_clorox.pcd"
    assert (
        main(["pose", "--scene", str(scene), "--model", str(tmp_path / "model.pcd"), "--json"]) == 0
    )
    report = json.loads(capsys.readouterr().out)
    assert report["failed_stage"] is None
    pose = np.array(report["pose"])
    assert np.linalg.norm(pose[:3, 3] - truth[:3, 3]) < 0.005
    cos = (np.trace(pose[:3, :3].T @ truth[:3, :3]) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 2.0
    mug = pcl_dir / "table_scene_mug_stereo_textured.pcd"
    assert (
        main(["pose", "--scene", str(mug), "--model", str(tmp_path / "model.pcd"), "--json"]) == 1
    )
    report = json.loads(capsys.readouterr().out)
    assert report["failed_stage"] is not None and report["pose"] is None
    assert report["reason"] and report["predicted_grasp_success"] is None


def test_a_garbage_scene_file_is_one_clear_error(capsys, tmp_path):
    garbage = tmp_path / "scene.pcd"
    garbage.write_bytes(b"VERSION .7\nFIELDS x y\x00\xff garbage")
    model = tmp_path / "model.pcd"
    model.write_text("not a model")
    assert main(["pose", "--scene", str(garbage), "--model", str(model)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxreg pose: ") and len(err.splitlines()) == 1
    assert "Traceback" not in err
    assert main(["demo", "--object", "teapot"]) == 2
    assert "unknown object 'teapot'" in capsys.readouterr().err


def test_bad_command_line_is_one_clear_error(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["nonsense"])
    assert exit_.value.code != 0
    assert "invalid choice" in capsys.readouterr().err


def test_pose_on_a_depth_png_exits_0_found_and_1_not_there(tmp_path, capsys, monkeypatch):
    """A depth PNG + intrinsics JSON frame (written from the demo's scene), a model in
    millimetres, and the options estimate_pose takes; a mask on a distractor exits 1 with the
    report still printed."""
    import trimesh
    from PIL import Image

    from jaxreg.geometry.metrics import add_s
    from jaxreg.io import write_frame, write_pcd
    from jaxreg.synth import tabletop_scene

    scene = tabletop_scene(4, object="box")
    write_frame(tmp_path / "scene.png", scene.frame)
    samples, _ = trimesh.sample.sample_surface(scene.model, 20_000, seed=0)
    write_pcd(tmp_path / "model.pcd", (1000 * samples).astype(np.float32))
    Image.fromarray((255 * (scene.labels == 2)).astype(np.uint8)).save(tmp_path / "other.png")
    Image.fromarray((255 * scene.mask).astype(np.uint8)).save(tmp_path / "mask.png")
    common = ["pose", "--scene", str(tmp_path / "scene.png"), "--model",
              str(tmp_path / "model.pcd"), "--model-units", "mm", "--json"]  # fmt: skip
    options = ["--symmetry", "box", "--depth-noise", "0", "0", "0.0025"]
    rows, cols = np.nonzero(scene.mask)
    pixel = [str(np.median(cols)), str(np.median(rows))]
    box = [str(v) for v in (cols.min(), rows.min(), cols.max(), rows.max())]
    for extra in ([], ["--mask", str(tmp_path / "mask.png")], ["--pixel", *pixel], ["--box", *box]):
        assert main([*common, *options, *extra]) == 0, extra
        report = json.loads(capsys.readouterr().out)
        assert report["failed_stage"] is None
        pose = SE3.from_matrix(jnp.asarray(report["pose"], jnp.float32))
        assert float(add_s(scene.model_points, pose, scene.truth)) < 0.005
    assert main([*common, "--mask", str(tmp_path / "other.png")]) == 1
    report = json.loads(capsys.readouterr().out)
    assert report["pose"] is None and report["failed_stage"] is not None and report["reason"]
    assert set(report["stages"]["segment"]) >= {"ms", "mask_pixels", "mask_grid_points"}
    # --view serves the frame of a refused estimate too, and the exit status stays 1.
    scenes, pages = _patch_view(monkeypatch)
    assert main([*common, "--mask", str(tmp_path / "other.png"), "--view", "--view-port", "0"]) == 1
    assert json.loads(capsys.readouterr().out)["pose"] is None
    (view,) = scenes
    assert pages and view.model is None and view.jaws == [] and view.truth is None


def test_pose_sets_aside_clusters_of_another_colour_given_model_color(tmp_path, capsys):
    """``--model-color R G B`` (or ``--model-colors``: the model file's own) with ``--rgb``:
    the distractors, painted otherwise, are set aside (the report's segment stage lists them)
    and the box is found; counts beyond 0-255, or both flags, exit 2."""
    from jaxreg.geometry.metrics import add_s
    from jaxreg.io import write_frame, write_ply
    from jaxreg.synth import tabletop_scene

    scene = tabletop_scene(4, object="box")
    write_frame(tmp_path / "scene.png", scene.frame)
    Image.fromarray(np.asarray(scene.frame.rgb)).save(tmp_path / "colour.png")
    write_ply(tmp_path / "model.ply", np.asarray(scene.model_points, np.float32),
              colors=scene.model_colors)  # fmt: skip
    paint = [str(c) for c in 255 * scene.model_colors[0]]
    common = ["pose", "--scene", str(tmp_path / "scene.png"), "--model",
              str(tmp_path / "model.ply"), "--rgb", str(tmp_path / "colour.png"), "--json",
              "--symmetry", "box"]  # fmt: skip
    for colours in (["--model-color", *paint], ["--model-colors"]):
        assert main([*common, *colours]) == 0
        report = json.loads(capsys.readouterr().out)
        assert len(report["stages"]["segment"]["other_color"]) == 2  # both distractors
        pose = SE3.from_matrix(jnp.asarray(report["pose"], jnp.float32))
        assert float(add_s(scene.model_points, pose, scene.truth)) < 0.005
    assert main([*common, "--model-color", "300", "0", "0"]) == 2
    assert "--model-color takes sRGB counts 0-255" in capsys.readouterr().err
    assert main([*common, "--model-colors", "--model-color", *paint]) == 2
    assert "not both" in capsys.readouterr().err


def test_pose_draws_its_pictures_on_the_colour_image_given_by_rgb(tmp_path, capsys):
    """``--rgb`` reads the colour image beside a depth PNG: the segmentation and the model
    overlay are drawn on its pixels (a colour image of another size exits 2, naming both)."""
    from jaxreg.io import write_frame, write_pcd
    from jaxreg.synth import tabletop_scene

    scene = tabletop_scene(4, object="box")
    depth_only = jr.RGBDFrame(scene.frame.depth, scene.frame.intrinsics,
                              base_T_camera=scene.frame.base_T_camera)  # fmt: skip
    write_frame(tmp_path / "scene.png", depth_only)
    write_pcd(tmp_path / "model.pcd", np.asarray(scene.model_points, np.float32))
    Image.fromarray((255 * scene.mask).astype(np.uint8)).save(tmp_path / "mask.png")
    # values below 200: the overlay's red (255, 40, 40) cannot come from the colour image
    colour = np.random.default_rng(0).integers(0, 200, (*scene.mask.shape, 3), dtype=np.uint8)
    Image.fromarray(colour).save(tmp_path / "colour.png")
    out = tmp_path / "out"
    common = ["pose", "--scene", str(tmp_path / "scene.png"), "--model",
              str(tmp_path / "model.pcd"), "--mask", str(tmp_path / "mask.png"),
              "--json"]  # fmt: skip
    assert main([*common, "--rgb", str(tmp_path / "colour.png"), "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["failed_stage"] is None
    overlay = np.asarray(Image.open(out / "model_overlay.png"))
    drawn = (overlay == (255, 40, 40)).all(-1)
    assert drawn.sum() > 50 and scene.mask[drawn].mean() > 0.9  # the model lands on the box
    np.testing.assert_array_equal(overlay[~drawn], colour[~drawn])
    segmentation = np.asarray(Image.open(out / "segmentation.png"))
    painted = (segmentation != colour).any(-1)
    assert painted.sum() > 100 and scene.mask[painted].mean() > 0.9  # green over the segment
    Image.fromarray(colour[:, :-1]).save(tmp_path / "narrow.png")
    assert main([*common, "--rgb", str(tmp_path / "narrow.png")]) == 2
    err = capsys.readouterr().err
    assert "colour image is 847x480" in err and "848x480" in err


YCBV_OBJECT = ("0000/000001", "025_mug", 14)  # frame, model, class index: an instance posed


@pytest.mark.slow
def test_pose_on_a_ycbv_frame_reports_errors_against_its_truth(ycbv_dir, capsys, tmp_path):
    """``--ycbv PREFIX --object NAME_OR_INDEX``: the dataset's frame, model and label mask; the
    report's ADD, ADD-S and errors agree with its own pose and truth."""
    frame_name, model_name, class_index = YCBV_OBJECT
    prefix = str(ycbv_dir / "data" / frame_name)
    args = ["pose", "--ycbv", prefix, "--object", str(class_index), "--json"]
    assert main([*args, "--out", str(tmp_path)]) == 0
    report = json.loads(capsys.readouterr().out)
    for key in (*KEYS, "translation_error_mm", "rotation_error_deg", "add_mm", "add_s_mm"):
        assert report[key] is not None or key == "failed_stage", key
    assert report["ycbv"] == {
        "frame": frame_name, "object": model_name, "class_index": class_index,
        "segment": "the label's mask", "model_points": 2621,
    }  # fmt: skip
    (ycbv,) = jr.io.read_ycbv(prefix)
    (instance,) = [i for i in ycbv.instances if i.class_index == class_index]
    truth, pose = np.array(report["truth"]), np.array(report["pose"])
    np.testing.assert_allclose(truth, np.asarray(instance.truth.as_matrix()), atol=1e-6)
    model = np.asarray(instance.model_points, np.float64)
    at_pose, at_truth = model @ pose[:3, :3].T + pose[:3, 3], model @ truth[:3, :3].T + truth[:3, 3]
    add_mm = 1e3 * np.linalg.norm(at_pose - at_truth, axis=1).mean()
    gaps = np.linalg.norm(at_pose[:, None] - at_truth[None], axis=-1)
    add_s_mm = 1e3 * gaps.min(axis=1).mean()
    assert report["add_mm"] == pytest.approx(add_mm, abs=0.01)
    assert report["add_s_mm"] == pytest.approx(add_s_mm, abs=0.01)
    shift = 1e3 * np.linalg.norm(pose[:3, 3] - truth[:3, 3])
    assert report["translation_error_mm"] == pytest.approx(shift, abs=0.01)
    diameter = 1e3 * np.linalg.norm(model[:, None] - model[None], axis=-1).max()
    assert report["add_s_mm"] < 0.1 * diameter  # a pose reported as found is right
    assert 0 <= report["grasp"]["probability_with_measured_error"] <= 1
    # the pictures are drawn on the frame's colour image
    overlay = np.asarray(Image.open(tmp_path / "model_overlay.png"))
    colour = np.asarray(ycbv.frame.rgb)
    untouched = (overlay != (255, 40, 40)).any(-1)
    assert untouched.mean() > 0.9
    np.testing.assert_array_equal(overlay[untouched], colour[untouched])
    # the model's name names the same instance
    assert main(["pose", "--ycbv", prefix, "--object", model_name, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["pose"] == report["pose"]


def test_pose_on_a_ycbv_frame_refuses_an_object_not_in_it(ycbv_dir, capsys):
    prefix = str(ycbv_dir / "data" / "0000" / "000001")
    for wanted in ("1", "002_master_chef_can", "teapot"):
        assert main(["pose", "--ycbv", prefix, "--object", wanted]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1
        assert f"--object {wanted!r} is not in frame 0000/000001" in err
        assert "009_gelatin_box (8), 025_mug (14), 061_foam_brick (21)" in err
    assert main(["pose", "--ycbv", prefix]) == 2
    assert "needs --object" in capsys.readouterr().err
    assert main(["pose", "--ycbv", prefix, "--object", "14", "--model", prefix]) == 2
    assert "--model cannot be given with --ycbv" in capsys.readouterr().err
    assert main(["pose", "--ycbv", prefix, "--object", "14", "--model-colors"]) == 2
    assert "YCB-Video's point models have none" in capsys.readouterr().err
    assert main(["pose", "--ycbv", str(ycbv_dir / "data" / "0000"), "--object", "14"]) == 2
    assert "names 5 frames" in capsys.readouterr().err


def test_an_internal_error_is_not_reported_as_bad_input(monkeypatch, capsys):
    """A bug inside a command (here a TypeError raised by the pipeline) exits 3 with its
    traceback and a line saying it is not the input's fault; bad input stays exit 2."""

    def broken(*_, **__):
        raise TypeError("unsupported operand type(s) for +: 'SE3' and 'NoneType'")

    monkeypatch.setattr("jaxreg.pipeline.estimate.estimate_pose", broken)
    assert main(["demo", "--seed", "4", "--object", "box"]) == 3
    err = capsys.readouterr().err
    assert "Traceback" in err and "TypeError" in err
    assert "internal error (TypeError), not a problem with the input" in err
