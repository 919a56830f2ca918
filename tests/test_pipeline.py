"""estimate_pose on a rendered tabletop frame, and each stage's failure signature built into it:
a stray table slab, depth holes over the object, phantom edge points, the object missing."""

import jax
import numpy as np
import pytest
import trimesh

from jaxreg.camera import RGBDFrame
from jaxreg.geometry.metrics import add_s
from jaxreg.pipeline import estimate_pose


@pytest.fixture(scope="module")
def scene():
    from jaxreg.synth import tabletop_scene

    scene = tabletop_scene(4, object="box", distractors=0)
    samples, _ = trimesh.sample.sample_surface(scene.model, 20_000, seed=0)
    symmetry = scene.symmetry
    return scene, samples.astype(np.float32), symmetry


def _with_depth(frame: RGBDFrame, depth: np.ndarray) -> RGBDFrame:
    return RGBDFrame(depth.astype(np.float32), frame.intrinsics, frame.rgb, frame.base_T_camera)


def _height_depth(frame: RGBDFrame, height: float) -> np.ndarray:
    """(H, W) z-depth at which every pixel's ray meets the plane z = height (base frame)."""
    rays = np.asarray(frame.intrinsics.pixel_rays(), np.float64)
    pose = frame.base_T_camera
    rotation, origin = np.asarray(pose.rotation().as_matrix()), np.asarray(pose.translation())
    return (height - origin[2]) / (rays @ rotation.T)[..., 2]


def _centre(mask):
    rows, cols = np.nonzero(mask)
    return float(cols.mean()), float(rows.mean())


def test_finds_the_box_with_error_bars_and_stage_diagnostics(scene):
    scene, model, symmetry = scene
    est = estimate_pose(scene.frame, model, symmetry=symmetry)
    assert est.failed_stage is None and est.success
    assert float(add_s(scene.model_points, est.pose, scene.truth)) < 0.005
    assert set(est.stages) == {"segment", "lift", "register"}
    assert all(stage["ms"] > 0 for stage in est.stages.values())
    assert est.stages["lift"]["valid_depth_fraction"] > 0.8
    # the covariance is a finite, positive definite error bar of sub-millimetre order
    eig = np.linalg.eigvalsh(est.covariance)
    assert np.all(np.isfinite(eig)) and eig.min() > 0
    assert np.sqrt(np.diag(est.covariance)[:3]).max() < 0.002
    assert 0.5 < est.inlier_fraction <= 1 and est.inlier_rmse < 0.004
    # the mask covers the target's pixels, little else
    assert np.mean(est.mask[scene.mask]) > 0.6 and np.mean(scene.mask[est.mask]) > 0.9


def test_a_new_model_runs_the_programs_already_compiled(scene):
    """A model of another point count and symmetry group after the first: not one XLA
    compilation (jax.monitoring's compile events), and the object is found."""
    box, model, symmetry = scene
    estimate_pose(box.frame, model, symmetry=symmetry)  # compiled here or by a test before
    other = trimesh.sample.sample_surface(box.model, 6000, seed=3)[0].astype(np.float32)
    compiles = []

    def listen(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        est = estimate_pose(box.frame, other, symmetry=None)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert compiles == []
    assert est.failed_stage is None
    assert float(add_s(box.model_points, est.pose, box.truth)) < 0.005


def test_models_of_every_object_and_point_count_give_the_programs_a_few_shapes(scene):
    """Every array the compiled register stage takes from a model (points, normals, the
    sparse screen, both grids' tables) is padded to a few size classes: the box at 6k, 10k
    and 20k points shares one, and the four objects at 6k and 20k points fall in four (each
    sampling had its own), padded with NaN points and zero normals after the model's rows."""
    from jaxreg.pipeline._register_stage import _prepare_model
    from jaxreg.synth import OBJECTS, object_mesh

    def shapes(prepared):
        arrays = (prepared.points, prepared.normals, prepared.screen, prepared.grid)
        return tuple(np.shape(a) for a in jax.tree.leaves((*arrays, prepared.fine_grid)))

    classes = {shapes(_prepare_model(scene[1], None, 0.004, 0.04, 0.015)): ["box 20k"]}
    for name in OBJECTS:
        mesh, _ = object_mesh(name)
        for count in (6000, 10_000, 20_000) if name == "box" else (6000, 20_000):
            points = trimesh.sample.sample_surface(mesh, count, seed=1)[0].astype(np.float32)
            prepared = _prepare_model(points, None, 0.004, 0.04, 0.015)
            classes.setdefault(shapes(prepared), []).append(f"{name} {count}")
    assert len(classes) <= 4, list(classes.values())
    boxes = {"box 20k", "box 6000", "box 10000", "box 20000"}
    assert any(boxes <= set(members) for members in classes.values())
    real = np.isfinite(prepared.points).all(1)
    assert 1000 < real.sum() < len(real) and not real[real.argmin() :].any()  # rows, then NaN
    assert not np.any(prepared.normals[~real])


def test_nan_model_rows_count_nowhere_in_the_images_judgement(scene):
    """visibility's counts (confirmed, contradicted, occluded, unknown, self-hidden) of a
    model padded with NaN rows are those of the model alone."""
    from jaxreg.pipeline.estimate import visibility

    box, model, _ = scene
    points = model[::20]
    padded = np.concatenate([points, np.full((200, 3), np.nan, np.float32)])
    alone = np.asarray(visibility(box.frame, box.truth, points, np.float32(0.01)))
    assert alone[0] > 100  # the true pose: much of the model confirmed
    np.testing.assert_array_equal(
        np.asarray(visibility(box.frame, box.truth, padded, np.float32(0.01))), alone
    )


def test_a_stray_table_slab_is_a_candidate_the_registration_rejects(scene):
    scene, model, symmetry = scene
    # a 2 cm board on the table beside the box, about its size in the image
    u, v = _centre(scene.mask)
    rows, cols = np.nonzero(scene.mask)
    width = cols.max() - cols.min()
    board = np.zeros_like(scene.mask)
    side = int(u + 1.2 * width) if u < scene.mask.shape[1] / 2 else int(u - 1.2 * width)
    board[int(v) - width // 2 : int(v) + width // 2, side - width // 2 : side + width // 2] = True
    board &= scene.labels == 0
    depth = np.where(board, _height_depth(scene.frame, 0.02), np.asarray(scene.frame.depth))
    est = estimate_pose(_with_depth(scene.frame, depth), model, symmetry=symmetry)
    assert est.failed_stage is None
    assert float(add_s(scene.model_points, est.pose, scene.truth)) < 0.005
    assert np.mean(est.mask[board]) < 0.05  # the board is not in the lifted segment
    # without the box, the board alone is not taken for it
    depth = np.where(scene.mask, _height_depth(scene.frame, 0.0), depth)
    missing = estimate_pose(_with_depth(scene.frame, depth), model, symmetry=symmetry)
    assert missing.pose is None and missing.failed_stage == "register"
    assert "the model is not there" in missing.reason


def test_depth_holes_over_the_object_fail_the_lift(scene):
    scene, model, symmetry = scene
    rng = np.random.default_rng(0)
    holes = scene.mask & (rng.random(scene.mask.shape) < 0.85)
    depth = np.where(holes, np.nan, np.asarray(scene.frame.depth))
    est = estimate_pose(_with_depth(scene.frame, depth), model, pixel=_centre(scene.mask))
    assert est.failed_stage == "lift" and est.pose is None
    assert "valid depth" in est.reason
    assert est.stages["lift"]["valid_depth_fraction"] < 0.5


def test_phantom_edge_points_are_removed_as_flying_pixels(scene):
    scene, model, symmetry = scene
    depth = np.asarray(scene.frame.depth).copy()
    mask = scene.mask
    edge_depth = np.full(depth.shape, np.nan)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0), (0, 2), (0, -2), (2, 0), (-2, 0)):
        shifted = np.roll(np.where(mask, depth, np.nan), (dy, dx), axis=(0, 1))
        edge_depth = np.where(np.isnan(edge_depth), shifted, edge_depth)
    band = ~mask & np.isfinite(edge_depth) & np.isfinite(depth) & (depth > edge_depth + 0.03)
    rng = np.random.default_rng(1)
    mix = rng.uniform(0.2, 0.8, depth.shape)
    phantom = np.where(band, edge_depth + mix * (depth - edge_depth), depth)
    clean = estimate_pose(scene.frame, model, symmetry=symmetry)
    est = estimate_pose(_with_depth(scene.frame, phantom), model, symmetry=symmetry)
    added = (
        est.stages["lift"]["flying_pixels_removed"] - clean.stages["lift"]["flying_pixels_removed"]
    )
    # the phantoms in the segment's footprint are removed as flying pixels; none is lifted
    assert band.sum() > 100 and added > 20
    assert np.mean(est.mask[band]) < 0.1
    assert est.failed_stage is None
    assert float(add_s(scene.model_points, est.pose, scene.truth)) < 0.005


def test_the_object_missing_makes_no_pose_claim(scene):
    scene, model, symmetry = scene
    rng = np.random.default_rng(2)
    table = _height_depth(scene.frame, 0.0) + rng.normal(0, 0.001, scene.mask.shape)
    depth = np.where(scene.mask, table, np.asarray(scene.frame.depth))
    est = estimate_pose(_with_depth(scene.frame, depth), model, symmetry=symmetry)
    assert est.pose is None and est.failed_stage == "segment"
    assert "nothing stands on the table" in est.reason
    assert np.isnan(est.covariance).all()


def test_bad_arguments_raise_clear_errors(scene):
    scene, model, _ = scene
    with pytest.raises(ValueError, match="RGBDFrame"):
        estimate_pose(np.zeros((480, 848)), model)
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        estimate_pose(scene.frame, model[:, :2])
    with pytest.raises(ValueError, match="at most one prompt"):
        estimate_pose(scene.frame, model, pixel=(1, 2), box=(0, 0, 5, 5))


def test_a_larger_box_of_a_similar_shape_is_not_taken_for_the_target(scene):
    """Seed 128: beside the 80 x 50 x 120 mm target stands an 89 x 61 x 114 mm box, which the
    box model fits as well by inlier fraction, residual and image support (it was claimed
    before the extent test); only its points reaching beyond the model tell them apart."""
    from jaxreg.pipeline._register_stage import _prepare_model, overhang
    from jaxreg.synth import tabletop_scene

    _, model, symmetry = scene
    other = tabletop_scene(128, object="box")
    rows, cols = np.nonzero(other.labels == 2)
    prompted = estimate_pose(
        other.frame,
        model,
        symmetry=symmetry,
        pixel=(float(np.median(cols)), float(np.median(rows))),
    )
    assert prompted.pose is None and prompted.failed_stage == "register"
    assert "beyond the model" in prompted.reason
    assert max(prompted.stages["register"]["overhang_mm"]) > 3
    est = estimate_pose(other.frame, model, symmetry=symmetry)
    assert est.failed_stage is None
    assert float(add_s(other.model_points, est.pose, other.truth)) < 0.005
    assert max(est.stages["register"]["overhang_mm"]) < 0
    # the measure itself: the model's own surface spans the model; a 10% larger copy reaches
    # 10% beyond it (a box's end faces hold more than 2% of its points)
    prepared = _prepare_model(model, None, 0.004, 0.04, 0.015)
    identity = np.array([1.0, 0, 0, 0, 0, 0, 0])
    assert np.all(overhang(prepared, identity, model) <= 0)
    larger = overhang(prepared, identity, 1.1 * model)
    assert np.allclose(larger, 0.1 * (prepared.bounds[1] - prepared.bounds[0]), atol=1e-3)


@pytest.mark.slow
def test_fifty_seeds_of_mixed_objects_are_found_within_5_mm_add_s():
    """The issue's bar: ADD-S < 5 mm in at least 95% of 50 frames (benchmarks/bench_pipeline.py
    prints the same study beside Open3D, with timings)."""
    from jaxreg.synth import OBJECTS, tabletop_scene

    errors = []
    for seed in range(50):
        scene = tabletop_scene(seed, object=OBJECTS[seed % len(OBJECTS)])
        samples, _ = trimesh.sample.sample_surface(scene.model, 20_000, seed=seed)
        symmetry = scene.symmetry
        est = estimate_pose(scene.frame, samples.astype(np.float32), symmetry=symmetry)
        ok = est.pose is not None
        errors.append(float(add_s(scene.model_points, est.pose, scene.truth)) if ok else np.inf)
    assert np.mean(np.asarray(errors) < 0.005) >= 0.95


def test_a_target_seen_from_above_is_a_candidate_though_far_from_its_visible_centroid(scene):
    """Seed 8: seen mostly from above, the box's visible centroid lies near its top, and its
    bottom edge is 97 mm from it (model radius 76 mm): the size test compares diameters."""
    from jaxreg.synth import tabletop_scene

    _, model, symmetry = scene
    frame8 = tabletop_scene(8, object="box")
    est = estimate_pose(frame8.frame, model, symmetry=symmetry)
    assert max(est.stages["segment"]["cluster_radii_mm"]) > 76 + 20
    assert est.failed_stage is None
    assert float(add_s(frame8.model_points, est.pose, frame8.truth)) < 0.005


def test_resting_starts_stand_the_model_on_the_table_on_each_principal_half_axis():
    import jax.numpy as jnp
    from jaxlie import SE3

    from jaxreg.pipeline._register_stage import _resting_starts
    from jaxreg.pipeline.segment import TablePlane

    rng = np.random.default_rng(0)
    model = (rng.uniform(-1, 1, (500, 3)) * [0.04, 0.025, 0.06]).astype(np.float32)
    axes = np.eye(3, dtype=np.float32)[:, [2, 0, 1]]  # largest extent first
    plane = TablePlane(jnp.array([0.0, 0.0, 1.0]), jnp.float32(-0.01), 0, 0.0)  # z = 0.01
    cloud = jnp.asarray(model + [0.1, 0.0, 0.08], jnp.float32)
    ok = jnp.ones(len(model), bool)
    eye = jnp.array([0.6, 0.0, 0.5])
    starts = _resting_starts(cloud, ok, jnp.asarray(model), jnp.asarray(axes), plane, eye, 4)
    assert starts.wxyz_xyz.shape == (24, 7)
    placed = SE3(starts.wxyz_xyz).inverse()  # base_T_object
    pts = np.asarray(jax.vmap(lambda T: T @ jnp.asarray(model))(placed))
    np.testing.assert_allclose(pts[..., 2].min(1), 0.01, atol=1e-5)  # lowest point on the table
    down = np.einsum("sij,j->si", np.asarray(placed.rotation().as_matrix()), [0, 0, 1])
    # six half-axes down, four headings each: the object's z axis up, down or level
    assert np.sum(np.isclose(down[:, 2], 1, atol=1e-5)) == 4
    assert np.sum(np.isclose(down[:, 2], -1, atol=1e-5)) == 4
    # NaN rows (a model padded to a bucketed size) change no start
    padded = jnp.concatenate([jnp.asarray(model), jnp.full((12, 3), jnp.nan)])
    again = _resting_starts(cloud, ok, padded, jnp.asarray(axes), plane, eye, 4)
    np.testing.assert_allclose(again.wxyz_xyz, starts.wxyz_xyz, atol=1e-6)
    # the front toward the camera meets the cloud's front (slid horizontally toward the eye)
    front = np.percentile(np.asarray(cloud)[:, 0], 95)
    np.testing.assert_allclose(pts[..., 0].max(1), front, atol=2e-3)
