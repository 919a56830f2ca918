"""BOP data in and out: a synthetic split written by `jaxreg.synth.write_bop_split` reads back
through `jaxreg.io.read_bop` with the scenes' own frames, poses, masks and symmetries;
hand-broken copies raise a `ValueError` naming the file; result CSVs round-trip and follow the
BOP19 row format."""

import json
import shutil

import numpy as np
import pytest
from PIL import Image

import jaxreg as jr
from jaxreg.synth.bop import DEPTH_SCALE, image_scene

OBJECTS = ("box", "cylinder")
SEED = 3


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """One scene of two images (box, cylinder), with the sensor's noise."""
    root = tmp_path_factory.mktemp("bop") / "synthetic"
    return jr.synth.write_bop_split(root, objects=OBJECTS, scenes=1, images_per_scene=2, seed=SEED)


def _matrix(pose) -> np.ndarray:
    return np.asarray(pose.as_matrix(), dtype=np.float64)


def test_split_reads_back_as_written(written):
    split = jr.io.read_bop(written)
    assert split.images == [(1, 0), (1, 1)]
    assert sorted(split.models) == [1, 3]
    targets = split.targets()
    assert [(t.scene_id, t.im_id, t.obj_id, t.gt_index) for t in targets] == [
        (1, 0, 1, 0),
        (1, 1, 3, 0),
    ]
    for k, target in enumerate(targets):
        scene = image_scene(SEED, k, OBJECTS)
        frame = split.frame(target.scene_id, target.im_id)
        truth, read = np.asarray(scene.frame.depth), np.asarray(frame.depth)
        np.testing.assert_array_equal(np.isnan(read), np.isnan(truth))
        quantum = DEPTH_SCALE * 1e-3  # metres per count
        assert np.nanmax(np.abs(read - truth)) <= quantum / 2 + 1e-6
        for key in ("fx", "fy", "cx", "cy"):
            assert float(getattr(frame.intrinsics, key)) == float(
                getattr(scene.frame.intrinsics, key)
            )
        assert frame.intrinsics.shape == scene.frame.intrinsics.shape
        np.testing.assert_array_equal(np.asarray(frame.rgb), np.asarray(scene.frame.rgb))
        base_T_camera = _matrix(scene.frame.base_T_camera)
        np.testing.assert_allclose(_matrix(frame.base_T_camera), base_T_camera, atol=1e-6)
        expected = np.linalg.inv(base_T_camera) @ _matrix(scene.truth)
        np.testing.assert_allclose(target.camera_T_object, expected, atol=1e-9)
        np.testing.assert_array_equal(split.mask(target), scene.mask)
        assert target.visib_fract == pytest.approx(1.0, abs=0.02)

        model = split.models[target.obj_id]
        np.testing.assert_allclose(model.points, scene.model.vertices, atol=1e-8)
        np.testing.assert_array_equal(model.mesh.faces, scene.model.faces)
        gaps = np.linalg.norm(model.points[:, None] - model.points[None], axis=-1)
        assert model.diameter == pytest.approx(gaps.max(), abs=1e-8)
        np.testing.assert_allclose(model.symmetry.rotations, scene.symmetry.rotations, atol=1e-12)
        if scene.symmetry.axis is None:
            assert model.symmetry.axis is None
        else:
            np.testing.assert_allclose(model.symmetry.axis, scene.symmetry.axis, atol=1e-12)


def test_symmetry_transforms_are_bops_discretisation(written):
    models = jr.io.read_bop(written).models
    box = models[1].symmetry_transforms
    np.testing.assert_allclose(box[:, :3, :3], models[1].symmetry.rotations, atol=1e-12)
    np.testing.assert_array_equal(box[:, :3, 3], 0.0)
    cylinder = models[3].symmetry_transforms
    # the identity and the half turn about x, each with ceil(pi / 0.01) = 315 turns about z
    assert cylinder.shape == (2 * 315, 4, 4)
    np.testing.assert_allclose(cylinder[0], np.eye(4), atol=1e-12)
    angles = np.arctan2(cylinder[:315, 1, 0], cylinder[:315, 0, 0]) % (2 * np.pi)
    np.testing.assert_allclose(np.sort(angles), 2 * np.pi * np.arange(315) / 315, atol=1e-9)
    flipped = cylinder[315:, :3, :3]
    np.testing.assert_allclose(flipped[:, 2, 2], -1.0, atol=1e-12)  # z -> -z: the half turn
    for transform in cylinder[::50]:  # each maps the can's rims onto themselves
        moved = models[3].points @ transform[:3, :3].T + transform[:3, 3]
        radius = np.linalg.norm(moved[:, :2], axis=1)
        assert np.all((radius < 1e-9) | (np.abs(radius - 0.035) < 1e-8))
        np.testing.assert_allclose(np.abs(moved[:, 2]), 0.06, atol=1e-8)


def test_targets_without_the_bop19_list_are_every_instance(written, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(written, copy)
    (copy / "test_targets_bop19.json").unlink()
    split = jr.io.read_bop(copy)
    assert [(t.im_id, t.obj_id) for t in split.targets()] == [(0, 1), (1, 3)]
    only_cylinder = jr.io.read_bop(copy, objects=[3])
    assert only_cylinder.images == [(1, 1)] and sorted(only_cylinder.models) == [3]
    assert [t.obj_id for t in only_cylinder.targets(1)] == [3]
    with pytest.raises(ValueError, match="no targets .* for objects \\[2\\]"):
        jr.io.read_bop(written, objects=[2])


def _rewrite_json(path, change):
    content = json.loads(path.read_text())
    change(content)
    path.write_text(json.dumps(content))


def _short_rotation(content):
    content["0"][0]["cam_R_m2c"] = content["0"][0]["cam_R_m2c"][:8]


BREAKS = {
    "missing scene_gt": (
        lambda root: (root / "test/000001/scene_gt.json").unlink(),
        "scene_gt.json: no such file",
    ),
    "malformed JSON": (
        lambda root: (root / "test/000001/scene_camera.json").write_text('{"0": {"cam_K": [1, 2'),
        "scene_camera.json: not valid JSON",
    ),
    "wrong-length cam_R": (
        lambda root: _rewrite_json(root / "test/000001/scene_gt.json", _short_rotation),
        r"scene_gt.json: image 0 instance 0: cam_\*_m2c rotation must be a list of 9 finite "
        "numbers, got 8 values",
    ),
    "missing model PLY": (
        lambda root: (root / "models/obj_000003.ply").unlink(),
        "obj_000003.ply: no such file",
    ),
    "model without diameter": (
        lambda root: _rewrite_json(
            root / "models/models_info.json", lambda c: c["1"].pop("diameter")
        ),
        "models_info.json: object 1: diameter must be a positive number",
    ),
    "visibility of another instance count": (
        lambda root: _rewrite_json(
            root / "test/000001/scene_gt_info.json", lambda c: c.update({"0": []})
        ),
        "scene_gt_info.json: image 0 lists 0 instances, scene_gt.json 1",
    ),
    "missing split": (lambda root: shutil.rmtree(root / "test"), "no such split folder"),
}


@pytest.mark.parametrize("name", sorted(BREAKS))
def test_broken_copies_name_the_file(written, tmp_path, name):
    copy = tmp_path / "copy"
    shutil.copytree(written, copy)
    jr.io.read_bop(copy)  # intact, the copy reads
    breaks, message = BREAKS[name]
    breaks(copy)
    with pytest.raises(ValueError, match=message):
        jr.io.read_bop(copy)


def test_a_colour_depth_image_is_refused_when_read(written, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(written, copy)
    path = copy / "test/000001/depth/000001.png"
    Image.fromarray(np.zeros((480, 848, 3), np.uint8)).save(path)
    split = jr.io.read_bop(copy)
    split.frame(1, 0)  # the other image is intact
    with pytest.raises(ValueError, match="depth/000001.png: a BOP depth image must be one 16-bit"):
        split.frame(1, 1)


def _results(count: int) -> list:
    rng = np.random.default_rng(0)
    rotations = np.linalg.qr(rng.normal(size=(count, 3, 3)))[0]
    rotations[:, :, 0] *= np.sign(np.linalg.det(rotations))[:, None]  # proper rotations
    return [
        jr.io.BopResult(
            scene_id=int(rng.integers(1, 50)),
            im_id=int(rng.integers(0, 2000)),
            obj_id=int(rng.integers(1, 30)),
            score=float(rng.uniform()),
            R=rotations[k],
            t=rng.uniform(-0.3, 1.5, 3),
            time=float(rng.uniform(0.01, 3.0)) if k else -1.0,
        )
        for k in range(count)
    ]


def test_results_round_trip(tmp_path):
    results = _results(5)
    path = jr.io.write_bop_results(tmp_path / "results.csv", results)
    back = jr.io.read_bop_results(path)
    assert len(back) == len(results)
    for ours, read in zip(results, back, strict=True):
        assert (read.scene_id, read.im_id, read.obj_id) == (ours.scene_id, ours.im_id, ours.obj_id)
        assert (read.score, read.time) == (ours.score, ours.time)
        np.testing.assert_array_equal(read.R, ours.R)
        np.testing.assert_allclose(read.t, ours.t, rtol=1e-15, atol=0)


def test_results_csv_is_bops_format(tmp_path):
    # The toolkit's inout.save_bop_results writes the header, then per estimate
    # "{scene_id},{im_id},{obj_id},{score},{R},{t},{time}" with R (row-major) and t (mm)
    # each joined by single spaces; load_bop_results splits on commas and whitespace.
    rotation = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    result = jr.io.BopResult(2, 17, 5, 0.75, rotation, np.array([0.01, -0.02, 0.5]), 0.125)
    path = jr.io.write_bop_results(tmp_path / "one.csv", [result])
    header, row = path.read_text().splitlines()
    assert header == "scene_id,im_id,obj_id,score,R,t,time"
    assert row == "2,17,5,0.75,0.0 -1.0 0.0 1.0 0.0 0.0 0.0 0.0 1.0,10.0 -20.0 500.0,0.125"


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("1,0,3,0.5,1 0 0 0 1 0 0 0 1,1 2 3", "line 3 has 6 comma-separated fields"),
        ("1,0,3,0.5,1 0 0 0 1 0 0 0,1 2 3,-1", "line 3: R must be 9 finite numbers"),
        (
            "1,0,x,0.5,1 0 0 0 1 0 0 0 1,1 2 3,-1",
            "line 3: scene_id, im_id, obj_id must be integers",
        ),
        ("1,0,3,0.5,1 0 0 0 1 0 0 0 1,1 nan 3,-1", "line 3: t must be 3 finite numbers"),
    ],
)
def test_a_bad_results_row_names_its_line(tmp_path, row, message):
    path = jr.io.write_bop_results(tmp_path / "results.csv", _results(1))
    path.write_text(path.read_text() + row + "\n")
    with pytest.raises(ValueError, match=f"results.csv: {message}"):
        jr.io.read_bop_results(path)


def test_a_result_with_a_bad_pose_is_not_written(tmp_path):
    bad = jr.io.BopResult(1, 0, 1, 1.0, np.eye(4), np.zeros(3))
    with pytest.raises(ValueError, match=r"result 0: R must be \(3, 3\)"):
        jr.io.write_bop_results(tmp_path / "bad.csv", [bad])


# ------------------------------------------------------------------------------------------
# YCB-Video frames written as a BOP split (jr.io.ycbv_to_bop)
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ycbv_split(ycbv_dir, tmp_path_factory):
    """The shipped YCB-Video frames converted: (their read_ycbv frames, the BOP root)."""
    root = tmp_path_factory.mktemp("ycbv") / "ycbv_bop"
    assert jr.io.ycbv_to_bop(ycbv_dir, root) == root / "test"
    return jr.io.read_ycbv(ycbv_dir), root


def test_ycbv_frames_read_back_through_read_bop(ycbv_dir, ycbv_split):
    """Counts, ids, depth counts, colour, intrinsics, truth, masks and point models."""
    frames, root = ycbv_split
    split = jr.io.read_bop(root)
    expected = [(int(f.name[:4]), int(f.name[5:])) for f in frames]
    assert split.images == expected and len(expected) == 10
    targets = split.targets()
    assert len(targets) == sum(len(f.instances) for f in frames) == 35
    assert sorted(split.models) == sorted({i.class_index for f in frames for i in f.instances})
    for frame, key in zip(frames, expected, strict=True):
        rows = split.targets(*key)
        assert [t.obj_id for t in rows] == [i.class_index for i in frame.instances]
        bop_frame = split.frame(*key)
        np.testing.assert_array_equal(bop_frame.rgb, frame.frame.rgb)
        np.testing.assert_array_equal(bop_frame.intrinsics.K, frame.frame.intrinsics.K)
        # BOP's depth unit is YCB-Video's (0.1 mm): the dataset's counts, unchanged
        with Image.open(ycbv_dir / "data" / f"{frame.name}-depth.png") as image:
            counts = np.asarray(image).astype(np.float64)
        np.testing.assert_allclose(split.depth(*key), counts * 1e-4, rtol=1e-12)
        for target, instance in zip(rows, frame.instances, strict=True):
            truth = np.asarray(instance.truth.as_matrix(), np.float64)
            np.testing.assert_allclose(target.camera_T_object, truth, atol=1e-9)
            np.testing.assert_array_equal(split.mask(target), frame.label == instance.class_index)
            model = split.models[target.obj_id]
            assert model.mesh is None  # points only: VSD cannot render it
            np.testing.assert_allclose(model.points, instance.model_points, atol=1e-9)
    for model in split.models.values():
        gaps = np.linalg.norm(model.points[:, None] - model.points[None], axis=-1)
        assert model.diameter == pytest.approx(gaps.max(), abs=1e-9)
        info = json.loads((root / "models" / "models_info.json").read_text())[str(model.obj_id)]
        np.testing.assert_allclose(
            [info[f"min_{a}"] for a in "xyz"], 1e3 * model.points.min(0), atol=1e-9
        )
        np.testing.assert_allclose(
            [info[f"size_{a}"] for a in "xyz"], 1e3 * np.ptp(model.points, axis=0), atol=1e-9
        )


def test_ycbv_conversion_adds_frames_to_a_split(ycbv_dir, ycbv_split, tmp_path):
    """One sequence, then one frame of the other: the split holds both; converting a frame
    again replaces it."""
    frames, whole = ycbv_split
    root = tmp_path / "grown"
    jr.io.ycbv_to_bop(ycbv_dir / "data" / "0000", root)
    for _ in range(2):
        jr.io.ycbv_to_bop(ycbv_dir / "data" / "0001" / "000003", root)
    split = jr.io.read_bop(root)
    assert split.images == [(0, k) for k in range(1, 6)] + [(1, 3)]
    reference = jr.io.read_bop(whole)
    for key in split.images:
        assert [t.obj_id for t in split.targets(*key)] == [
            t.obj_id for t in reference.targets(*key)
        ]
    with pytest.raises(ValueError, match="depth_scale must be positive"):
        jr.io.ycbv_to_bop(ycbv_dir / "data" / "0000", root, depth_scale=0)
    with pytest.raises(ValueError, match="larger depth_scale"):
        jr.io.ycbv_to_bop(ycbv_dir / "data" / "0000" / "000001", tmp_path / "x", depth_scale=0.01)
    assert not (tmp_path / "x").exists()  # checked before anything is written
