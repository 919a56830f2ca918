"""Point-cloud files: PCD (every variant PCL writes), PLY/OBJ/STL/OFF through trimesh, writers.

Everything here runs on the host and returns numpy arrays; hand the results to the JAX solvers
with ``jnp.asarray``.

PCD support covers what PCL's ``PCDReader`` accepts:

* versions ``.5`` / ``.6`` / ``0.7``; header lines PCL made optional default the way PCL
  defaults them (no ``SIZE``/``TYPE``/``COUNT``: 4-byte floats, one value each; no
  ``WIDTH``/``HEIGHT``: an unorganized cloud of ``POINTS`` points; no ``VIEWPOINT``: the
  identity; ``COLUMNS`` is read as ``FIELDS``);
* ``DATA ascii``, ``binary`` and ``binary_compressed`` (LZF, :mod:`jaxreg._lzf`, in PCL's
  column-major layout: a little-endian ``uint32`` compressed size and uncompressed size, then
  all values of the first field, then all values of the second, ...);
* any field set: ``TYPE`` F (``SIZE`` 4, 8), U and I (``SIZE`` 1, 2, 4, 8), any ``COUNT``
  (FPFH's 33), padding fields named ``_`` (skipped);
* organized clouds (``HEIGHT > 1``) keep their image layout, with NaN where the sensor saw
  nothing.

Malformed files raise ``ValueError`` naming the file and the problem. Every size a header
declares is checked against the bytes actually present before anything is allocated.
"""

from __future__ import annotations

import dataclasses
import struct
from pathlib import Path

import numpy as np

from . import _lzf

__all__ = [
    "PointCloud",
    "load_points",
    "read_frame",
    "read_pcd",
    "write_frame",
    "write_pcd",
    "write_ply",
]

_IDENTITY_VIEWPOINT = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # jaxlie wxyz_xyz
_HEADER_KEYS = frozenset(
    "VERSION FIELDS COLUMNS SIZE TYPE COUNT WIDTH HEIGHT VIEWPOINT POINTS DATA".split()
)
_TYPE_SIZES = {"F": (4, 8), "U": (1, 2, 4, 8), "I": (1, 2, 4, 8)}
_NUMPY_KIND = {"F": "f", "U": "u", "I": "i"}
_DATA_KINDS = ("ascii", "binary", "binary_compressed")
_COLOR_FIELDS = ("rgb", "rgba")
_ASCII_FORMATS = {np.dtype(np.float32): "%.9g", np.dtype(np.float64): "%.17g"}  # bit-exact


@dataclasses.dataclass(frozen=True, eq=False)
class PointCloud:
    """A point cloud as read from a file; host-side numpy arrays.

    Shapes use a leading ``S``: ``S = (H, W)`` for an organized cloud (``HEIGHT > 1`` in the
    file; row-major like the sensor image) and ``S = (N,)`` otherwise.

    Attributes:
        points: ``S + (3,)`` float coordinates in the cloud's frame, NaN where an organized
            cloud has no return; ``None`` when the file has no ``x``/``y``/``z`` fields (for
            example a file of FPFH descriptors). The dtype is the file's (float32 for ``F 4``).
        colors: ``S + (3,)`` uint8 RGB unpacked from the ``rgb`` (or ``rgba``) field, PCL's
            packing ``(a << 24) | (r << 16) | (g << 8) | b``; ``None`` when absent. Divide by
            255 for Open3D's float colors; alpha stays in ``fields["rgba"]``.
        normals: ``S + (3,)`` from ``normal_x``/``normal_y``/``normal_z``; ``None`` when absent.
        fields: every field by name (padding ``_`` excluded), shape ``S`` when its COUNT is 1
            and ``S + (COUNT,)`` otherwise, in the file's dtype (``rgb`` keeps its packed
            bits).
        viewpoint: ``(7,)`` float64 sensor pose in the cloud's frame in jaxlie's
            ``wxyz_xyz`` order (the file stores ``tx ty tz qw qx qy qz``), so
            ``jaxlie.SE3(cloud.viewpoint)`` is the acquisition viewpoint.
    """

    points: np.ndarray | None
    colors: np.ndarray | None
    normals: np.ndarray | None
    fields: dict[str, np.ndarray]
    viewpoint: np.ndarray

    @property
    def is_organized(self) -> bool:
        """True when the cloud keeps an image layout ``(H, W, ...)``."""
        return self.points is not None and self.points.ndim == 3

    @property
    def finite_mask(self) -> np.ndarray:
        """``S`` bool: the points whose three coordinates are finite (depth holes excluded)."""
        if self.points is None:
            raise ValueError("this cloud has no x y z fields")
        return np.isfinite(self.points).all(axis=-1)

    def finite_points(self) -> np.ndarray:
        """``(M, 3)`` points with finite coordinates, in row-major (image) order."""
        return self.points[self.finite_mask]


# --------------------------------------------------------------------------------------------
# PCD reading.


@dataclasses.dataclass(frozen=True)
class _Field:
    name: str
    dtype: np.dtype  # little-endian scalar dtype
    count: int

    @property
    def nbytes(self) -> int:
        return self.dtype.itemsize * self.count


@dataclasses.dataclass(frozen=True)
class _Header:
    fields: tuple[_Field, ...]
    width: int
    height: int
    points: int
    viewpoint: np.ndarray
    data: str

    @property
    def point_step(self) -> int:
        return sum(f.nbytes for f in self.fields)


def _ints(key: str, values: list[str]) -> list[int]:
    if not all(v.isascii() and v.isdigit() for v in values):
        raise ValueError(f"{key} needs non-negative integers, got {' '.join(values)!r}")
    return [int(v) for v in values]


def _one_int(entries: dict[str, list[str]], key: str) -> int | None:
    if key not in entries:
        return None
    values = _ints(key, entries[key])
    if len(values) != 1:
        raise ValueError(f"{key} needs one integer, got {' '.join(entries[key])!r}")
    return values[0]


def _parse_header(raw: bytes) -> tuple[_Header, int]:
    """Returns the header and the byte offset where the data starts."""
    entries: dict[str, list[str]] = {}
    pos = 0
    line_no = 0
    while "DATA" not in entries:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise ValueError("no DATA line: the header is truncated or this is not a PCD file")
        line_no += 1
        try:
            text = raw[pos:end].decode("ascii")
        except UnicodeDecodeError:
            raise ValueError(f"header line {line_no} is not text: not a PCD file") from None
        pos = end + 1
        tokens = text.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        key = tokens[0]
        if key not in _HEADER_KEYS:
            raise ValueError(f"header line {line_no} starts with unknown keyword {key[:32]!r}")
        entries["FIELDS" if key == "COLUMNS" else key] = tokens[1:]

    names = entries.get("FIELDS")
    if not names:
        raise ValueError("the header has no FIELDS")
    n_fields = len(names)
    sizes = _ints("SIZE", entries.get("SIZE", ["4"] * n_fields))
    types = entries.get("TYPE", ["F"] * n_fields)
    counts = _ints("COUNT", entries.get("COUNT", ["1"] * n_fields))
    for key, values in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(values) != n_fields:
            raise ValueError(f"{key} has {len(values)} entries but FIELDS has {n_fields}")
    fields = []
    for name, size, kind, count in zip(names, sizes, types, counts, strict=True):
        if kind not in _TYPE_SIZES:
            raise ValueError(f"field {name!r} has unknown TYPE {kind[:8]!r} (expected F, U or I)")
        if size not in _TYPE_SIZES[kind]:
            raise ValueError(f"field {name!r} has TYPE {kind} with unsupported SIZE {size}")
        if count < 1:
            raise ValueError(f"field {name!r} has COUNT {count}")
        fields.append(_Field(name, np.dtype(f"<{_NUMPY_KIND[kind]}{size}"), count))
    real = [f.name for f in fields if f.name != "_"]
    if len(set(real)) != len(real):
        raise ValueError(f"FIELDS repeats a name: {' '.join(names)}")

    points = _one_int(entries, "POINTS")
    width = _one_int(entries, "WIDTH")
    height = _one_int(entries, "HEIGHT")
    if points is None:
        if width is None:
            raise ValueError("the header has neither POINTS nor WIDTH")
        points = width * (1 if height is None else height)
    if width is None:
        if height not in (None, 1):
            raise ValueError(f"HEIGHT {height} is given without WIDTH")
        width = points
    if height is None:
        height = 1
    if width * height != points:
        raise ValueError(f"WIDTH {width} x HEIGHT {height} != POINTS {points}")

    viewpoint = np.array(_IDENTITY_VIEWPOINT)
    if "VIEWPOINT" in entries:
        try:
            values = [float(v) for v in entries["VIEWPOINT"]]
        except ValueError:
            values = []
        if len(values) != 7:
            raise ValueError("VIEWPOINT needs 7 numbers: tx ty tz qw qx qy qz")
        viewpoint = np.array(values[3:] + values[:3])

    data = entries["DATA"][0] if entries["DATA"] else ""
    if data not in _DATA_KINDS:
        raise ValueError(
            f"unknown DATA kind {data[:32]!r} (expected one of {', '.join(_DATA_KINDS)})"
        )
    return _Header(tuple(fields), width, height, points, viewpoint, data), pos


def _parse_ascii_values(tokens: list[bytes], field: _Field) -> np.ndarray:
    """Converts one component's tokens (one per point) to the field's dtype.

    Python's ``float``/``int`` parse each token, so a very long token costs its own length
    only (a fixed-width numpy string table would cost it for every token).
    """
    if field.dtype.kind != "f":
        return np.array([int(t) for t in tokens], field.dtype)
    values = np.array([float(t) for t in tokens], field.dtype)
    if field.name in _COLOR_FIELDS and field.dtype == np.float32:
        # PCL writes a float rgb as its uint32 bit pattern in decimal; older files print the float.
        integer = np.array([t.isdigit() for t in tokens], bool)
        bits = values.view(np.uint32)
        bits[integer] = np.array([int(t) for t in tokens if t.isdigit()], np.uint32)
    return values


def _read_ascii(body: bytes, header: _Header) -> list[np.ndarray]:
    n = header.points
    width = sum(f.count for f in header.fields)
    rows = [row for row in body.splitlines() if row.strip()]
    if len(rows) < n:
        raise ValueError(f"POINTS declares {n} points but the ascii data holds {len(rows)} rows")
    tokens = b" ".join(rows[:n]).split()
    if len(tokens) != n * width:
        raise ValueError(
            f"the {n} ascii rows hold {len(tokens)} values; the fields need {width} per row"
        )
    columns, start = [], 0
    for field in header.fields:
        parts = [_parse_ascii_values(tokens[start + k :: width], field) for k in range(field.count)]
        columns.append(np.stack(parts, axis=-1).reshape(n, field.count))
        start += field.count
    return columns


def _read_binary(body: memoryview, header: _Header) -> list[np.ndarray]:
    n, step = header.points, header.point_step
    if len(body) < n * step:
        raise ValueError(
            f"POINTS {n} x {step} bytes per point needs {n * step} bytes of binary data, "
            f"the file holds {len(body)}"
        )
    table = np.frombuffer(body, np.uint8, count=n * step).reshape(n, step)
    columns, start = [], 0
    for field in header.fields:
        block = np.ascontiguousarray(table[:, start : start + field.nbytes])
        columns.append(block.view(field.dtype).reshape(n, field.count))
        start += field.nbytes
    return columns


def _read_compressed(body: memoryview, header: _Header) -> list[np.ndarray]:
    n, step = header.points, header.point_step
    expected = n * step
    if len(body) < 8:
        if expected == 0:
            return [np.empty((0, f.count), f.dtype) for f in header.fields]
        raise ValueError("binary_compressed data is truncated before its size header")
    compressed, uncompressed = struct.unpack("<II", body[:8])
    if uncompressed != expected:
        raise ValueError(
            f"binary_compressed uncompressed size {uncompressed} != POINTS {n} x {step} bytes "
            f"per point = {expected}"
        )
    if compressed > len(body) - 8:
        raise ValueError(
            f"binary_compressed declares {compressed} compressed bytes, the file holds "
            f"{len(body) - 8}"
        )
    buffer = _lzf.decompress(bytes(body[8 : 8 + compressed]), uncompressed)
    columns, start = [], 0
    for field in header.fields:  # column-major: all of field 1, then all of field 2, ...
        columns.append(
            np.frombuffer(buffer, field.dtype, count=n * field.count, offset=start)
            .reshape(n, field.count)
            .copy()
        )
        start += n * field.nbytes
    return columns


def read_pcd(path: str | Path) -> PointCloud:
    """Reads a PCD file of any version, DATA kind and field set PCL writes.

    Args:
        path: the ``.pcd`` file.

    Returns:
        A `PointCloud`: ``points`` ``(H, W, 3)`` with NaN holes for an organized cloud
        (``HEIGHT > 1``), ``(N, 3)`` otherwise; ``colors`` (uint8), ``normals`` and every field
        by name in ``fields``; ``viewpoint`` in jaxlie ``wxyz_xyz`` order.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is empty, its header is malformed or inconsistent, or its data is
            truncated or corrupt; the message names the file and the problem.
    """
    path = Path(path)
    raw = path.read_bytes()
    try:
        if not raw:
            raise ValueError("the file is empty")
        header, offset = _parse_header(raw)
        body = memoryview(raw)[offset:]
        if header.data == "ascii":
            columns = _read_ascii(bytes(body), header)
        elif header.data == "binary":
            columns = _read_binary(body, header)
        else:
            columns = _read_compressed(body, header)
    except (ValueError, OverflowError) as error:
        raise ValueError(f"{path}: {error}") from None

    shape = (header.height, header.width) if header.height > 1 else (header.points,)
    fields = {}
    for field, column in zip(header.fields, columns, strict=True):
        if field.name != "_":
            fields[field.name] = column.reshape(shape + ((field.count,) if field.count > 1 else ()))

    def stacked(names: tuple[str, str, str]) -> np.ndarray | None:
        if not all(name in fields for name in names):
            return None
        parts = [fields[name] for name in names]
        if any(part.shape != shape for part in parts):
            raise ValueError(f"{path}: fields {' '.join(names)} must have COUNT 1")
        return np.stack(parts, axis=-1).astype(np.result_type(*parts, np.float32))

    colors = None
    for name in _COLOR_FIELDS:
        if name in fields and fields[name].shape == shape and fields[name].dtype.itemsize == 4:
            bits = fields[name].view(np.uint32)
            colors = np.stack([bits >> 16, bits >> 8, bits], axis=-1).astype(np.uint8)
            break
    return PointCloud(
        points=stacked(("x", "y", "z")),
        colors=colors,
        normals=stacked(("normal_x", "normal_y", "normal_z")),
        fields=fields,
        viewpoint=header.viewpoint,
    )


# --------------------------------------------------------------------------------------------
# load_points: .pcd and everything trimesh reads.


def _subsample(arrays: tuple[np.ndarray, ...], n_points: int | None, seed: int):
    count = len(arrays[0])
    if n_points is None or n_points >= count:
        return arrays
    keep = np.sort(np.random.default_rng(seed).choice(count, n_points, replace=False))
    return tuple(a[keep] for a in arrays)


def _ply_vertex_normals(geometry) -> np.ndarray | None:
    """``nx ny nz`` of a PLY point cloud, from the raw vertex table trimesh keeps in metadata
    (a structured array for binary files, a dict of columns for ascii ones)."""
    vertex = geometry.metadata.get("_ply_raw", {}).get("vertex", {}).get("data")
    if isinstance(vertex, dict):
        names = set(vertex)
    elif isinstance(vertex, np.ndarray) and vertex.dtype.names:
        names = set(vertex.dtype.names)
    else:
        return None
    if not {"nx", "ny", "nz"} <= names:
        return None
    return np.stack([vertex["nx"], vertex["ny"], vertex["nz"]], axis=-1).reshape(-1, 3)


def _load_with_trimesh(path: Path, n_points: int | None, with_normals: bool, seed: int):
    import trimesh  # imported here so that `import jaxreg` stays light

    try:
        geometry = trimesh.load(path, process=False)
        if isinstance(geometry, trimesh.Scene):  # several parts: one mesh in world coordinates
            geometry = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # noqa: BLE001 (trimesh's loaders raise many types)
        raise ValueError(f"{path}: trimesh cannot read it: {error}") from None
    faces = getattr(geometry, "faces", None)
    if faces is not None and len(faces):
        samples, face_index = trimesh.sample.sample_surface(
            geometry, 10_000 if n_points is None else n_points, seed=seed
        )
        arrays = (np.asarray(samples),)
        if with_normals:
            arrays += (np.asarray(geometry.face_normals)[face_index],)
        return arrays
    vertices = np.asarray(getattr(geometry, "vertices", np.empty((0, 3)))).reshape(-1, 3)
    arrays = (vertices,)
    if with_normals:
        normals = _ply_vertex_normals(geometry)
        if normals is None:
            raise ValueError(f"{path}: the point cloud has no nx ny nz vertex normals")
        arrays += (normals,)
    mask = np.isfinite(vertices).all(axis=-1)
    return _subsample(tuple(a[mask] for a in arrays), n_points, seed)


def load_points(
    path: str | Path, *, n_points: int | None = None, with_normals: bool = False, seed: int = 0
):
    """Loads ``(N, 3)`` finite points from a point-cloud or mesh file.

    * ``.pcd``: `read_pcd`, NaN holes dropped. Normals come from ``normal_x/y/z``.
    * anything trimesh reads (``.ply``, ``.obj``, ``.stl``, ``.off``, ...): a point cloud
      (a PLY without faces) is read as is, with its ``nx/ny/nz`` vertex normals; a mesh is
      sampled uniformly over its surface area and each sample gets its face's normal.

    Args:
        path: the file.
        n_points: for a mesh, the number of surface samples (default 10_000). For a point
            cloud, a random subset of this many points (all points when the cloud has fewer,
            or when ``None``).
        with_normals: also return ``(N, 3)`` unit normals; ValueError when the file has none.
        seed: seeds the mesh sampling and the subset choice.

    Returns:
        ``points`` ``(N, 3)``, or ``(points, normals)`` with ``with_normals``. The dtype is
        the file's: float32 for PCD ``F 4`` data, float64 from trimesh.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is malformed, holds no points, or has no normals when asked.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if n_points is not None and (not isinstance(n_points, (int, np.integer)) or n_points < 1):
        raise ValueError(f"n_points must be a positive integer, got {n_points!r}")
    if path.suffix.lower() == ".pcd":
        cloud = read_pcd(path)
        if cloud.points is None:
            raise ValueError(f"{path}: the file has no x y z fields")
        mask = cloud.finite_mask
        arrays = (cloud.points[mask],)
        if with_normals:
            if cloud.normals is None:
                raise ValueError(f"{path}: the file has no normal_x normal_y normal_z fields")
            arrays += (cloud.normals[mask],)
        arrays = _subsample(arrays, n_points, seed)
    else:
        arrays = _load_with_trimesh(path, n_points, with_normals, seed)
    if len(arrays[0]) == 0:
        raise ValueError(f"{path}: the file holds no finite points")
    return arrays if with_normals else arrays[0]


# --------------------------------------------------------------------------------------------
# Writers.


def _as_uint8_colors(colors, shape: tuple[int, ...]) -> np.ndarray:
    colors = np.asarray(colors)
    if colors.shape != shape:
        raise ValueError(f"colors must have the points' shape {shape}, got {colors.shape}")
    if np.issubdtype(colors.dtype, np.floating):
        if not np.isfinite(colors).all():
            raise ValueError("float colors must be finite, in [0, 1]")
        return np.round(np.clip(colors, 0.0, 1.0) * 255).astype(np.uint8)
    if colors.size and (colors.min() < 0 or colors.max() > 255):
        raise ValueError("integer colors must lie in [0, 255]")
    return colors.astype(np.uint8)


def _flatten_inputs(points, colors, normals):
    """Validates writer inputs; returns flat ``(M, 3)`` points, normals or None, uint8 colors
    or None, and the grid shape (``(H, W)`` or ``(N,)``)."""
    points = np.asarray(points)
    if points.ndim not in (2, 3) or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (N, 3) or (H, W, 3), got {points.shape}")
    dtype = np.float64 if points.dtype == np.float64 else np.float32
    flat_normals = None
    if normals is not None:
        normals = np.asarray(normals)
        if normals.shape != points.shape:
            raise ValueError(
                f"normals must have the points' shape {points.shape}, got {normals.shape}"
            )
        flat_normals = normals.reshape(-1, 3).astype(dtype)
    flat_colors = None
    if colors is not None:
        flat_colors = _as_uint8_colors(colors, points.shape).reshape(-1, 3)
    return points.reshape(-1, 3).astype(dtype), flat_normals, flat_colors, points.shape[:-1]


def _check_data(data: str, allowed: tuple[str, ...]) -> None:
    if data not in allowed:
        raise ValueError(f"data must be one of {', '.join(allowed)}, got {data!r}")


def _ascii_table(columns: list[tuple[str, np.ndarray]]) -> bytes:
    """One row per point; floats with enough digits to read back bit-exactly."""
    row = " ".join(_ASCII_FORMATS.get(column.dtype, "%d") for _, column in columns)
    values = zip(*(column.tolist() for _, column in columns), strict=True)
    return "".join(row % v + "\n" for v in values).encode("ascii")


def _binary_table(columns: list[tuple[str, np.ndarray]]) -> bytes:
    """One little-endian record per point, the columns interleaved (PCD and PLY binary)."""
    table = np.empty(
        len(columns[0][1]), np.dtype([(name, col.dtype.newbyteorder("<")) for name, col in columns])
    )
    for name, col in columns:
        table[name] = col
    return table.tobytes()


def write_pcd(
    path: str | Path,
    points,
    *,
    colors=None,
    normals=None,
    data: str = "binary",
    viewpoint=None,
) -> None:
    """Writes a PCD v0.7 file that PCL, Open3D and `read_pcd` read back exactly.

    Args:
        path: the output file.
        points: ``(N, 3)``, or ``(H, W, 3)`` for an organized cloud (NaN holes allowed).
            Written as ``F 8`` when float64, ``F 4`` otherwise.
        colors: optional, the points' shape; uint8 in [0, 255] or float in [0, 1]. Written
            like Open3D does, as one packed ``rgb`` field of ``TYPE U SIZE 4``.
        normals: optional, the points' shape; fields ``normal_x normal_y normal_z``.
        data: ``"binary"``, ``"ascii"`` or ``"binary_compressed"`` (LZF).
        viewpoint: optional ``(7,)`` sensor pose in jaxlie ``wxyz_xyz`` order (identity by
            default), the convention of `PointCloud.viewpoint`.
    """
    _check_data(data, _DATA_KINDS)
    xyz, nxyz, rgb, grid = _flatten_inputs(points, colors, normals)
    named = [(name, xyz[:, k]) for k, name in enumerate("xyz")]
    if nxyz is not None:
        named += [(f"normal_{name}", nxyz[:, k]) for k, name in enumerate("xyz")]
    if rgb is not None:
        rgb = rgb.astype(np.uint32)
        named.append(("rgb", (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]))
    if viewpoint is None:
        viewpoint = _IDENTITY_VIEWPOINT
    viewpoint = np.asarray(viewpoint, np.float64)
    if viewpoint.shape != (7,):
        raise ValueError(f"viewpoint must have shape (7,) (wxyz_xyz), got {viewpoint.shape}")

    n = len(named[0][1])
    height, width = grid if len(grid) == 2 else (1, n)
    kinds = {"f": "F", "u": "U", "i": "I"}
    vp = np.concatenate([viewpoint[4:], viewpoint[:4]])
    header = "\n".join(
        [
            "# .PCD v0.7 - Point Cloud Data file format",
            "VERSION 0.7",
            "FIELDS " + " ".join(name for name, _ in named),
            "SIZE " + " ".join(str(col.dtype.itemsize) for _, col in named),
            "TYPE " + " ".join(kinds[col.dtype.kind] for _, col in named),
            "COUNT " + " ".join("1" for _ in named),
            f"WIDTH {width}",
            f"HEIGHT {height}",
            "VIEWPOINT " + " ".join(f"{v:.17g}" for v in vp),
            f"POINTS {n}",
            f"DATA {data}",
            "",
        ]
    ).encode("ascii")
    if data == "ascii":
        body = _ascii_table(named)
    elif data == "binary":
        body = _binary_table(named)
    else:
        raw = b"".join(col.astype(col.dtype.newbyteorder("<")).tobytes() for _, col in named)
        packed = _lzf.compress(raw)
        body = struct.pack("<II", len(packed), len(raw)) + packed
    Path(path).write_bytes(header + body)


def write_ply(path: str | Path, points, *, colors=None, normals=None, data: str = "binary") -> None:
    """Writes the points as a PLY vertex list (no faces).

    Args:
        path: the output file.
        points: ``(..., 3)``; an organized ``(H, W, 3)`` cloud is flattened row-major, NaN kept.
            Stored as ``double`` when float64, ``float`` otherwise.
        colors: optional, the points' shape; uint8 in [0, 255] or float in [0, 1]; stored as
            ``uchar red green blue``.
        normals: optional, the points' shape; stored as ``nx ny nz``.
        data: ``"binary"`` (little endian) or ``"ascii"``.
    """
    _check_data(data, ("binary", "ascii"))
    xyz, nxyz, rgb, _ = _flatten_inputs(points, colors, normals)
    columns = [(name, xyz[:, k]) for k, name in enumerate("xyz")]
    if nxyz is not None:
        columns += [(name, nxyz[:, k]) for k, name in enumerate(("nx", "ny", "nz"))]
    if rgb is not None:
        columns += [(name, rgb[:, k]) for k, name in enumerate(("red", "green", "blue"))]
    ply_types = {"f4": "float", "f8": "double", "u1": "uchar"}
    n = len(columns[0][1])
    lines = [
        "ply",
        "format ascii 1.0" if data == "ascii" else "format binary_little_endian 1.0",
        "comment written by jaxreg",
        f"element vertex {n}",
    ]
    lines += [f"property {ply_types[col.dtype.str[1:]]} {name}" for name, col in columns]
    header = ("\n".join(lines + ["end_header", ""])).encode("ascii")
    if data == "ascii":
        body = _ascii_table(columns)
    else:
        body = _binary_table(columns)
    Path(path).write_bytes(header + body)


# RGB-D frames (organized PCD, depth PNG + intrinsics JSON) are read with read_pcd above, so
# their module imports this one; they are re-exported here, where users look for file input.
from jaxreg._frames import read_frame, write_frame  # noqa: E402
