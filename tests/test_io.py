"""jaxreg.io: PCD reading (every variant PCL writes), LZF, writers, load_points, malformed files."""

import contextlib
import struct
import tracemalloc

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings, strategies as st

from jaxreg.io import load_points, read_pcd, write_pcd, write_ply
from jaxreg.io._lzf import compress as lzf_compress, decompress as lzf_decompress


def _open3d():
    return pytest.importorskip(
        "open3d", reason="open3d (the `peers` extra) is not importable", exc_type=ImportError
    )


def _header(fields, sizes, types, counts, width, height, points, data, viewpoint="0 0 0 1 0 0 0"):
    lines = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(fields),
        "SIZE " + " ".join(map(str, sizes)),
        "TYPE " + " ".join(types),
        "COUNT " + " ".join(map(str, counts)),
        f"WIDTH {width}",
        f"HEIGHT {height}",
        f"VIEWPOINT {viewpoint}",
        f"POINTS {points}",
        f"DATA {data}",
        "",
    ]
    return "\n".join(lines).encode()


@contextlib.contextmanager
def _peak_memory():
    """Yields a list that holds, once the block exits, the peak number of bytes allocated in
    it (numpy reports its buffers to tracemalloc)."""
    peak = []
    tracemalloc.start()
    try:
        yield peak
    finally:
        peak.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()


def _literal_lzf(raw: bytes) -> bytes:
    """A valid LZF stream of literal runs only: independent of the module's compressor."""
    return b"".join(
        bytes([len(raw[i : i + 32]) - 1]) + raw[i : i + 32] for i in range(0, len(raw), 32)
    )


# ------------------------------------------------------------------------------------------
# The real files PCL wrote
# ------------------------------------------------------------------------------------------


def _real_files(pcl_dir):
    files = sorted(pcl_dir.glob("*.pcd"))
    assert files, f"no .pcd files in {pcl_dir}"
    return files


def _header_values(path) -> dict[str, list[str]]:
    values = {}
    with open(path, "rb") as f:
        for line in f:
            tokens = line.decode("ascii").split()
            if tokens and not tokens[0].startswith("#"):
                values[tokens[0]] = tokens[1:]
            if tokens and tokens[0] == "DATA":
                return values
    raise AssertionError(f"{path}: no DATA line")


def test_real_files_agree_with_open3d(pcl_dir):
    o3d = _open3d()
    kinds = set()
    for path in _real_files(pcl_dir):
        cloud = read_pcd(path)
        head = _header_values(path)
        width, height = int(head.get("WIDTH", ["0"])[0]), int(head.get("HEIGHT", ["1"])[0])
        kinds.add((head["DATA"][0], height > 1))
        if height > 1:
            assert cloud.is_organized and cloud.points.shape == (height, width, 3), path
        else:
            assert not cloud.is_organized and cloud.points.ndim == 2, path
        ref = o3d.io.read_point_cloud(
            str(path), remove_nan_points=False, remove_infinite_points=False
        )
        ref_points = np.asarray(ref.points)
        ours = cloud.points.reshape(-1, 3)
        # Open3D parses ascii as float64; the file's type is float32, so compare in it.
        np.testing.assert_array_equal(ours, ref_points.astype(ours.dtype), err_msg=str(path))
        assert ref.has_colors() == (cloud.colors is not None), path
        if ref.has_colors():
            ref_colors = np.round(np.asarray(ref.colors) * 255).astype(np.uint8)
            np.testing.assert_array_equal(
                cloud.colors.reshape(-1, 3), ref_colors, err_msg=str(path)
            )
        assert ref.has_normals() == (cloud.normals is not None), path
        if ref.has_normals():
            ref_normals = np.asarray(ref.normals).astype(cloud.normals.dtype)
            np.testing.assert_array_equal(
                cloud.normals.reshape(-1, 3), ref_normals, err_msg=str(path)
            )
    # The shared data exercises ascii (v.5 and 0.7) and compressed, organized and not.
    assert {("ascii", False), ("binary_compressed", True)} <= kinds


def test_real_ascii_files_agree_with_loadtxt(pcl_dir):
    """A second, numpy-only route for the ascii files (runs without open3d)."""
    checked = 0
    for path in _real_files(pcl_dir):
        head = _header_values(path)
        if head["DATA"][0] != "ascii":
            continue
        with open(path, "rb") as f:
            n_header = next(i for i, line in enumerate(f) if line.startswith(b"DATA")) + 1
        table = np.loadtxt(path, skiprows=n_header, dtype=np.float32, ndmin=2)
        cloud = read_pcd(path)
        assert list(cloud.fields) == head["FIELDS"], path
        for k, name in enumerate(head["FIELDS"]):
            np.testing.assert_array_equal(cloud.fields[name], table[:, k], err_msg=f"{path} {name}")
        np.testing.assert_array_equal(cloud.points, table[:, :3])
        checked += 1
    assert checked


def test_real_organized_files(pcl_dir):
    organized = [
        p for p in _real_files(pcl_dir) if int(_header_values(p).get("HEIGHT", ["1"])[0]) > 1
    ]
    if not organized:
        pytest.skip("no organized cloud in the shared data")
    path = organized[0]
    cloud = read_pcd(path)
    mask = cloud.finite_mask
    assert mask.shape == cloud.points.shape[:2]
    assert 0 < mask.sum() < mask.size  # real depth images have holes
    assert np.isnan(cloud.points[~mask]).all()
    np.testing.assert_array_equal(cloud.finite_points(), cloud.points[mask])
    np.testing.assert_array_equal(load_points(path), cloud.finite_points())
    assert cloud.colors.dtype == np.uint8 and cloud.colors.shape == cloud.points.shape
    assert cloud.fields["rgba"].shape == mask.shape


# ------------------------------------------------------------------------------------------
# LZF
# ------------------------------------------------------------------------------------------


def test_lzf_decodes_hand_written_stream():
    # literal "abc"; back-reference length 5 at distance 3 (overlapping); long back-reference
    # of length 7 + 2 + 3 = 12 at distance 1; literal "Z".
    stream = b"\x02abc" + bytes([3 << 5, 2]) + bytes([7 << 5, 3, 0]) + b"\x00Z"
    assert bytes(lzf_decompress(stream, 21)) == b"abcabcab" + b"b" * 12 + b"Z"


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.one_of(
            st.binary(max_size=40),
            st.tuples(st.binary(min_size=1, max_size=5), st.integers(1, 400)).map(
                lambda t: t[0] * t[1]
            ),
        ),
        max_size=12,
    )
)
def test_lzf_round_trip(parts):
    raw = b"".join(parts)
    packed = lzf_compress(raw)
    assert bytes(lzf_decompress(packed, len(raw))) == raw
    assert len(packed) <= len(raw) + (len(raw) + 31) // 32  # never worse than all literals


def test_lzf_compresses_runs_and_far_repeats():
    block = np.random.default_rng(0).bytes(3000)
    run = b"\x00\x00\xc0\x7f" * 20_000  # float32 NaN, as in organized clouds
    raw = run + block + block  # the second block repeats 3000 bytes back
    packed = lzf_compress(raw)
    assert len(packed) < 4_200  # 86000 bytes: 303 max-length references + 3000 literals
    assert len(packed) - len(lzf_compress(run + block)) < 50  # the repeat costs ~12 tokens
    assert bytes(lzf_decompress(packed, len(raw))) == raw


@pytest.mark.parametrize(
    "stream, out_len, match",
    [
        (bytes([1 << 5, 0]), 3, "before the start"),
        (b"\x00a" + bytes([1 << 5, 5]), 4, "before the start"),
        (b"\x05abc", 6, "truncated inside a literal"),
        (b"\x00a" + bytes([7 << 5]), 20, "truncated inside a back-reference"),
        (b"\x00a" + bytes([1 << 5]), 4, "truncated inside a back-reference"),
        (b"\x03abcd", 2, "beyond the declared"),
        (b"\x00a" + bytes([7 << 5, 255, 0]), 10, "beyond the declared"),
        (b"\x02abc", 10, "ends after 3"),
        (b"\x00a", 200, "cannot expand 2 bytes to 200"),
    ],
)
def test_lzf_rejects_corrupt_streams(stream, out_len, match):
    with pytest.raises(ValueError, match=match):
        lzf_decompress(stream, out_len)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=64), st.integers(0, 600))
def test_lzf_garbage_decodes_exactly_or_raises(stream, out_len):
    try:
        out = lzf_decompress(stream, out_len)
    except ValueError:
        return
    assert len(out) == out_len


# ------------------------------------------------------------------------------------------
# Header variants and field types
# ------------------------------------------------------------------------------------------


def test_v05_header_defaults(tmp_path):
    """v.5 files may lack SIZE/TYPE/COUNT, WIDTH/HEIGHT and VIEWPOINT, and say COLUMNS."""
    path = tmp_path / "old.pcd"
    path.write_bytes(
        b"# .PCD v.5\nVERSION .5\nCOLUMNS x y z\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 nan\n"
    )
    cloud = read_pcd(path)
    assert cloud.points.dtype == np.float32 and not cloud.is_organized
    np.testing.assert_array_equal(cloud.points, [[1, 2, 3], [4, 5, np.nan]])
    np.testing.assert_array_equal(cloud.viewpoint, [1, 0, 0, 0, 0, 0, 0])
    assert cloud.colors is None and cloud.normals is None
    np.testing.assert_array_equal(cloud.finite_points(), [[1, 2, 3]])


def test_viewpoint_is_wxyz_xyz(tmp_path):
    path = tmp_path / "vp.pcd"
    path.write_bytes(
        _header("xyz", [4] * 3, "FFF", [1] * 3, 1, 1, 1, "ascii", "1 2 3 0 1 0 0") + b"0 0 0\n"
    )
    np.testing.assert_array_equal(read_pcd(path).viewpoint, [0, 1, 0, 0, 1, 2, 3])


_KIND = {"F": "f", "U": "u", "I": "i"}
_ALL_TYPES = [
    ("F", 4),
    ("F", 8),
    ("U", 1),
    ("U", 2),
    ("U", 4),
    ("U", 8),
    ("I", 1),
    ("I", 2),
    ("I", 4),
    ("I", 8),
]


def _typed_cloud(n, rng):
    """Every PCD type, a COUNT-33 field and a padding field, as (header fields, arrays)."""
    fields = [("x", "F", 4, 1), ("y", "F", 4, 1), ("z", "F", 8, 1)]
    fields += [(f"v_{t}{s}", t, s, 1) for t, s in _ALL_TYPES]
    fields += [("fpfh", "F", 4, 33), ("_", "U", 1, 3), ("rgba", "U", 4, 1)]
    arrays = {}
    for name, t, s, c in fields:
        dtype = np.dtype(f"<{_KIND[t]}{s}")
        if t == "F":
            values = rng.normal(size=(n, c)).astype(dtype)
        else:
            info = np.iinfo(dtype)
            values = rng.integers(info.min, info.max, size=(n, c), dtype=dtype, endpoint=True)
        arrays[name] = values
    return fields, arrays


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_every_type_count_and_padding(tmp_path, data):
    rng = np.random.default_rng(1)
    n = 7
    fields, arrays = _typed_cloud(n, rng)
    head = _header(
        [f[0] for f in fields],
        [f[2] for f in fields],
        [f[1] for f in fields],
        [f[3] for f in fields],
        n,
        1,
        n,
        data,
    )
    if data == "ascii":
        rows = []
        for i in range(n):
            rows.append(" ".join(repr(v.item()) for name, *_ in fields for v in arrays[name][i]))
        body = ("\n".join(rows) + "\n").encode()
    elif data == "binary":
        body = b"".join(
            b"".join(arrays[name][i].tobytes() for name, *_ in fields) for i in range(n)
        )
    else:
        raw = b"".join(arrays[name].tobytes() for name, *_ in fields)
        packed = _literal_lzf(raw)
        body = struct.pack("<II", len(packed), len(raw)) + packed
    path = tmp_path / f"{data}.pcd"
    path.write_bytes(head + body)
    cloud = read_pcd(path)
    assert "_" not in cloud.fields
    for name, _, _, count in fields:
        if name == "_":
            continue
        expected = arrays[name] if count > 1 else arrays[name][:, 0]
        assert cloud.fields[name].dtype == arrays[name].dtype, name
        np.testing.assert_array_equal(cloud.fields[name], expected, err_msg=name)
    assert cloud.fields["fpfh"].shape == (n, 33)
    assert cloud.points.dtype == np.float64  # x, y float32 and z float64 promote
    bits = arrays["rgba"][:, 0]
    np.testing.assert_array_equal(cloud.colors[:, 0], (bits >> 16) & 255)
    np.testing.assert_array_equal(cloud.colors[:, 2], bits & 255)


def test_ascii_float_rgb_accepts_bit_pattern_and_float(tmp_path):
    """PCL writes a float `rgb` as its uint32 bits in decimal; older writers print the float."""
    packed = np.array([0x00102030, 0xFF405060], np.uint32)
    as_float = packed.view(np.float32)
    path = tmp_path / "rgb.pcd"
    body = f"0 0 0 {packed[0]}\n0 0 0 {as_float[1].item()!r}\n".encode()
    path.write_bytes(
        _header(["x", "y", "z", "rgb"], [4] * 4, "FFFF", [1] * 4, 2, 1, 2, "ascii") + body
    )
    cloud = read_pcd(path)
    np.testing.assert_array_equal(cloud.colors, [[0x10, 0x20, 0x30], [0x40, 0x50, 0x60]])


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_empty_cloud_round_trip(tmp_path, data):
    path = tmp_path / "empty.pcd"
    write_pcd(path, np.zeros((0, 3), np.float32), colors=np.zeros((0, 3), np.uint8), data=data)
    cloud = read_pcd(path)
    assert cloud.points.shape == (0, 3) and cloud.colors.shape == (0, 3)
    with pytest.raises(ValueError, match="no finite points"):
        load_points(path)


def test_ascii_long_token_is_cheap(tmp_path):
    """One megabyte-long number must not cost a megabyte per value (no fixed-width table)."""
    path = tmp_path / "long.pcd"
    path.write_bytes(_xyz(2000, 1, 2000, "ascii") + b"1 2 3\n" * 1999 + b"1 2 " + b"7" * 10**6)
    with _peak_memory() as peak:
        cloud = read_pcd(path)
    assert peak[0] < 32 * 2**20  # a table of 6000 megabyte-wide strings would need 6 GB
    assert cloud.points[-1, 2] == np.inf and (cloud.points[:-1] == [1, 2, 3]).all()


def test_organized_binary_keeps_layout(tmp_path):
    points = np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)
    points[1, 2] = np.nan
    path = tmp_path / "grid.pcd"
    path.write_bytes(_header("xyz", [4] * 3, "FFF", [1] * 3, 3, 2, 6, "binary") + points.tobytes())
    cloud = read_pcd(path)
    assert cloud.is_organized and cloud.fields["x"].shape == (2, 3)
    np.testing.assert_array_equal(cloud.points, points)
    np.testing.assert_array_equal(cloud.finite_mask, [[True] * 3, [True, True, False]])


# ------------------------------------------------------------------------------------------
# Writers
# ------------------------------------------------------------------------------------------


def _random_cloud(shape, dtype, rng, holes=True):
    points = rng.normal(size=shape + (3,)).astype(dtype)
    if holes:
        points.reshape(-1, 3)[::5] = np.nan
    normals = rng.normal(size=shape + (3,)).astype(dtype)
    colors = rng.integers(0, 256, size=shape + (3,), dtype=np.uint8)
    return points, normals, colors


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
@pytest.mark.parametrize("shape", [(40,), (4, 10)], ids=["unorganized", "organized"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_write_pcd_round_trip(tmp_path, data, shape, dtype):
    rng = np.random.default_rng(2)
    points, normals, colors = _random_cloud(shape, dtype, rng)
    viewpoint = np.array([0.5, 0.5, -0.5, 0.5, 1.0, -2.0, 0.25])
    path = tmp_path / "out.pcd"
    write_pcd(path, points, colors=colors, normals=normals, data=data, viewpoint=viewpoint)
    cloud = read_pcd(path)
    assert cloud.points.dtype == dtype and cloud.is_organized == (len(shape) == 2)
    np.testing.assert_array_equal(cloud.points, points)
    np.testing.assert_array_equal(cloud.normals, normals)
    np.testing.assert_array_equal(cloud.colors, colors)
    np.testing.assert_array_equal(cloud.viewpoint, viewpoint)
    assert cloud.fields["rgb"].dtype == np.uint32


def test_write_pcd_points_only_and_float_colors(tmp_path):
    points = np.random.default_rng(3).normal(size=(5, 3))
    path = tmp_path / "plain.pcd"
    write_pcd(path, points, colors=np.full((5, 3), 0.5), data="ascii")
    cloud = read_pcd(path)
    np.testing.assert_array_equal(cloud.points, points)
    assert cloud.normals is None and list(cloud.fields) == ["x", "y", "z", "rgb"]
    np.testing.assert_array_equal(cloud.colors, np.full((5, 3), 128, np.uint8))


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_open3d_reads_our_pcd(tmp_path, data):
    o3d = _open3d()
    points, normals, colors = _random_cloud((4, 25), np.float32, np.random.default_rng(4))
    path = tmp_path / "ours.pcd"
    write_pcd(path, points, colors=colors, normals=normals, data=data)
    ref = o3d.io.read_point_cloud(str(path), remove_nan_points=False, remove_infinite_points=False)
    np.testing.assert_array_equal(np.asarray(ref.points).astype(np.float32), points.reshape(-1, 3))
    np.testing.assert_array_equal(
        np.asarray(ref.normals).astype(np.float32), normals.reshape(-1, 3)
    )
    np.testing.assert_array_equal(np.round(np.asarray(ref.colors) * 255), colors.reshape(-1, 3))


@pytest.mark.parametrize("mode", ["ascii", "binary", "compressed"])
def test_we_read_open3d_pcd(tmp_path, mode):
    o3d = _open3d()
    rng = np.random.default_rng(5)
    ref = o3d.geometry.PointCloud()
    ref.points = o3d.utility.Vector3dVector(rng.normal(size=(300, 3)))
    ref.normals = o3d.utility.Vector3dVector(rng.normal(size=(300, 3)))
    ref.colors = o3d.utility.Vector3dVector(rng.integers(0, 256, size=(300, 3)) / 255)
    path = tmp_path / "open3d.pcd"
    o3d.io.write_point_cloud(
        str(path), ref, write_ascii=mode == "ascii", compressed=mode == "compressed"
    )
    cloud = read_pcd(path)
    # Open3D stores float32 and prints ascii with 10 digits: compare with its own reading.
    back = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(cloud.points, np.asarray(back.points).astype(np.float32))
    np.testing.assert_array_equal(cloud.normals, np.asarray(back.normals).astype(np.float32))
    np.testing.assert_allclose(cloud.points, np.asarray(ref.points), rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(cloud.colors, np.round(np.asarray(ref.colors) * 255))


@pytest.mark.parametrize("data", ["ascii", "binary"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_write_ply_round_trip(tmp_path, data, dtype):
    points, normals, colors = _random_cloud((50,), dtype, np.random.default_rng(6), holes=False)
    path = tmp_path / "cloud.ply"
    write_ply(path, points, colors=colors, normals=normals, data=data)
    got_points, got_normals = load_points(path, with_normals=True)
    np.testing.assert_array_equal(got_points, points)
    np.testing.assert_array_equal(got_normals, normals)
    colors_read = trimesh.load(path).colors[:, :3]
    np.testing.assert_array_equal(colors_read, colors)


def test_open3d_reads_our_ply(tmp_path):
    o3d = _open3d()
    points, normals, colors = _random_cloud(
        (30,), np.float64, np.random.default_rng(7), holes=False
    )
    path = tmp_path / "cloud.ply"
    write_ply(path, points, colors=colors, normals=normals)
    ref = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(ref.points), points)
    np.testing.assert_array_equal(np.asarray(ref.normals), normals)
    np.testing.assert_array_equal(np.round(np.asarray(ref.colors) * 255), colors)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"points": np.zeros((4, 2))}, "shape"),
        ({"points": np.zeros((4, 3)), "colors": np.zeros((3, 3))}, "colors"),
        ({"points": np.zeros((4, 3)), "colors": np.full((4, 3), 300)}, r"\[0, 255\]"),
        ({"points": np.zeros((4, 3)), "normals": np.zeros((4, 2))}, "normals"),
        ({"points": np.zeros((4, 3)), "data": "lzma"}, "data must be"),
    ],
)
def test_writers_reject_bad_input(tmp_path, kwargs, match):
    with pytest.raises(ValueError, match=match):
        write_pcd(tmp_path / "bad.pcd", **kwargs)
    if "data" not in kwargs:
        with pytest.raises(ValueError, match=match):
            write_ply(tmp_path / "bad.ply", **kwargs)


# ------------------------------------------------------------------------------------------
# load_points
# ------------------------------------------------------------------------------------------


def test_load_points_pcd_drops_holes_and_subsamples(tmp_path):
    points, normals, _ = _random_cloud((6, 10), np.float32, np.random.default_rng(8))
    path = tmp_path / "grid.pcd"
    write_pcd(path, points, normals=normals, data="binary_compressed")
    finite = np.isfinite(points).all(-1)
    got, got_normals = load_points(path, with_normals=True)
    np.testing.assert_array_equal(got, points[finite])
    np.testing.assert_array_equal(got_normals, normals[finite])
    sub = load_points(path, n_points=20, seed=3)
    assert sub.shape == (20, 3)
    assert np.isin(sub.view("V12"), got.view("V12")).all()
    np.testing.assert_array_equal(sub, load_points(path, n_points=20, seed=3))
    assert load_points(path, n_points=10_000).shape == got.shape
    write_pcd(path, points)
    with pytest.raises(ValueError, match="no normal_x"):
        load_points(path, with_normals=True)


@pytest.mark.parametrize("suffix", [".obj", ".stl", ".off", ".ply"])
def test_load_points_samples_meshes(tmp_path, suffix):
    path = tmp_path / f"box{suffix}"
    trimesh.creation.box(extents=(1.0, 1.0, 1.0)).export(path)
    points, normals = load_points(path, n_points=500, with_normals=True, seed=1)
    assert points.shape == normals.shape == (500, 3)
    np.testing.assert_allclose(np.abs(points).max(axis=1), 0.5, atol=1e-9)  # on the surface
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.sum(normals * points, axis=1), 0.5, atol=1e-9)  # outward face
    np.testing.assert_array_equal(load_points(path, n_points=500, seed=1), points)
    assert not np.array_equal(load_points(path, n_points=500, seed=2), points)
    assert load_points(path).shape == (10_000, 3)


def test_load_points_scene_of_several_meshes(tmp_path):
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    sphere = trimesh.creation.icosphere(radius=0.5).apply_translation([3.0, 0.0, 0.0])
    path = tmp_path / "scene.glb"
    trimesh.Scene([box, sphere]).export(path)
    points = load_points(path, n_points=2_000)
    on_box = np.abs(points).max(axis=1) < 0.5 + 1e-6
    on_sphere = np.linalg.norm(points - [3.0, 0.0, 0.0], axis=1) < 0.5 + 1e-6
    assert (on_box | on_sphere).all() and on_box.any() and on_sphere.any()


@pytest.mark.parametrize("n_points", [0, -3, 2.5])
def test_load_points_rejects_bad_n_points(tmp_path, n_points):
    path = tmp_path / "one.pcd"
    write_pcd(path, np.zeros((1, 3)))
    with pytest.raises(ValueError, match="n_points"):
        load_points(path, n_points=n_points)


def test_load_points_ply_without_normals(tmp_path):
    path = tmp_path / "plain.ply"
    write_ply(path, np.eye(3), data="ascii")
    np.testing.assert_array_equal(load_points(path), np.eye(3))
    with pytest.raises(ValueError, match="no nx ny nz"):
        load_points(path, with_normals=True)


def test_missing_files(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_pcd(tmp_path / "nope.pcd")
    with pytest.raises(FileNotFoundError):
        load_points(tmp_path / "nope.ply")


def test_load_points_garbage_mesh(tmp_path):
    path = tmp_path / "garbage.stl"
    path.write_bytes(b"\x00\xff" * 10)
    with pytest.raises(ValueError, match="garbage.stl"):
        load_points(path)


# ------------------------------------------------------------------------------------------
# Malformed PCD files: ValueError naming the file and the problem, quickly
# ------------------------------------------------------------------------------------------

_XYZ = {"fields": "xyz", "sizes": [4] * 3, "types": "FFF", "counts": [1] * 3}


def _xyz(width, height, points, data, **over):
    spec = {**_XYZ, **over}
    return _header(
        spec["fields"], spec["sizes"], spec["types"], spec["counts"], width, height, points, data
    )


def _compressed(points: int, compressed: int, uncompressed: int, stream: bytes) -> bytes:
    return (
        _xyz(points, 1, points, "binary_compressed")
        + struct.pack("<II", compressed, uncompressed)
        + stream
    )


_GOOD_STREAM = _literal_lzf(np.zeros(6, np.float32).tobytes())

MALFORMED = {
    "empty": (b"", "empty"),
    "garbage": (bytes(range(256)) * 4, "not text|unknown keyword|no DATA"),
    "no DATA line": (b"VERSION 0.7\nFIELDS x y z\nPOINTS 1\n", "no DATA"),
    "unknown keyword": (b"VERSION 0.7\nFEILDS x\nDATA ascii\n", "unknown keyword"),
    "no FIELDS": (b"VERSION 0.7\nPOINTS 1\nDATA ascii\n0\n", "no FIELDS"),
    "unknown DATA": (_xyz(1, 1, 1, "lzma") + b"\0" * 12, "unknown DATA kind 'lzma'"),
    "unknown TYPE": (_xyz(1, 1, 1, "binary", types="FFQ") + b"\0" * 12, "unknown TYPE 'Q'"),
    "bad SIZE": (_xyz(1, 1, 1, "binary", sizes=[4, 4, 2]) + b"\0" * 12, "unsupported SIZE 2"),
    "SIZE length": (_xyz(1, 1, 1, "binary", sizes=[4, 4]) + b"\0" * 12, "SIZE has 2 entries"),
    "TYPE length": (_xyz(1, 1, 1, "binary", types="FFFF") + b"\0" * 12, "TYPE has 4 entries"),
    "COUNT length": (_xyz(1, 1, 1, "binary", counts=[1]) + b"\0" * 12, "COUNT has 1 entries"),
    "COUNT zero": (_xyz(1, 1, 1, "binary", counts=[1, 1, 0]) + b"\0" * 12, "COUNT 0"),
    "repeated field": (_xyz(1, 1, 1, "binary", fields="xyx") + b"\0" * 12, "repeats"),
    "WIDTH x HEIGHT": (_xyz(4, 2, 7, "binary") + b"\0" * 84, r"WIDTH 4 x HEIGHT 2 != POINTS 7"),
    "negative POINTS": (_xyz(1, 1, -1, "binary"), "non-negative"),
    "text POINTS": (_xyz(1, 1, "many", "binary"), "non-negative integers"),
    "short VIEWPOINT": (
        b"FIELDS x\nVIEWPOINT 0 0 0\nPOINTS 1\nDATA ascii\n1\n",
        "VIEWPOINT needs 7",
    ),
    "HEIGHT without WIDTH": (b"FIELDS x\nHEIGHT 2\nPOINTS 2\nDATA ascii\n1\n2\n", "without WIDTH"),
    "binary truncated": (_xyz(3, 1, 3, "binary") + b"\0" * 35, "needs 36 bytes"),
    "binary giant POINTS": (
        _xyz(10**12, 1, 10**12, "binary") + b"\0" * 64,
        "needs 12000000000000 bytes",
    ),
    "ascii too few rows": (_xyz(3, 1, 3, "ascii") + b"1 2 3\n4 5 6\n", "holds 2 rows"),
    "ascii short row": (_xyz(2, 1, 2, "ascii") + b"1 2 3\n4 5\n", "hold 5 values"),
    "ascii not a number": (_xyz(1, 1, 1, "ascii") + b"1 2 abc\n", "could not convert"),
    "ascii giant integer": (
        _xyz(2000, 1, 2000, "ascii", types="FFU") + b"1 2 3\n" * 1999 + b"1 2 " + b"7" * 10**6,
        "digits",
    ),
    "ascii int overflow": (
        _xyz(1, 1, 1, "ascii", types="FFU", sizes=[4, 4, 1]) + b"1 2 300\n",
        "out of bounds",
    ),
    "compressed no size header": (
        _xyz(2, 1, 2, "binary_compressed") + b"\0" * 5,
        "before its size header",
    ),
    "compressed size beyond file": (
        _compressed(2, 1000, 24, _GOOD_STREAM),
        "declares 1000 compressed bytes",
    ),
    "compressed wrong uncompressed size": (
        _compressed(2, len(_GOOD_STREAM), 25, _GOOD_STREAM),
        "uncompressed size 25 != POINTS 2",
    ),
    "compressed impossible expansion": (
        _header("x", [1], "U", [1], 4_000_000_000, 1, 4_000_000_000, "binary_compressed")
        + struct.pack("<II", 10, 4_000_000_000)
        + b"\0" * 10,
        "cannot expand 10 bytes",
    ),
    "compressed truncated back-reference": (
        _compressed(2, 2, 24, bytes([7 << 5, 14])),
        "truncated inside a back-reference",
    ),
    "compressed back-reference before start": (
        _compressed(2, 3, 24, bytes([7 << 5, 13, 5])),
        "before the start",
    ),
    "compressed stream cut short": (
        _compressed(2, len(_GOOD_STREAM) - 4, 24, _GOOD_STREAM),
        "truncated inside a literal",
    ),
}


@pytest.mark.parametrize("content, match", list(MALFORMED.values()), ids=list(MALFORMED))
def test_malformed_pcd_raises_value_error(tmp_path, content, match):
    path = tmp_path / "broken.pcd"
    path.write_bytes(content)
    with _peak_memory() as peak, pytest.raises(ValueError, match=match) as info:
        read_pcd(path)
    assert str(path) in str(info.value)
    # Declared sizes (up to 12 TB here) are checked against the file before any allocation.
    assert peak[0] < 32 * 2**20


def test_load_points_with_colors_from_clouds_and_meshes(tmp_path):
    """Colours as estimate_pose's model_colors take them (uint8 RGB): a PLY's and a PCD's
    vertex colours row for row (holes dropped with their points), a mesh's vertex colours
    interpolated at each surface sample; a file without colours says so."""
    rng = np.random.default_rng(4)
    points = rng.random((50, 3)).astype(np.float32)
    colors = rng.integers(0, 256, (50, 3)).astype(np.uint8)
    points[7] = np.nan
    for name, write in (("c.ply", write_ply), ("c.pcd", write_pcd)):
        write(tmp_path / name, points, colors=colors)
        loaded, loaded_colors = load_points(tmp_path / name, with_colors=True)
        np.testing.assert_array_equal(loaded, np.delete(points, 7, axis=0))
        np.testing.assert_array_equal(loaded_colors, np.delete(colors, 7, axis=0))
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    paint = np.where(box.vertices[:, :1] > 0, [200, 20, 20, 255], [20, 20, 200, 255])
    box.visual.vertex_colors = paint.astype(np.uint8)  # red at x > 0, blue at x < 0
    box.export(tmp_path / "box.ply")
    samples, normals, sampled = load_points(
        tmp_path / "box.ply", n_points=500, with_normals=True, with_colors=True
    )
    assert samples.shape == normals.shape == sampled.shape == (500, 3)
    expected = 20 + 180 * (samples[:, 0] + 0.05) / 0.1  # linear across the faces along x
    np.testing.assert_allclose(sampled[:, 0], expected, atol=1.01)
    np.testing.assert_allclose(sampled[:, 2], 220 - expected, atol=1.01)
    write_ply(tmp_path / "plain.ply", points)
    with pytest.raises(ValueError, match="no red green blue vertex colours"):
        load_points(tmp_path / "plain.ply", with_colors=True)
    trimesh.creation.box((0.1, 0.1, 0.1)).export(tmp_path / "plain_box.stl")
    with pytest.raises(ValueError, match="no vertex colours or texture"):
        load_points(tmp_path / "plain_box.stl", with_colors=True)
