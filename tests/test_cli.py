import json
import urllib.request

import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3
from PIL import Image
from scipy import ndimage

import jaxreg as jr
from jaxreg.cli import main
from jaxreg.cli._overlay import ESTIMATE, REFUSED, TRUTH, model_overlay

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
    # values below 200: the overlay's outline (255, 140, 0) cannot come from the colour image
    colour = np.random.default_rng(0).integers(0, 200, (*scene.mask.shape, 3), dtype=np.uint8)
    Image.fromarray(colour).save(tmp_path / "colour.png")
    out = tmp_path / "out"
    common = ["pose", "--scene", str(tmp_path / "scene.png"), "--model",
              str(tmp_path / "model.pcd"), "--mask", str(tmp_path / "mask.png"),
              "--json"]  # fmt: skip
    assert main([*common, "--rgb", str(tmp_path / "colour.png"), "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["failed_stage"] is None
    overlay = np.asarray(Image.open(out / "model_overlay.png"))
    changed = (overlay != colour).any(-1)
    # the box is filled (single pixels at a quarter of the model points would change at most
    # that many) and outlined along its edge; below the legend little else changes
    assert changed[scene.mask].mean() > 0.8
    assert changed[scene.mask].sum() > len(scene.model_points) // 4
    outline = (overlay == ESTIMATE).all(-1)
    outline[:40] = False  # the legend's orange line
    near_box = ndimage.binary_dilation(scene.mask, iterations=5)
    assert outline.sum() > 200 and near_box[outline].mean() > 0.95
    assert changed[40:][~near_box[40:]].mean() < 0.01
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
    untouched = (overlay == colour).all(-1)
    assert untouched.mean() > 0.8
    assert (~untouched[instance.mask]).mean() > 0.8  # the mug is filled
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


def _estimate(pose=None, reason="found", hypothesis=None, failed_stage=None):
    """What the overlay reads of a PoseEstimate: the pose, or the failed stage, its reason
    and the register record's hypothesis."""
    from types import SimpleNamespace

    stages = {} if hypothesis is None else {"register": SimpleNamespace(hypothesis=hypothesis)}
    return SimpleNamespace(pose=pose, failed_stage=failed_stage, reason=reason, stages=stages)


@pytest.fixture(scope="module")
def mug_frame(ycbv_dir):
    """YCB-Video frame 0000/000001 and its mug, partly hidden behind the foam brick."""
    (ycbv,) = jr.io.read_ycbv(ycbv_dir / "data" / "0000" / "000001")
    (mug,) = [i for i in ycbv.instances if i.model_name == "025_mug"]
    (brick,) = [i for i in ycbv.instances if i.model_name == "061_foam_brick"]
    return ycbv.frame, mug, brick


def test_the_overlay_fills_and_outlines_the_visible_model_with_its_axes(mug_frame):
    """At the true pose the mug's silhouette covers its label mask, the part the brick hides
    is not drawn, the outline and the axes are drawn, and the truth's outline is magenta."""
    frame, mug, brick = mug_frame
    colour = np.asarray(frame.rgb)
    drawn = model_overlay(colour, frame, _estimate(mug.truth), mug.model_points, truth=mug.truth)
    changed = (drawn.image != colour).any(-1)
    filled = drawn.filled["estimate"]
    assert changed[mug.mask].mean() > 0.9
    # single red pixels at every fourth model point could change at most this many
    assert changed[mug.mask].sum() > 5 * len(mug.model_points) // 4
    assert ndimage.binary_dilation(mug.mask, iterations=6)[filled].mean() > 0.95
    assert filled[brick.mask].mean() < 0.02  # the brick stands in front of the mug
    assert (drawn.image == TRUTH).all(-1).sum() > 200  # the truth's outline, drawn last
    for axis in ((235, 35, 35), (40, 215, 40), (50, 110, 255)):
        assert (drawn.image == axis).all(-1).sum() > 20
    assert drawn.legend[0] == "orange: the estimate"
    assert "magenta outline: the truth" in drawn.legend
    # without the truth, the estimate's outline is orange (below the legend's orange line;
    # two of the photo's own pixels have that colour)
    alone = model_overlay(colour, frame, _estimate(mug.truth), mug.model_points).image
    outline = (alone == ESTIMATE).all(-1) & (colour != ESTIMATE).any(-1)
    outline[:40] = False
    assert outline.sum() > 200 and filled[outline].all()


def test_a_refused_estimate_draws_its_hypothesis_in_grey_with_its_reason(mug_frame):
    frame, mug, _ = mug_frame
    colour = np.asarray(frame.rgb)
    reason = "the model is not there: the image sees through it"
    hypothesis = np.asarray(mug.truth.as_matrix(), np.float64).tolist()
    refused = _estimate(None, reason, hypothesis, failed_stage="register")
    drawn = model_overlay(colour, frame, refused, mug.model_points)
    grey = drawn.filled["hypothesis"] & mug.mask
    assert grey.sum() > 0.9 * mug.mask.sum()
    # the fill is the grey blended into the image (but on the outline and the axes)
    blended = 0.55 * colour[grey].astype(float) + 0.45 * np.asarray(REFUSED)
    assert (np.abs(drawn.image[grey] - blended).max(-1) <= 1.0).mean() > 0.85
    assert (drawn.image == REFUSED).all(-1).sum() > 200  # its outline
    assert drawn.legend[0] == f"REFUSED at register: {reason}"
    assert drawn.legend[1] == "grey: the best hypothesis, refused"
    top = (drawn.image[:40] != colour[:40]).any(-1)
    assert top[:, :200].mean() > 0.5  # the legend's band and its text
    # a hypothesis sunk behind the measured surface (20% farther along the line of sight) is
    # drawn whole, and one behind the camera is said to be outside the image
    refused_line = "grey: the best hypothesis, refused, "
    for scale, where in ((1.2, "drawn whole: it lies behind the measured surface"),
                         (-1.0, "outside the image")):  # fmt: skip
        moved = np.array(hypothesis)
        moved[:3, 3] *= scale
        drawn = model_overlay(colour, frame, _estimate(None, reason, moved.tolist(), "register"),
                              mug.model_points)  # fmt: skip
        assert drawn.legend[-2] == refused_line + where
        area = drawn.filled["hypothesis"].sum()
        assert area > 0.5 * mug.mask.sum() if scale > 0 else area == 0
    # a stage that failed before the refinement has no hypothesis: the reason alone
    lift = _estimate(None, "too few pixels with depth", failed_stage="lift")
    drawn = model_overlay(colour, frame, lift, mug.model_points)
    assert drawn.filled == {} and drawn.legend[0].startswith("REFUSED at lift: too few")
    assert (drawn.image[100:] == colour[100:]).all()


@pytest.fixture(scope="module")
def bop_ycbv(ycbv_dir, tmp_path_factory):
    """Sequence 0000 of the shipped YCB-Video frames as a BOP split (jaxreg convert-ycbv):
    scene 0, images 1-5, objects 8, 14 and 21 (the gelatin box, the mug, the foam brick)."""
    root = tmp_path_factory.mktemp("bop_ycbv")
    assert main(["convert-ycbv", str(ycbv_dir / "data" / "0000"), str(root)]) == 0
    return root


@pytest.mark.slow
def test_pose_on_a_bop_image_reports_errors_against_its_truth(bop_ycbv, capsys, tmp_path):
    """``--bop DATASET --scene S --image I --object O``: the split's frame, model and
    mask_visib; the truth is scene_gt's, and the overlay is drawn on the image (the frame and
    the mug of the --ycbv test)."""
    args = ["pose", "--bop", str(bop_ycbv), "--scene", "0", "--image", "1", "--object", "14"]
    assert main([*args, "--json", "--out", str(tmp_path)]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["bop"] == {
        "dataset": str(bop_ycbv), "split": "test", "scene_id": 0, "im_id": 1, "obj_id": 14,
        "gt_index": 1, "instances": 1, "visib_fract": 1.0, "segment": "mask_visib",
        "model_points": 2621,
    }  # fmt: skip
    split = jr.io.read_bop(bop_ycbv, scenes=[0])
    (target,) = [t for t in split.targets(0, 1) if t.obj_id == 14]
    np.testing.assert_allclose(report["truth"], target.camera_T_object, atol=1e-5)
    pose, model = np.array(report["pose"]), split.models[14].points
    at_pose = model @ pose[:3, :3].T + pose[:3, 3]
    at_truth = model @ target.camera_T_object[:3, :3].T + target.camera_T_object[:3, 3]
    add_mm = 1e3 * np.linalg.norm(at_pose - at_truth, axis=1).mean()
    assert report["add_mm"] == pytest.approx(add_mm, abs=0.01)
    assert report["add_s_mm"] < 0.1 * split.models[14].diameter * 1e3
    overlay = np.asarray(Image.open(tmp_path / "model_overlay.png"))
    changed = (overlay != np.asarray(split.frame(0, 1).rgb)).any(-1)
    assert changed[split.mask(target)].mean() > 0.8
    assert main(args) == 0  # the printed report says the errors too
    out = capsys.readouterr().out
    assert f"error vs truth: translation {report['translation_error_mm']:.2f} mm" in out
    assert f"ADD-S {report['add_s_mm']:.2f} mm" in out


def test_pose_on_a_bop_image_names_what_exists_when_asked_for_what_does_not(bop_ycbv, capsys):
    bop = ["pose", "--bop", str(bop_ycbv)]
    cases = [
        (["--scene", "7", "--image", "1", "--object", "14"],
         "no scene folders for [7] (it has [0])"),
        (["--scene", "0", "--image", "9", "--object", "14"],
         "--image 9 is not in scene 0 of " + str(bop_ycbv / "test") + ": its images with "
         "targets are 1-5"),
        (["--scene", "0", "--image", "1", "--object", "2"],
         "--object 2 is not in image 1 of scene 0: it holds objects 8, 14, 21"),
        (["--scene", "0", "--image", "1"], "--bop DATASET needs --object"),
        (["--scene", "zero", "--image", "1", "--object", "14"], "integer id, got 'zero'"),
        (["--scene", "0", "--image", "1", "--object", "14", "--split", "val"],
         "no such split folder"),
        (["--scene", "0", "--image", "1", "--object", "14", "--symmetry", "box"],
         "--symmetry cannot be given with --bop"),
        (["--scene", "0", "--image", "1", "--object", "14", "--model", "m.ply"],
         "--model cannot be given with --bop"),
    ]  # fmt: skip
    for extra, message in cases:
        assert main([*bop, *extra]) == 2, extra
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and message in err, (extra, err)
    assert main(["pose", "--image", "1"]) == 2
    assert "--image is for --bop datasets" in capsys.readouterr().err
    assert main(["pose", "--json"]) == 2
    assert "give --scene FILE, --ycbv PREFIX or --bop DATASET" in capsys.readouterr().err


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
