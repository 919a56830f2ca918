"""Camera frames: Intrinsics, RGBDFrame and their files (jaxreg.io.read_frame / write_frame).

The PCL captures in the shared data folder must read as frames whose intrinsics re-project
every valid point to its own pixel; a depth PNG + intrinsics JSON written by `write_frame`
must read back as the same frame; malformed or inconsistent files raise a `ValueError` that
names the problem.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

import jaxreg as jr
from jaxreg.geometry.lie import se3_to_matrix
from jaxreg.io import read_frame, read_pcd, write_frame, write_pcd

CAPTURES = {
    # file: (fx, fy, cx, cy) where the data README states them, else None
    "milk_cartoon_all_small_clorox.pcd": (525.0, 525.0, 319.5, 239.5),
    "table_scene_mug_stereo_textured.pcd": None,
    "frame_20121214T142255.814212.pcd": None,
}


def small_frame(dist_coeffs=None) -> jr.RGBDFrame:
    """A 6 x 8 frame: depths on the 1 mm grid, a NaN hole and a 0 hole, colour, a hand-eye
    pose that is not the identity."""
    rng = np.random.default_rng(0)
    counts = rng.integers(400, 1500, (6, 8))
    depth = (counts * 0.001).astype(np.float32)
    depth[1, 2] = np.nan
    depth[4, 5] = 0.0
    rgb = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    intrinsics = jr.Intrinsics(9.5, 9.0, 3.6, 2.4, 8, 6, dist_coeffs)
    pose = jr.SE3.exp(jnp.array([0.1, -0.2, 0.7, 0.3, -0.2, 0.5]))
    return jr.RGBDFrame(depth, intrinsics, rgb=rgb, base_T_camera=pose)


def assert_same_frame(a: jr.RGBDFrame, b: jr.RGBDFrame):
    np.testing.assert_array_equal(np.asarray(a.depth), np.asarray(b.depth))
    np.testing.assert_array_equal(np.asarray(a.rgb), np.asarray(b.rgb))
    assert (a.intrinsics.width, a.intrinsics.height) == (b.intrinsics.width, b.intrinsics.height)
    np.testing.assert_array_equal(np.asarray(a.intrinsics.K), np.asarray(b.intrinsics.K))
    if a.intrinsics.dist_coeffs is None:
        assert b.intrinsics.dist_coeffs is None
    else:
        np.testing.assert_allclose(a.intrinsics.dist_coeffs, b.intrinsics.dist_coeffs, rtol=1e-7)
    np.testing.assert_allclose(
        se3_to_matrix(a.base_T_camera), se3_to_matrix(b.base_T_camera), atol=1e-6
    )


# ------------------------------------------------------------------------------------------
# Intrinsics and RGBDFrame
# ------------------------------------------------------------------------------------------


def test_intrinsics_project_and_lift_are_inverse_with_distortion():
    dist = (-0.12, 0.05, 1e-3, -5e-4, 0.01)
    intrinsics = jr.Intrinsics.from_matrix(
        [[600.0, 0.0, 330.0], [0.0, 590.0, 235.0], [0.0, 0.0, 1.0]], 640, 480, dist
    )
    assert intrinsics.shape == (480, 640)
    pixels = intrinsics.pixel_grid()[::37, ::41]
    rays = intrinsics.rays(pixels)
    np.testing.assert_allclose(intrinsics.project(2.5 * rays), pixels, atol=1e-3)
    # the same as the free function PnP uses
    np.testing.assert_allclose(
        intrinsics.project(rays),
        jr.camera.project(rays.reshape(-1, 3), intrinsics.K, dist).reshape(pixels.shape),
        atol=1e-4,
    )


def test_bad_intrinsics_raise():
    with pytest.raises(ValueError, match="width"):
        jr.Intrinsics(500.0, 500.0, 320.0, 240.0, 0, 480)
    with pytest.raises(ValueError, match="fx"):
        jr.Intrinsics(-1.0, 500.0, 320.0, 240.0, 640, 480)
    with pytest.raises(ValueError, match="K must be"):
        jr.Intrinsics.from_matrix([[500.0, 1.0, 320.0], [0, 500.0, 240.0], [0, 0, 1]], 640, 480)
    with pytest.raises(ValueError, match="intrinsics are for"):
        jr.RGBDFrame(np.ones((5, 8)), small_frame().intrinsics)


def test_frames_of_host_data_compile_no_jax_program():
    """A command line process pays for every JAX program it compiles or loads (jnp.asarray of
    host data is one per shape): intrinsics and frames of numpy data are built on the host.
    The shapes are this test's own, so a program compiled here could not be an earlier one."""
    compiled = []

    def listen(event, duration, **kwargs):
        if event.endswith("backend_compile_duration"):
            compiled.append(kwargs.get("fun_name"))

    depth = np.full((7, 13), 0.5, np.float32)
    depth[2, 3], depth[4, 5], depth[6, 0] = 0.0, np.nan, -1.0
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        intrinsics = jr.Intrinsics(11.0, 12.0, 6.0, 3.0, 13, 7, [0.01, -0.02, 0.001, 0.0])
        frame = jr.RGBDFrame(depth, intrinsics, rgb=np.zeros((7, 13, 3), np.uint8))
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert compiled == []
    holes = np.isnan(np.asarray(frame.depth))
    assert holes.sum() == 3 and holes[2, 3] and holes[4, 5] and holes[6, 0]
    np.testing.assert_array_equal(
        np.asarray(intrinsics.dist_coeffs), np.float32([0.01, -0.02, 0.001, 0.0, 0.0])
    )
    assert frame.depth.dtype == intrinsics.fx.dtype == jnp.float32


def test_frame_lifts_pixels_to_camera_and_base():
    frame = small_frame()
    depth = np.asarray(frame.depth)
    assert np.isnan(depth[1, 2]) and np.isnan(depth[4, 5])  # NaN and 0 are both holes
    assert int(frame.valid.sum()) == 46
    camera = np.asarray(frame.camera_points())
    v, u = np.mgrid[0:6, 0:8]
    expected = depth[..., None] * np.stack([(u - 3.6) / 9.5, (v - 2.4) / 9.0, np.ones((6, 8))], -1)
    np.testing.assert_allclose(camera, expected, rtol=1e-6, atol=1e-7)
    base = np.asarray(frame.points())
    np.testing.assert_allclose(
        base[frame.valid], np.asarray(frame.base_T_camera @ camera[frame.valid]), atol=1e-6
    )
    mask = np.zeros((6, 8), bool)
    mask[2:4] = True
    masked = np.asarray(frame.points(mask))
    assert np.isfinite(masked).all(-1).sum() == 16 and np.isnan(masked[~mask]).all()
    # chosen pixels alone, a hole among them: the same points, NaN at the hole
    rows, cols = np.array([[0, 1], [4, 4]]), np.array([[7, 2], [0, 5]])
    picked = np.asarray(frame.points_at(rows, cols))
    assert picked.shape == (2, 2, 3)
    assert np.isnan(picked[0, 1]).all() and np.isnan(picked[1, 1]).all()
    # one program for the picks, another for the image: XLA may round the last bit apart
    np.testing.assert_allclose(picked, base[rows, cols], rtol=1e-6, atol=1e-7)


def test_frame_points_are_differentiable_in_intrinsics_and_hand_eye():
    frame = small_frame()
    valid = frame.valid

    def total(fx, tangent):
        intrinsics = jr.Intrinsics(fx, 9.0, 3.6, 2.4, 8, 6)
        pose = frame.base_T_camera @ jr.SE3.exp(tangent)
        moved = jr.RGBDFrame(frame.depth, intrinsics, base_T_camera=pose)
        return jnp.sum(jnp.where(valid[..., None], moved.points(), 0.0))

    grad_fx, grad_tangent = jax.jit(jax.grad(total, argnums=(0, 1)))(jnp.float32(9.5), jnp.zeros(6))
    assert np.isfinite(grad_fx) and np.isfinite(grad_tangent).all()  # holes give no NaN
    # d x_cam / d fx = -x_cam / fx, rotated into the base frame
    depth = np.where(np.asarray(valid), np.asarray(frame.depth), 0.0)
    u = np.arange(8)[None, :]
    d_camera = np.array([np.sum(-depth * (u - 3.6) / 9.5**2), 0.0, 0.0])
    rotation = np.asarray(frame.base_T_camera.rotation().as_matrix())
    assert float(grad_fx) == pytest.approx(np.sum(rotation @ d_camera), rel=1e-4)
    # a right translation delta moves every valid point by R @ delta
    np.testing.assert_allclose(grad_tangent[:3], 46 * rotation.sum(axis=0), rtol=1e-5)


# ------------------------------------------------------------------------------------------
# files
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", sorted(CAPTURES))
def test_pcl_captures_read_as_frames_with_the_intrinsics_their_pixels_imply(pcl_dir, name):
    frame = read_frame(pcl_dir / name)
    cloud = read_pcd(pcl_dir / name).points
    valid = np.isfinite(cloud).all(axis=-1)
    np.testing.assert_array_equal(np.asarray(frame.valid), valid)
    assert valid.mean() > 0.5
    # every valid point projects to its own pixel, and the frame lifts it back
    pixels = np.asarray(frame.intrinsics.project(cloud[valid]))
    np.testing.assert_allclose(pixels, np.asarray(frame.intrinsics.pixel_grid())[valid], atol=0.05)
    lifted = np.asarray(frame.camera_points())[valid]
    np.testing.assert_allclose(lifted, cloud[valid], atol=1e-4 * np.nanmax(cloud[..., 2]))
    assert frame.rgb is not None and frame.rgb.shape == (480, 640, 3)
    stated = CAPTURES[name]
    if stated is not None:
        intrinsics = frame.intrinsics
        recovered = [float(x) for x in (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)]
        np.testing.assert_allclose(recovered, stated, atol=1e-3)


def test_unorganized_or_transformed_clouds_are_refused(pcl_dir, tmp_path):
    with pytest.raises(ValueError, match="not an organized cloud"):
        read_frame(pcl_dir / "milk.pcd")
    with pytest.raises(ValueError, match="intrinsics only with a depth PNG"):
        read_frame(pcl_dir / "milk.pcd", intrinsics=small_frame().intrinsics)
    # an organized cloud moved out of its camera frame is no pinhole image any more
    frame = small_frame()
    points = np.asarray(frame.points())  # base frame, not camera
    write_pcd(tmp_path / "moved.pcd", points)
    with pytest.raises(ValueError, match="not one pinhole image"):
        read_frame(tmp_path / "moved.pcd")
    write_pcd(tmp_path / "camera.pcd", np.asarray(frame.camera_points()))
    recovered = read_frame(tmp_path / "camera.pcd").intrinsics
    np.testing.assert_allclose(np.asarray(recovered.K), np.asarray(frame.intrinsics.K), atol=1e-4)


@pytest.mark.parametrize("dist_coeffs", [None, (-0.1, 0.02, 1e-3, 2e-3, 0.0)])
def test_png_and_json_round_trip_returns_the_same_frame(tmp_path, dist_coeffs):
    frame = small_frame(dist_coeffs)
    write_frame(tmp_path / "depth.png", frame)
    meta = json.loads((tmp_path / "depth.json").read_text())
    assert meta["depth_scale"] == 0.001 and meta["width"] == 8 and meta["height"] == 6
    with Image.open(tmp_path / "depth.png") as image:
        counts = np.asarray(image)
    assert counts[1, 2] == 0 and counts[4, 5] == 0  # holes are count 0
    assert_same_frame(frame, read_frame(tmp_path / "depth.png"))


def test_synthetic_scene_round_trips(tmp_path):
    pytest.importorskip("embreex", reason="jaxreg.synth ray casts with Embree (embreex)")
    from jaxreg import synth

    scene = synth.tabletop_scene(1, intrinsics=synth.StereoSensor.d435().intrinsics(212, 120))
    write_frame(tmp_path / "scene.png", scene.frame)
    assert_same_frame(scene.frame, read_frame(tmp_path / "scene.png"))


def test_malformed_png_frames_raise(tmp_path):
    frame = small_frame()
    write_frame(tmp_path / "d.png", frame)
    meta = json.loads((tmp_path / "d.json").read_text())

    def write_meta(**changes):
        (tmp_path / "d.json").write_text(json.dumps({**meta, **changes}))

    write_meta(width=9)
    with pytest.raises(ValueError, match="intrinsics are for 9x6"):
        read_frame(tmp_path / "d.png")
    (tmp_path / "d.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "fy"}))
    with pytest.raises(ValueError, match="missing fy"):
        read_frame(tmp_path / "d.png")
    write_meta(depth_scale=0)
    with pytest.raises(ValueError, match="depth_scale"):
        read_frame(tmp_path / "d.png")
    (tmp_path / "d.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        read_frame(tmp_path / "d.png")
    (tmp_path / "d.json").unlink()
    with pytest.raises(ValueError, match="not found"):
        read_frame(tmp_path / "d.png")
    # an 8-bit image is not a depth PNG, even with its intrinsics
    Image.fromarray(np.zeros((6, 8), np.uint8)).save(tmp_path / "eight.png")
    with pytest.raises(ValueError, match="16-bit"):
        read_frame(tmp_path / "eight.png", intrinsics=frame.intrinsics)
    with pytest.raises(ValueError, match="reads .pcd"):
        read_frame(tmp_path / "d.jpg")
    with pytest.raises(ValueError, match="larger depth_scale"):
        write_frame(tmp_path / "far.png", frame, depth_scale=1e-5)


def test_a_colour_image_beside_a_depth_png_is_read_into_the_frame(tmp_path):
    """`rgb=` names the colour image of a depth PNG (or replaces the JSON's); a file or an array
    of another size is refused, naming both sizes."""
    frame = small_frame()
    bare = jr.RGBDFrame(frame.depth, frame.intrinsics, base_T_camera=frame.base_T_camera)
    write_frame(tmp_path / "d.png", bare)
    assert read_frame(tmp_path / "d.png").rgb is None
    colour = np.asarray(frame.rgb)
    Image.fromarray(colour).save(tmp_path / "colour.png")
    Image.fromarray(colour).save(tmp_path / "colour.jpg", quality=100)
    assert_same_frame(frame, read_frame(tmp_path / "d.png", rgb=tmp_path / "colour.png"))
    np.testing.assert_array_equal(read_frame(tmp_path / "d.png", rgb=colour).rgb, colour)
    jpeg = np.asarray(read_frame(tmp_path / "d.png", rgb=tmp_path / "colour.jpg").rgb)
    assert jpeg.dtype == np.uint8 and jpeg.shape == (6, 8, 3)
    # with Intrinsics given (no JSON read) too, and over the JSON's own colour image
    given = read_frame(tmp_path / "d.png", frame.intrinsics, rgb=tmp_path / "colour.png")
    np.testing.assert_array_equal(given.rgb, colour)
    write_frame(tmp_path / "c.png", frame)
    flipped = np.ascontiguousarray(colour[::-1])
    np.testing.assert_array_equal(read_frame(tmp_path / "c.png", rgb=flipped).rgb, flipped)
    Image.fromarray(np.zeros((6, 9, 3), np.uint8)).save(tmp_path / "wide.png")
    with pytest.raises(ValueError, match=r"colour image is 9x6 .* is 8x6"):
        read_frame(tmp_path / "d.png", rgb=tmp_path / "wide.png")
    with pytest.raises(ValueError, match="no such file"):
        read_frame(tmp_path / "d.png", rgb=tmp_path / "missing.png")
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8"):
        read_frame(tmp_path / "d.png", rgb=colour.astype(np.float32))


def test_a_colour_image_replaces_an_organized_clouds_colours(pcl_dir, tmp_path):
    name = pcl_dir / "milk_cartoon_all_small_clorox.pcd"
    colour = np.random.default_rng(1).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    Image.fromarray(colour).save(tmp_path / "colour.png")
    frame = read_frame(name, rgb=tmp_path / "colour.png")
    np.testing.assert_array_equal(frame.rgb, colour)
    np.testing.assert_array_equal(np.asarray(frame.valid), np.asarray(read_frame(name).valid))
    Image.fromarray(colour[:240]).save(tmp_path / "half.png")
    with pytest.raises(ValueError, match="640x240"):
        read_frame(name, rgb=tmp_path / "half.png")
