"""estimate_pose on a rendered tabletop frame, and each stage's failure signature built into it:
a stray table slab, depth holes over the object, phantom edge points, the object missing."""

import jax
import numpy as np
import pytest
import trimesh

from jaxreg.camera import Intrinsics, RGBDFrame
from jaxreg.geometry.metrics import Symmetry, add_s, pose_error
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
    assert all(stage.ms > 0 for stage in est.stages.values())
    assert est.stages["lift"].valid_depth_fraction > 0.8
    # the covariance is a finite, positive definite error bar of sub-millimetre order
    eig = np.linalg.eigvalsh(est.covariance)
    assert np.all(np.isfinite(eig)) and eig.min() > 0
    assert np.sqrt(np.diag(est.covariance)[:3]).max() < 0.002
    assert 0.5 < est.inlier_fraction <= 1 and est.inlier_rmse < 0.004
    # the mask covers the target's pixels, little else
    assert np.mean(est.mask[scene.mask]) > 0.6 and np.mean(scene.mask[est.mask]) > 0.9


def test_a_new_model_runs_the_programs_already_compiled(scene):
    """A model of another point count and symmetry group (a continuous axis, as a
    cylinder's) after the first: not one XLA compilation (jax.monitoring's compile events),
    and the object is found."""
    box, model, symmetry = scene
    estimate_pose(box.frame, model, symmetry=symmetry)  # compiled here or by a test before
    other = trimesh.sample.sample_surface(box.model, 6000, seed=3)[0].astype(np.float32)
    compiles = []

    def listen(event, duration, **_):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        turned = Symmetry(np.stack([np.eye(3), np.diag([1.0, -1.0, -1.0])]), np.array([0, 0, 1.0]))
        est = estimate_pose(box.frame, other, symmetry=turned)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert compiles == []
    assert est.failed_stage is None
    assert float(add_s(box.model_points, est.pose, box.truth)) < 0.005


def test_models_of_every_object_and_point_count_give_the_programs_a_few_shapes(scene):
    """Every array the compiled register stage takes from a model (points, normals, the
    sparse screen, both grids' tables) is padded to a few size classes: the four objects at
    6k, 10k and 20k points share one (each sampling had its own), padded with NaN points and
    zero normals after the model's rows."""
    from jaxreg.pipeline._model import _prepare_model
    from jaxreg.synth import OBJECTS, object_mesh

    def shapes(prepared):
        arrays = (prepared.points, prepared.normals, prepared.screen, prepared.grid)
        return tuple(np.shape(a) for a in jax.tree.leaves((*arrays, prepared.fine_grid)))

    classes = {shapes(_prepare_model(scene[1], None, 0.004, 0.04, 0.015)): ["box 20k"]}
    for name in OBJECTS:
        mesh, _ = object_mesh(name)
        for count in (6000, 10_000, 20_000):
            points = trimesh.sample.sample_surface(mesh, count, seed=1)[0].astype(np.float32)
            prepared = _prepare_model(points, None, 0.004, 0.04, 0.015)
            classes.setdefault(shapes(prepared), []).append(f"{name} {count}")
    assert len(classes) == 1, list(classes.values())
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


def test_a_batch_of_poses_is_judged_as_each_pose_alone(scene):
    """The register stage's judgement of a batch of poses (one z-buffer scatter into the
    poses' cell grids laid end to end) gives each pose the counts that visibility gives it
    alone, with the table plane and the depth noise: poses whose models cover the same
    pixels do not hide one another's points."""
    from jaxlie import SE3

    from jaxreg.pipeline._judge import _judge
    from jaxreg.pipeline.estimate import visibility
    from jaxreg.pipeline.segment import segment_frame

    box, model, _ = scene
    points = model[::10]
    plane = segment_frame(box.frame).plane
    sigma_z = np.asarray([0.0, 0.0, 2.5e-3], np.float32)
    rng = np.random.default_rng(0)
    scale = np.float32([0.01] * 3 + [0.3] * 3)
    nudges = SE3.exp(rng.normal(size=(6, 6)).astype(np.float32) * scale)
    base_T_object = box.truth @ nudges  # overlapping views of the box
    object_T_base = base_T_object.inverse().wxyz_xyz
    batch = np.asarray(
        _judge(box.frame, plane, object_T_base, points, np.float32(0.01), sigma_z)
    )
    alone = [
        np.asarray(visibility(box.frame, pose, points, np.float32(0.01), plane, sigma_z=sigma_z))
        for pose in (SE3(q) for q in np.asarray(base_T_object.wxyz_xyz))
    ]
    assert batch[:, 0].max() > 100 and len({tuple(row) for row in batch}) == len(batch)
    np.testing.assert_array_equal(batch, np.stack(alone))


def test_a_failed_final_registration_fails_the_register_stage(scene, monkeypatch):
    """The refinement's ICP ending non-finite (or degenerate without a symmetry) leaves no
    pose to claim, however well its last finite pose fits: the register stage fails with
    the ICP status's message."""
    import equinox as eqx

    from jaxreg.pipeline import _fits as fits
    from jaxreg.registration.icp import ICPStatus

    scene, model, symmetry = scene
    refine = fits._starts_in_pieces

    def ending(status, symmetric):
        def starts(*args, **options):
            results = refine(*args, **options)
            code = np.full(results.status._value.shape, status._value, np.int32)
            return eqx.tree_at(lambda r: r.status._value, results, jax.numpy.asarray(code))

        monkeypatch.setattr(fits, "_starts_in_pieces", starts)
        return estimate_pose(scene.frame, model, symmetry=symmetry if symmetric else None)

    est = ending(ICPStatus.non_finite, True)
    assert est.failed_stage == "register" and est.pose is None
    assert "a non-finite update" in est.reason
    assert est.stages["register"].icp_status.startswith("a non-finite update")
    assert ending(ICPStatus.degenerate, False).reason.startswith(
        "the final registration failed: degenerate geometry"
    )
    assert ending(ICPStatus.degenerate, True).success  # the symmetry's free directions


def test_an_overhang_that_cannot_be_measured_refuses(scene, monkeypatch):
    """A NaN overhang (a NaN comparison is False) must not pass the overhang test."""
    from jaxreg.pipeline import _evidence as evidence

    scene, model, symmetry = scene
    monkeypatch.setattr(evidence, "overhang", lambda *args: np.full(3, np.nan))
    est = estimate_pose(scene.frame, model, symmetry=symmetry)
    assert est.failed_stage == "register" and est.pose is None
    assert "could not be measured (NaN" in est.reason


def test_no_judged_surface_and_too_little_confirmed_surface_refuse(scene, monkeypatch):
    """Evidence is counted, never assumed: a pose where the image judges none of the model's
    surface (every point unknown) is refused as such, not passed as "0% contradicted"; and a
    pose whose confirmed share is below ``min_confirmed`` is refused with both numbers."""
    from jaxreg.pipeline import _judge as judging

    scene, model, symmetry = scene
    strict = estimate_pose(scene.frame, model, symmetry=symmetry, min_confirmed=0.99)
    assert strict.failed_stage == "register" and strict.pose is None
    assert "the image confirms only" in strict.reason and "(need 99%)" in strict.reason
    assert 0.2 < strict.stages["register"].model_confirmed <= 0.99  # rounded to 3 places

    judge = judging._judge

    def unknown(*args):
        counts = np.array(judge(*args))
        counts[..., 3] += counts[..., :3].sum(-1)  # confirmed, contradicted, occluded: unknown
        counts[..., :3] = 0
        return counts

    monkeypatch.setattr(judging, "_judge", unknown)  # every fit's judgement (judged_fits)
    est = estimate_pose(scene.frame, model, symmetry=symmetry)
    assert est.failed_stage == "register" and est.pose is None
    assert "the image judges none of the model's surface" in est.reason
    assert est.stages["register"].model_confirmed is None


def test_a_model_mostly_outside_the_image_is_refused_as_too_little_in_view(scene):
    """With a fifth of the box's width in the image, the model's fit confirms what is seen,
    but most of its surface facing the camera lies outside the image: a corner fits the
    corner of many objects, so the pose is refused, by mask or without a prompt, naming the
    share seen. With half of it in view the box is found."""
    scene, model, symmetry = scene
    cols = np.nonzero(scene.mask.any(0))[0]
    k = scene.frame.intrinsics

    def moved(image, keep, fill):
        """``image``'s first ``keep`` columns moved right to end at its right edge."""
        out = np.full_like(image, fill)
        out[:, k.width - keep :] = image[:, :keep]
        return out

    for part, found in ((0.2, False), (0.5, True)):
        # the principal point moves with the columns: every pixel keeps its ray, and the rest
        # of the box lies past the image's edge
        keep = int(cols.min() + part * (cols.max() - cols.min()))
        frame = RGBDFrame(
            moved(np.asarray(scene.frame.depth), keep, np.nan),
            Intrinsics(k.fx, k.fy, k.cx + k.width - keep, k.cy, k.width, k.height), None,
            scene.frame.base_T_camera,
        )  # fmt: skip
        for prompt in ({}, {"mask": moved(scene.mask, keep, False)}):
            est = estimate_pose(frame, model, symmetry=symmetry, **prompt)
            assert (est.pose is not None) == found, est.reason
            if not found:
                assert "too little of the model is in view" in est.reason, est.reason
                assert est.failed_stage == "register"


def test_the_image_judges_a_pose_within_the_depth_noise_at_its_depth():
    """A model patch 2 cm in front of a wall the camera sees 1 m away: beyond the 1 cm floor
    of the depth agreement the wall contradicts it, but under a sensor whose sigma_z(1 m) is
    1 cm (4 sigma = 4 cm) the wall confirms it; the default sensor (2.5 mm there) does not."""
    from jaxlie import SE3

    from jaxreg.camera import Intrinsics
    from jaxreg.pipeline.estimate import visibility

    frame = RGBDFrame(np.ones((48, 64), np.float32), Intrinsics(60.0, 60.0, 31.5, 23.5, 64, 48))
    u, v = np.meshgrid(np.linspace(-0.1, 0.1, 5), np.linspace(-0.1, 0.1, 5))
    patch = np.stack([u.ravel(), v.ravel(), np.full(25, 0.98)], -1).astype(np.float32)
    floor = np.float32(0.01)

    def counts(sigma_z=None):
        coefficients = None if sigma_z is None else np.float32(sigma_z)
        seen = visibility(frame, SE3.identity(), patch, floor, sigma_z=coefficients)
        return np.asarray(seen)[:2].tolist()  # confirmed, contradicted

    assert counts() == [0, 25]
    assert counts([0.0, 0.0, 2.5e-3]) == [0, 25]
    assert counts([0.0, 0.0, 1e-2]) == [25, 0]


def test_the_refined_starts_are_a_setting(scene):
    scene, model, symmetry = scene
    est = estimate_pose(scene.frame, model, symmetry=symmetry, refined_starts=2)
    assert est.success and est.stages["register"].refined_starts == 2
    assert float(add_s(scene.model_points, est.pose, scene.truth)) < 0.005
    with pytest.raises(ValueError, match="refined_starts"):
        estimate_pose(scene.frame, model, refined_starts=0)


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
    assert est.stages["lift"].valid_depth_fraction < 0.5


def test_a_segment_without_depth_lifts_no_points(scene):
    """No pixel left to lift (every one a hole) gives an empty mask and no points, which the
    lift stage reports as too few points, not an indexing error."""
    from jaxreg.pipeline._lift_stage import lift_region

    scene, _, _ = scene
    none = np.zeros(0, np.int64)
    mask, points, counts = lift_region(
        scene.frame, none, none, np.zeros(0), None, None, min_height=0.0, max_height=np.inf,
        band_sigmas=3.0, voxel_size=0.004, min_consistent_neighbors=5,
    )  # fmt: skip
    assert mask.shape == np.asarray(scene.frame.depth).shape and not mask.any()
    assert points.shape == (0, 3)
    assert counts["points"] == 0 and counts["flying_pixels_removed"] == 0


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
        est.stages["lift"].flying_pixels_removed - clean.stages["lift"].flying_pixels_removed
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
    box model fits as well by inlier fraction, residual and image support; only its faces
    running on past the model's edges tell them apart."""
    from jaxreg.pipeline._evidence import overhang
    from jaxreg.pipeline._model import _prepare_model
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
    assert "carry the model's surface on past its edge" in prompted.reason
    assert prompted.stages["register"].runs_on >= (0.012 / 0.004) ** 2  # a patch's worth
    est = estimate_pose(other.frame, model, symmetry=symmetry)
    assert est.failed_stage is None
    assert float(add_s(other.model_points, est.pose, other.truth)) < 0.005
    assert max(est.stages["register"].overhang_mm) < 0
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
    assert max(est.stages["segment"].cluster_radii_mm) > 76 + 20
    assert est.failed_stage is None
    assert float(add_s(frame8.model_points, est.pose, frame8.truth)) < 0.005


def test_resting_starts_stand_the_model_on_the_table_on_each_principal_half_axis():
    import jax.numpy as jnp
    from jaxlie import SE3

    from jaxreg.pipeline._coarse import _resting_starts
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


def test_your_own_mask_skips_the_table_and_clusters_and_works_without_a_table(scene):
    scene, model, symmetry = scene
    est = estimate_pose(scene.frame, model, mask=scene.mask, symmetry=symmetry)
    assert est.failed_stage is None
    assert float(add_s(scene.model_points, est.pose, scene.truth)) < 0.005
    seg = est.stages["segment"]
    assert seg.mask_pixels == scene.mask.sum() and seg.cluster_sizes is None
    assert seg.plane_inliers > 0  # the table outside the mask still filters the segment
    assert not est.mask[~scene.mask].any()  # nothing outside the caller's mask is lifted
    # a frame without a table: only the object has depth
    depth = np.where(scene.mask, np.asarray(scene.frame.depth), np.nan)
    alone = estimate_pose(_with_depth(scene.frame, depth), model, mask=scene.mask)
    assert alone.failed_stage is None and alone.stages["segment"].plane_inliers is None
    assert float(add_s(scene.model_points, alone.pose, scene.truth)) < 0.005
    # the table route finds nothing standing on a table in the same frame
    assert estimate_pose(_with_depth(scene.frame, depth), model).failed_stage == "segment"


def test_a_mask_on_another_object_claims_no_pose(scene):
    from jaxreg.synth import tabletop_scene

    _, model, symmetry = scene
    cluttered = tabletop_scene(4, object="box")  # the same box beside two distractors
    for label in (2, 3):
        est = estimate_pose(cluttered.frame, model, mask=cluttered.labels == label)
        assert est.pose is None and est.failed_stage in ("segment", "register"), label
    # another scene's mug mask (every scene centres its target): moved beside the box, no
    # pose; where it lies, over most of the box, the box is found (a pose, and the right one)
    over = tabletop_scene(5, object="mug").mask
    beside = np.roll(over, 300, axis=1)
    assert not (beside & cluttered.mask).any() and (over & cluttered.mask).mean() > 0
    est = estimate_pose(cluttered.frame, model, mask=beside, symmetry=symmetry)
    assert est.pose is None and est.failed_stage is not None
    est = estimate_pose(cluttered.frame, model, mask=over, symmetry=symmetry)
    assert est.success, est.reason
    assert float(add_s(cluttered.model_points, est.pose, cluttered.truth)) < 0.005


def test_a_model_in_other_units_is_refused_naming_the_units(scene):
    scene, model, _ = scene
    with pytest.raises(ValueError, match="millimetres"):
        estimate_pose(scene.frame, 1000 * model)
    for mask in (None, scene.mask):
        est = estimate_pose(scene.frame, 10 * model, mask=mask)
        assert est.pose is None and "metres" in est.reason, est.reason
        assert "340282" not in est.reason
    millimetres = _with_depth(scene.frame, 1000 * np.asarray(scene.frame.depth))
    with pytest.raises(ValueError, match="depth must be metres"):
        estimate_pose(millimetres, model)


@pytest.mark.parametrize("name, seed", [("mug", 1), ("cylinder", 2), ("container", 3)])
def test_every_object_is_found_on_the_table_and_with_its_mask(name, seed):
    """The main job on each object besides the box (which the tests above cover): one frame
    with two distractors, by the table route and with the true mask."""
    from jaxreg.synth import tabletop_scene

    scene = tabletop_scene(seed, object=name)
    samples, _ = trimesh.sample.sample_surface(scene.model, 20_000, seed=0)
    model = samples.astype(np.float32)
    for mask in (None, scene.mask):
        est = estimate_pose(scene.frame, model, mask=mask, symmetry=scene.symmetry)
        assert est.failed_stage is None, est.reason
        assert float(add_s(scene.model_points, est.pose, scene.truth)) < 0.005


def test_the_budgets_border_distances_are_the_whole_images():
    """The error budget's distances into and around the mask, computed on the mask's box
    grown by a margin, are the whole image's (inside; and outside up to the margin, beyond
    which they only need to exceed it), for masks in the middle and against the border."""
    from scipy import ndimage

    from jaxreg.pipeline._error_sources import _distances

    rng = np.random.default_rng(0)
    for top, left in [(20, 30), (0, 5), (50, 70), (0, 0)]:
        mask = np.zeros((60, 80), bool)
        mask[top : top + 25, left : left + 20] = True
        mask &= rng.random(mask.shape) > 0.2  # holes: inner distances of several sizes
        inside, outside = _distances(mask, 4)
        np.testing.assert_array_equal(inside, ndimage.distance_transform_edt(mask))
        whole = ndimage.distance_transform_edt(~mask)
        near = whole <= 4
        np.testing.assert_array_equal(outside[near], whole[near])
        assert np.all(outside[~near] > 4)


def test_identical_twins_on_the_table_are_refused_naming_both():
    """Two identical boxes side by side: depth cannot say which one is meant, so no pose is
    claimed; the reason names both segments and what to give. A pixel on either twin then
    poses that twin."""
    from jaxreg.synth import object_mesh, tabletop_scene

    box, symmetry = object_mesh("box")
    twins = trimesh.util.concatenate([box, box.copy().apply_translation((0.16, 0.0, 0.0))])
    scene = tabletop_scene(6, mesh=twins, distractors=0, symmetry=symmetry)
    model = trimesh.sample.sample_surface(box, 6000, seed=1)[0].astype(np.float32)
    est = estimate_pose(scene.frame, model, symmetry=symmetry)
    assert est.failed_stage == "register" and est.pose is None
    assert "two separate segments fit the model equally well" in est.reason
    assert est.reason.count("at pixel (") == 2 and "give pixel=, box= or mask=" in est.reason
    truth = np.asarray(scene.truth.as_matrix())
    second = scene.truth @ jax.numpy.asarray([0.16, 0.0, 0.0])
    for centre in (truth[:3, 3], np.asarray(second)):
        camera = scene.frame.base_T_camera.inverse() @ jax.numpy.asarray(centre)
        u, v = np.asarray(scene.frame.intrinsics.project(camera))
        chosen = estimate_pose(scene.frame, model, symmetry=symmetry, pixel=(u, v))
        assert chosen.success, chosen.reason
        found = np.asarray(chosen.pose.translation())
        assert np.linalg.norm(found[:2] - centre[:2]) < 0.01



def test_pieces_of_one_object_are_not_twins(monkeypatch):
    """Seed 9309 (a bench_silent development seed): the clustering splits the mug into three
    clusters, and the coarse search scores each alike. The winner's coarse pose explains the
    others, so they are pieces of it, not a second mug: the pose is found, right, with the
    pieces joined. The coarse search runs one concurrent call per core, each on every second
    candidate slot: in two pieces the candidates' scores and the answer are those of the
    search in one call."""
    from jaxreg.pipeline import _fits as fits
    from jaxreg.synth import StereoSensor, tabletop_scene

    scene = tabletop_scene(9309, object="mug", distractors=3)
    noise = StereoSensor.d435().depth_noise(scene.frame.intrinsics)

    def estimate(pieces):
        monkeypatch.setattr(fits, "lane_pieces", lambda lanes, per_piece=8: min(pieces, lanes))
        return estimate_pose(
            scene.frame, scene.model_points, symmetry=scene.symmetry, depth_noise=noise
        )

    est, whole = estimate(2), estimate(1)
    assert est.success, est.reason
    assert float(add_s(scene.model_points, est.pose, scene.truth)) < 0.0127  # 10% of 127 mm
    assert len(est.stages["register"].chosen_clusters) >= 2
    scored = [est.stages["register"].candidates, whole.stages["register"].candidates]
    assert len(scored[0]) >= 3
    assert [c.clusters for c in scored[0]] == [c.clusters for c in scored[1]]
    np.testing.assert_allclose([c.score for c in scored[0]], [c.score for c in scored[1]])
    np.testing.assert_allclose(est.pose.as_matrix(), whole.pose.as_matrix(), atol=1e-5)


def _held_out(seed: int, name: str, model_points: int):
    """bench_silent's scene of object ``name`` at ``seed`` (three distractors, the D435's
    noise) and its estimate with ``model_points`` surface samples of the object."""
    from jaxreg.synth import StereoSensor, tabletop_scene

    scene = tabletop_scene(seed, object=name, distractors=3, model_points=model_points)
    noise = StereoSensor.d435().depth_noise(scene.frame.intrinsics)
    est = estimate_pose(scene.frame, scene.model_points, symmetry=scene.symmetry, depth_noise=noise)
    return scene, est


@pytest.mark.parametrize("seed", [10622, 11318])
def test_a_rival_that_looks_better_at_coarse_is_refined_before_either_is_claimed(seed):
    """Dense mug models of bench_silent (seeds looked at while the rival tests were written).
    10622: a can's coarse score beat the mug's by 2.2 standard errors (the mug's best coarse
    pose saw through its handle) and the can was claimed, 167 mm away. 11318: the mug's
    coarse poses turned it about its axis, so its handle spanned 17 mm beyond the model and
    the mug was set aside as a larger object; a can was claimed, 234 mm away. Both segments
    are now refined and probed first (within the model's span); the can's fit is not clearly
    better, so neither is claimed: both are refused as twins, the reason naming both."""
    scene, est = _held_out(seed, "mug", 8192)
    assert not est.success and est.failed_stage == "register"
    assert "two separate segments fit the model equally well" in est.reason


def test_sunk_and_underneath_measure_a_pose_against_the_table():
    """The table plane z = 0 (normal +z): a model resting on it is not sunk, the same model
    moved down by 7 mm is sunk 7 mm, moved up it floats (0), and a pose turned upside down
    about x keeps its lowest point's depth. A segment of the resting box's own points stays
    above its lowest point; the same segment with the model floated 20 mm up reaches 20 mm
    below it (a model on top of a taller object). Without a plane both are 0."""
    from jaxlie import SE3, SO3

    from jaxreg.pipeline._judge import sunk, underneath
    from jaxreg.pipeline._model import _prepare_model
    from jaxreg.pipeline.segment import TablePlane

    box = trimesh.creation.box((0.08, 0.05, 0.12))
    points = np.asarray(box.sample(2000, seed=0), np.float32) + np.float32([0, 0, 0.06])
    prepared = _prepare_model(points, None, 0.004, 0.04, 0.015)
    plane = TablePlane(np.array([0.0, 0.0, 1.0]), np.array(0.0), np.array(0), np.array(0.0))

    def object_T_base(height, flip=False):
        base_T_object = SE3.from_translation(np.array([0.1, -0.2, height]))
        if flip:  # upside down about its own bottom face's centre
            base_T_object = base_T_object @ SE3.from_rotation(SO3.from_x_radians(np.pi))
        return np.asarray(base_T_object.inverse().wxyz_xyz)

    assert sunk(prepared, plane, object_T_base(0.0)) == pytest.approx(0.0, abs=1e-6)
    assert sunk(prepared, plane, object_T_base(-0.007)) == pytest.approx(0.007, abs=1e-6)
    assert sunk(prepared, plane, object_T_base(0.02)) == 0.0
    assert sunk(prepared, plane, object_T_base(0.05, flip=True)) == pytest.approx(0.07, abs=1e-6)
    assert sunk(prepared, None, object_T_base(-0.05)) == 0.0
    segment = points[points[:, 0] > 0.03] + np.float32([0.1, -0.2, 0.0])  # one face, in base
    resting = underneath(prepared, plane, object_T_base(0.0), segment)
    assert -0.004 < resting <= 0  # the face's 2% quantile, 2.4 mm up its 120 mm
    floated = underneath(prepared, plane, object_T_base(0.02), segment)
    assert floated - resting == pytest.approx(0.02, abs=1e-6)
    assert underneath(prepared, None, object_T_base(0.02), segment) == 0.0


def test_resting_contacts_find_a_face_on_the_table_not_an_edge_or_a_gap():
    """A 80 x 50 x 120 mm box over the table z = 0, four poses in one batch: standing 1 mm
    above the table rests on its bottom face (contact points on the plane, inside that face,
    and the 1 mm it stood above); balanced on an edge (turned 45 degrees about x) it is
    within the tolerance but has no face there; 20 mm above, beyond the tolerance; a
    non-finite pose is never resting."""
    from jaxlie import SE3, SO3

    from jaxreg.pipeline._answer import CONTACT_POINTS, resting_contacts

    box = trimesh.creation.box((0.08, 0.05, 0.12))
    points = np.asarray(box.sample(3000, seed=1), np.float64)
    edge = SE3.from_rotation(SO3.from_x_radians(np.pi / 4))
    edge_height = 0.5 * (0.05 + 0.12) * np.sin(np.pi / 4) + 0.001
    poses = [
        SE3.from_translation(np.array([0.1, -0.2, 0.061])),
        SE3.from_translation(np.array([0.1, -0.2, edge_height])) @ edge,
        SE3.from_translation(np.array([0.1, -0.2, 0.08])),
    ]
    matrices = np.stack([np.asarray(p.as_matrix(), np.float64) for p in poses])
    matrices = np.concatenate([matrices, np.full((1, 4, 4), np.nan)])
    found = resting_contacts(points, matrices, np.array([0.0, 0, 1]), 0.0, 0.005, 0.004)
    assert [f is None for f in found] == [False, True, True, True]
    contact, lowest = found[0]
    assert contact.shape == (CONTACT_POINTS, 3) and lowest == pytest.approx(0.001, abs=1e-6)
    inside = contact[np.all(np.isfinite(contact), axis=1)]
    assert len(inside) > 3 and np.all(inside[:, 2] == 0.0)
    assert np.all(np.abs(inside[:, :2] - [0.1, -0.2]) <= [0.04 + 1e-6, 0.025 + 1e-6])
    assert np.ptp(inside[:, 0]) > 0.06 and np.ptp(inside[:, 1]) > 0.035  # the whole face


def test_a_target_whose_best_coarse_pose_spans_beyond_the_model_is_still_found():
    """Seed 11204 (bench_silent, looked at while this was written), a mug: its best coarse
    pose turned it about its axis, so its handle spanned 20 mm beyond the model; the mug was
    ranked after three small distractors and two of those were refused as twins. A candidate
    is now scored at its best coarse pose that keeps the segment within the model's span and
    the model out of the table, and the refinement ranks such fits first. Its refined answer
    is the mug turned half round (the handle on the hidden side, the seen handle's points
    left unexplained), and the probe that turns it back explains clearly more of the segment:
    the refinement answers again from that probe, and the mug is found with its handle where
    the image shows it, on the sparse 2,048-sample model."""
    scene, est = _held_out(11204, "mug", 2048)
    assert est.success, est.reason
    translation, rotation = pose_error(est.pose, scene.truth)
    assert float(translation) < 0.005 and float(np.degrees(rotation)) < 5.0
    assert est.stages["register"].runs_on < 10


def test_the_model_flows_down_the_pipeline_modules_never_back_up():
    """Following the model through one ``estimate_pose`` (every call that takes the model
    points, or the model prepared from them, as an argument): each pipeline module is
    entered from at most two other modules, and no module is entered from one it calls
    (the stages hand records down; none reaches back into the stage that called it)."""
    import collections
    import graphlib
    import sys

    import jaxreg.pipeline.estimate as estimate
    from jaxreg.synth import StereoSensor

    scene, est = _held_out(11204, "mug", 2048)  # warm: the traced call compiles nothing
    followed = {id(scene.model_points)}
    prepare = estimate._prepare_model

    def prepared(*args, **kwargs):
        model = prepare(*args, **kwargs)
        followed.update(id(v) for v in (args[0], model, model.points, model.normals))
        return model

    callers = collections.defaultdict(set)
    stack = []

    def profile(frame, event, _):
        if event == "return" and stack:
            stack.pop()
        if event != "call":
            return
        name = frame.f_code.co_filename.replace("\\", "/")
        module = None
        if "/jaxreg/pipeline/" in name and any(
            id(value) in followed for value in frame.f_locals.values()
        ):
            module = name.rsplit("/", 1)[1].removesuffix(".py")
            caller = next((m for m in reversed(stack) if m is not None), None)
            if caller not in (None, module):
                callers[module].add(caller)
        stack.append(module)

    noise = StereoSensor.d435().depth_noise(scene.frame.intrinsics)
    try:
        estimate._prepare_model = prepared
        sys.setprofile(profile)
        again = estimate.estimate_pose(
            scene.frame, scene.model_points, symmetry=scene.symmetry, depth_noise=noise
        )
    finally:
        sys.setprofile(None)
        estimate._prepare_model = prepare
    assert again.success == est.success
    assert callers["_segment_stage"] == callers["_register_stage"] == {"estimate"}
    assert all(len(entered_from) <= 2 for entered_from in callers.values()), dict(callers)
    graph = {module: entered_from for module, entered_from in callers.items()}
    graphlib.TopologicalSorter(graph).prepare()  # raises CycleError on a climb back up


def test_a_winner_that_sits_on_a_taller_neighbour_is_not_clearly_better():
    """Seed 11510 (bench_silent, looked at while this was written), a mug: a taller can
    outscored it at coarse, and refined, the mug model sat on top of the can, 24 mm above the
    table with the can's points beneath it; a rule that let that fit be clearly better than
    the mug's own claimed the can, 151 mm away. A fit with the segment reaching below the
    model now goes beyond what the frame allows and is never clearly better, and the mug's
    own fit is not clearly better than the can's either: both are refused as twins."""
    scene, est = _held_out(11510, "mug", 2048)
    assert not est.success and est.failed_stage == "register"
    assert "two separate segments fit the model equally well" in est.reason
