"""Synthetic tabletop scenes (jaxreg.synth) and the stereo sensor model (StereoSensor).

The scenes' truth is checked against their own pixels (noise-free object pixels lifted through
the intrinsics and the hand-eye pose lie on the mesh at `truth`); the sensor model is checked
on planes at known distances and a step edge, where every prediction (axial spread, the
invalid band, the occlusion shadow, flying pixels, dark and grazing holes) has a closed form.
Images are small (at most 424x240) except where the default 848x480 is the point.
"""

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import jaxreg as jr
from jaxreg import synth
from jaxreg.geometry.lie import se3_to_matrix

SENSOR = synth.StereoSensor.d435()
FX = float(SENSOR.intrinsics().fx)  # the D435's focal length at 848x480, ~447 px
SMALL = SENSOR.intrinsics(424, 240)


def crop(width: int, height: int) -> jr.Intrinsics:
    """A `width` x `height` window about the optical axis of the D435 at 848x480: the real
    camera's focal length (so its real disparity noise) on few pixels."""
    return jr.Intrinsics(FX, FX, (width - 1) / 2, (height - 1) / 2, width, height)


def plane(z: float, tilt_deg: float = 0.0) -> trimesh.Trimesh:
    """A 4 m square slab whose front face passes through (0, 0, z), facing the camera at the
    origin (camera frame = base frame), turned by `tilt_deg` about the camera's y axis."""
    slab = trimesh.creation.box((4.0, 4.0, 0.01))
    slab.apply_translation((0.0, 0.0, 0.005))
    turn = trimesh.transformations.rotation_matrix(np.radians(tilt_deg), (0, 1, 0))
    slab.apply_transform(turn)
    return slab.apply_translation((0.0, 0.0, z))


def surface_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """`(N,)` distance from each point to the nearest point of `mesh` (brute force over the
    faces with trimesh's exact point-triangle closest point; no spatial index needed)."""
    faces = len(mesh.faces)
    out = []
    for chunk in np.array_split(np.asarray(points, np.float64), max(1, len(points) // 48)):
        repeated = np.repeat(chunk, faces, axis=0)
        nearest = trimesh.triangles.closest_point(
            np.tile(mesh.triangles, (len(chunk), 1, 1)), repeated
        )
        out.append(np.linalg.norm(nearest - repeated, axis=1).reshape(len(chunk), faces).min(1))
    return np.concatenate(out)


def grey(*albedos: float) -> np.ndarray:
    """`(M, 3)` grey colours of the given luminances."""
    return np.repeat(np.asarray(albedos, float)[:, None], 3, axis=1)


def measured(meshes, intrinsics, colors=None, seed=0, sensor=SENSOR):
    rendering = synth.render(meshes, intrinsics, np.eye(4), colors)
    return rendering, sensor.measure(rendering, np.random.default_rng(seed))


@pytest.fixture(scope="module")
def scenes():
    """Per object: the noise-free and the noisy render of one seed at 424x240."""
    return {
        name: (
            synth.tabletop_scene(7, object=name, noise=False, intrinsics=SMALL),
            synth.tabletop_scene(7, object=name, intrinsics=SMALL),
        )
        for name in synth.OBJECTS
    }


# ------------------------------------------------------------------------------------------
# scenes
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", synth.OBJECTS)
def test_noise_free_object_pixels_lie_on_the_mesh_at_truth(scenes, name):
    exact, noisy = scenes[name]
    assert exact.mask.sum() > 300, f"{name} covers only {exact.mask.sum()} pixels"
    np.testing.assert_array_equal(exact.mask, noisy.mask)  # noise=False: the same scene
    np.testing.assert_array_equal(exact.labels, noisy.labels)
    points = np.asarray(exact.frame.points(exact.mask))[exact.mask]
    assert np.isfinite(points).all()
    object_points = np.asarray(exact.truth.inverse() @ jnp.asarray(points), np.float64)
    distance = surface_distance(exact.model, object_points)
    assert distance.max() < 1e-4, f"{name}: a pixel lies {distance.max() * 1e3:.3f} mm off"
    # the check can fail: the same pixels against the truth moved by 0.3 mm miss the mesh
    moved = jr.SE3.from_translation(jnp.array([3e-4, 3e-4, 3e-4])) @ exact.truth
    shifted = np.asarray(moved.inverse() @ jnp.asarray(points), np.float64)
    assert surface_distance(exact.model, shifted).max() > 1e-4
    # the model points are surface samples of the same mesh
    assert surface_distance(exact.model, exact.model_points[:100]).max() < 1e-5


@pytest.mark.parametrize("name", synth.OBJECTS)
def test_noisy_object_depth_spreads_as_the_model_predicts(scenes, name):
    exact, noisy = scenes[name]
    rendering = synth.render(
        [exact.model.copy().apply_transform(np.asarray(se3_to_matrix(exact.truth), float))],
        SMALL,
        np.asarray(se3_to_matrix(exact.frame.base_T_camera), float),
    )
    sigma = SENSOR.depth_sigma(rendering)
    depth = np.asarray(noisy.frame.depth, np.float64)
    inside = noisy.mask & np.isfinite(depth)
    inside &= np.abs(SENSOR.edge_jump(exact.exact_depth)) <= SENSOR.flying_min_jump_m
    assert inside.sum() > 200
    z = (depth - exact.exact_depth)[inside] / sigma[inside]
    assert abs(np.mean(z)) < 0.15
    assert 0.85 < np.std(z) < 1.15, f"{name}: standardised spread {np.std(z):.3f}"


def test_scene_symmetry_is_the_metrics_symmetry_and_maps_the_mesh_onto_itself(scenes):
    for name in synth.OBJECTS:
        exact = scenes[name][0]
        symmetry = exact.symmetry
        assert isinstance(symmetry, jr.Symmetry)
        samples = np.asarray(exact.model_points[:100], np.float64)
        turns = list(np.asarray(symmetry.rotations))
        if symmetry.axis is not None:  # a facet step about the axis maps the 64-gon exactly
            turns += [
                r
                @ trimesh.transformations.rotation_matrix(2 * np.pi / 64 * 5, symmetry.axis)[:3, :3]
                for r in turns
            ]
        for turn in turns:
            assert surface_distance(exact.model, samples @ turn.T).max() < 1e-5, name
        if not symmetry.is_symmetric:
            continue
        # the metrics forgive the symmetric turn, not a turn that is no symmetry
        est = exact.truth @ jr.SE3.from_rotation(jr.SO3.from_matrix(jnp.asarray(turns[-1])))
        t_error, r_error = jr.pose_error(est, exact.truth, symmetry=symmetry)
        assert float(t_error) < 1e-6 and float(r_error) < 1e-3
        assert float(jr.add(exact.model_points, est, exact.truth, symmetry=symmetry)) < 1e-5
        canonical = jr.canonicalise(est, exact.truth, symmetry)
        assert float(jr.rotation_error(canonical, exact.truth)) < 1e-3
        tipped = exact.truth @ jr.SE3.from_rotation(jr.SO3.from_y_radians(0.3))
        assert float(jr.pose_error(tipped, exact.truth, symmetry=symmetry)[1]) > 0.29
    mug = scenes["mug"][0]
    assert not mug.symmetry.is_symmetric
    half_turn = np.diag([-1.0, -1.0, 1.0])
    assert (
        surface_distance(mug.model, mug.model_points[:100] @ half_turn.T).max() > 0.01
    )  # the handle


def test_same_seed_same_scene_bit_for_bit():
    first = synth.tabletop_scene(3, object="mug", distractors=3)
    second = synth.tabletop_scene(3, object="mug", distractors=3)
    assert first.frame.depth.shape == (480, 848)  # the default D435 depth image
    np.testing.assert_array_equal(np.asarray(first.frame.depth), np.asarray(second.frame.depth))
    np.testing.assert_array_equal(np.asarray(first.frame.rgb), np.asarray(second.frame.rgb))
    np.testing.assert_array_equal(first.truth.wxyz_xyz, second.truth.wxyz_xyz)
    np.testing.assert_array_equal(first.model_points, second.model_points)
    other = synth.tabletop_scene(4, object="mug", distractors=3, intrinsics=SMALL)
    assert not np.allclose(other.truth.wxyz_xyz, first.truth.wxyz_xyz)


@pytest.mark.parametrize("seed", range(3))
def test_distractors_never_hide_the_target(seed):
    scene = synth.tabletop_scene(seed, object="box", distractors=6, noise=False, intrinsics=SMALL)
    assert set(np.unique(scene.labels)) >= set(range(2 + 6))  # every distractor is in view
    # the target alone, from the same camera: the same visible pixels
    table_and_target = synth.render(
        [
            trimesh.creation.box((1.2, 0.8, 0.04)).apply_translation((0, 0, -0.02)),
            scene.model.copy().apply_transform(np.asarray(se3_to_matrix(scene.truth), float)),
        ],
        SMALL,
        np.asarray(se3_to_matrix(scene.frame.base_T_camera), float),
    )
    assert np.sum(scene.mask != (table_and_target.labels == 1)) <= 2


def test_explicit_object_pose_camera_and_noise_seed():
    """A study's hooks: the seed's own poses passed back render the same scene; a moved
    target lies on its mesh at the new pose, seen from a given camera; `noise_seed` re-measures
    the same geometry (and defaults to the seed)."""
    base = synth.tabletop_scene(5, object="box", distractors=2, noise=False, intrinsics=SMALL)
    again = synth.tabletop_scene(
        5, object="box", distractors=2, noise=False, intrinsics=SMALL,
        base_T_object=base.truth, base_T_camera=np.asarray(se3_to_matrix(base.frame.base_T_camera)),
    )  # fmt: skip
    both = np.isfinite(base.exact_depth) & np.isfinite(again.exact_depth)
    assert np.sum(np.isfinite(base.exact_depth) != np.isfinite(again.exact_depth)) <= 2
    assert np.abs(base.exact_depth[both] - again.exact_depth[both]).max() < 1e-5
    moved = np.asarray(se3_to_matrix(base.truth), float)
    moved[:3, :3] = moved[:3, :3] @ trimesh.transformations.rotation_matrix(0.4, (0, 0, 1))[:3, :3]
    moved[:2, 3] += (0.02, -0.01)
    camera = synth.look_at(moved[:3, 3] + (0.0, -0.45, 0.35), moved[:3, 3])
    scene = synth.tabletop_scene(
        5, object="box", noise=False, intrinsics=SMALL, base_T_object=moved, base_T_camera=camera
    )
    np.testing.assert_allclose(se3_to_matrix(scene.truth), moved, atol=1e-6)
    np.testing.assert_allclose(se3_to_matrix(scene.frame.base_T_camera), camera, atol=1e-6)
    on_target = np.asarray(scene.frame.points(scene.mask))[scene.mask]
    in_object = (on_target - moved[:3, 3]) @ moved[:3, :3]
    assert len(in_object) > 500 and surface_distance(scene.model, in_object).max() < 1e-4
    first = synth.tabletop_scene(5, intrinsics=SMALL, distractors=0)
    same = synth.tabletop_scene(5, intrinsics=SMALL, distractors=0, noise_seed=5)
    other = synth.tabletop_scene(5, intrinsics=SMALL, distractors=0, noise_seed=6)
    np.testing.assert_array_equal(np.asarray(first.frame.depth), np.asarray(same.frame.depth))
    np.testing.assert_array_equal(first.exact_depth, other.exact_depth)
    a, b = np.asarray(first.frame.depth), np.asarray(other.frame.depth)
    valid = np.isfinite(a) & np.isfinite(b)
    assert np.mean(a[valid] != b[valid]) > 0.5
    with pytest.raises(ValueError, match="base_T_camera"):
        synth.tabletop_scene(5, intrinsics=SMALL, base_T_camera=np.eye(3))


def test_bad_scene_requests_raise():
    with pytest.raises(ValueError, match="unknown object"):
        synth.tabletop_scene(object="teapot")
    with pytest.raises(ValueError, match="distractors"):
        synth.tabletop_scene(distractors=9)
    with pytest.raises(ValueError, match="at least one mesh"):
        synth.render([], SMALL, np.eye(4))
    with pytest.raises(ValueError, match="colors"):
        synth.render([plane(1.0)], SMALL, np.eye(4), np.ones((2, 3)))


# ------------------------------------------------------------------------------------------
# the sensor model on planes and a step edge
# ------------------------------------------------------------------------------------------


def test_axial_noise_grows_with_distance_as_the_model_says():
    # a 2 degree tilt spreads each plane over a few millimetres of depth, so the 1 mm depth
    # unit's rounding error takes every phase (the model's uniform-error variance)
    intrinsics = crop(160, 100)
    spreads = []
    for z in (0.3, 0.6, 1.2, 2.4):
        rendering, depth = measured([plane(z, tilt_deg=2.0)], intrinsics, grey(0.6), int(10 * z))
        valid = np.isfinite(depth)
        assert valid.mean() > 0.5
        error = (depth - rendering.depth)[valid]
        predicted = SENSOR.depth_sigma(rendering)[valid]
        assert np.median(predicted) == pytest.approx(SENSOR.axial_sigma(z, FX), rel=0.02)
        assert abs(np.mean(error)) < 0.25 * np.mean(predicted)  # the depth unit's rounding
        assert np.std(error / predicted) == pytest.approx(1.0, abs=0.05), z
        spreads.append(np.std(error))
    # 8x the distance: ~48x the spread (64x for the disparity term, the 1 mm depth unit's
    # constant share aside), far from the 8x of noise proportional to distance
    model_ratio = SENSOR.axial_sigma(2.4, FX) / SENSOR.axial_sigma(0.3, FX)
    assert model_ratio > 40
    assert spreads[-1] / spreads[0] == pytest.approx(model_ratio, rel=0.07)
    # the covariance model handed to jaxreg.uncertainty has the same disparity term
    noise = SENSOR.depth_noise(intrinsics)
    assert float(noise.axial_sigma(2.4)) == pytest.approx(SENSOR.axial_sigma(2.4, FX), rel=0.01)


def test_slanted_plane_spreads_with_the_lateral_term():
    rendering, depth = measured([plane(0.5, tilt_deg=60.0)], crop(160, 100), grey(0.8), seed=1)
    sigma = SENSOR.depth_sigma(rendering)
    assert (sigma > 1.3 * SENSOR.axial_sigma(rendering.depth, FX)).all()  # lateral dominates
    valid = np.isfinite(depth)
    assert valid.mean() > 0.5
    z = (depth - rendering.depth)[valid] / sigma[valid]
    assert np.std(z) == pytest.approx(1.0, abs=0.08)


def test_too_near_and_left_band_are_holes():
    intrinsics = crop(200, 60)
    focal_baseline = FX * SENSOR.baseline_m
    _, near = measured([plane(0.95 * focal_baseline / SENSOR.max_disparity_px)], intrinsics)
    assert np.isnan(near).all()  # nearer than the 126-disparity search reaches
    for z in (0.2, 0.4):
        _, depth = measured([plane(z)], intrinsics, grey(0.8))
        band = focal_baseline / z - 0.5  # the right imager sees column u at u - fx B / z
        columns = np.arange(intrinsics.width)
        assert np.isnan(depth[:, columns < band]).all()
        assert np.isfinite(depth[:, columns > band + 1]).all()


def test_step_edge_casts_a_shadow_and_flying_pixels_only_at_the_edge():
    intrinsics = crop(240, 120)
    z_near, z_far = 0.6, 1.0
    # a 12 x 10 cm card at 0.6 m before a wall at 1 m: ~89 x 74 px about the centre
    card = trimesh.creation.box((0.12, 0.10, 0.01)).apply_translation((0.0, 0.0, z_near + 0.005))
    sensor = synth.StereoSensor.d435(flying_probability=0.6)
    rendering, depth = measured([card, plane(z_far)], intrinsics, grey(0.8, 0.8), 2, sensor)
    on_card = rendering.labels == 0
    columns = np.flatnonzero(on_card.any(axis=0))
    rows = np.flatnonzero(on_card.any(axis=1))
    left = columns[0]
    middle_rows = slice(rows[0] + 2, rows[-1] - 1)
    # the wall left of the card is hidden from the right imager: fx B (1/z_near - 1/z_far) px
    width = FX * SENSOR.baseline_m * (1 / z_near - 1 / z_far)
    u = np.arange(intrinsics.width)
    shadow = (u >= left - width + 1) & (u < left - 1)
    clear = (u < left - width - 1) & (u > FX * SENSOR.baseline_m / z_far + 2)
    assert np.isnan(depth[middle_rows][:, shadow]).all()
    assert np.isfinite(depth[middle_rows][:, clear]).mean() > 0.99
    # flying pixels: depths between the surfaces, only where the model puts them
    jump = np.abs(sensor.edge_jump(rendering.depth)) > sensor.flying_min_jump_m
    sigma_far = SENSOR.axial_sigma(z_far, FX)
    between = (depth > z_near + 6 * sigma_far) & (depth < z_far - 6 * sigma_far)
    assert not between[~jump].any()
    edge = jump & np.isfinite(depth)
    # a mixed pixel lands between the surfaces unless t is within ~6 sigma of either end
    spread = 6 * sigma_far / (z_far - z_near)
    expected = sensor.flying_probability * (1 - 2 * spread)
    assert between[edge].mean() == pytest.approx(expected, abs=0.1)


def test_dark_and_grazing_surfaces_lose_their_depth():
    intrinsics = crop(160, 100)
    lo, hi = SENSOR.signal_range
    _, dark = measured([plane(0.8)], intrinsics, grey(0.9 * lo))
    _, bright = measured([plane(0.8)], intrinsics, grey(1.1 * hi))
    _, middle = measured([plane(0.8)], intrinsics, grey((lo + hi) / 2), seed=3)
    visible = np.isfinite(bright)  # the left band aside
    assert visible.mean() > 0.8
    assert np.isnan(dark[visible]).all()
    assert np.isfinite(middle[visible]).mean() == pytest.approx(0.5, abs=0.03)
    # a wall seen at 76-96 degrees incidence: no return where albedo * cos(incidence) < lo,
    # always one (in the right imager's view) where it exceeds hi
    rendering, grazing = measured([plane(1.5, tilt_deg=86.0)], intrinsics, grey(0.9))
    signal = 0.9 * np.abs(np.sum(rendering.normals * rendering.rays, axis=-1))
    signal /= np.linalg.norm(rendering.rays, axis=-1)
    weak, strong = signal < lo, signal > hi
    assert weak.sum() > 100 and strong.sum() > 100
    assert np.isnan(grazing[weak]).all()
    assert np.isfinite(grazing[strong]).mean() > 0.95
