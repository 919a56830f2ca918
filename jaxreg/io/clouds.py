"""Point-cloud files: PCD (every variant PCL writes), PLY/OBJ/STL/OFF through trimesh, writers.

Everything here runs on the host and returns numpy arrays; hand the results to the JAX solvers
with ``jnp.asarray``.

PCD support covers what PCL's ``PCDReader`` accepts:

* versions ``.5`` / ``.6`` / ``0.7``; header lines PCL made optional default the way PCL
  defaults them (no ``SIZE``/``TYPE``/``COUNT``: 4-byte floats, one value each; no
  ``WIDTH``/``HEIGHT``: an unorganized cloud of ``POINTS`` points; no ``VIEWPOINT``: the
  identity; ``COLUMNS`` is read as ``FIELDS``);
* ``DATA ascii``, ``binary`` and ``binary_compressed`` (LZF, :mod:`jaxreg.io._lzf`, in PCL's
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

from jaxreg.io import _lzf, _pcd

__all__ = [
    "PointCloud",
    "load_points",
    "read_pcd",
    "write_pcd",
    "write_ply",
]

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
        header, columns = _pcd.decode(raw)
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
    for name in _pcd.COLOR_FIELDS:
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


def _load_with_trimesh(path: Path, n_points: int | None, with_normals: bool, with_colors: bool,
                       seed: int):  # fmt: skip
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
        if with_colors:
            arrays += (_surface_colors(path, geometry, np.asarray(samples), face_index),)
        return arrays
    vertices = np.asarray(getattr(geometry, "vertices", np.empty((0, 3)))).reshape(-1, 3)
    arrays = (vertices,)
    if with_normals:
        normals = _ply_vertex_normals(geometry)
        if normals is None:
            raise ValueError(f"{path}: the point cloud has no nx ny nz vertex normals")
        arrays += (normals,)
    if with_colors:
        colors = getattr(geometry, "colors", None)
        if colors is None or len(colors) != len(vertices):
            raise ValueError(f"{path}: the point cloud has no red green blue vertex colours")
        arrays += (np.asarray(colors)[:, :3].astype(np.uint8),)
    mask = np.isfinite(vertices).all(axis=-1)
    return _subsample(tuple(a[mask] for a in arrays), n_points, seed)


def _surface_colors(path: Path, mesh, samples: np.ndarray, face_index: np.ndarray) -> np.ndarray:
    """``(N, 3)`` uint8 RGB of a mesh's surface ``samples`` on faces ``face_index``: its
    vertex colours (a texture's, sampled at the vertices' UVs, when it has one instead)
    interpolated over each face; ``ValueError`` for a mesh with neither."""
    import trimesh

    visual = mesh.visual
    if visual.kind == "texture":
        visual = visual.to_color()
    if visual.kind != "vertex":
        raise ValueError(f"{path}: the mesh has no vertex colours or texture")
    vertex = np.asarray(visual.vertex_colors, np.float64)[:, :3]
    corners = np.asarray(mesh.faces)[face_index]
    weights = trimesh.triangles.points_to_barycentric(
        np.asarray(mesh.vertices)[corners], samples
    )  # fmt: skip
    mixed = np.einsum("nk,nkc->nc", np.clip(weights, 0.0, 1.0), vertex[corners])
    return np.clip(np.rint(mixed), 0, 255).astype(np.uint8)


def load_points(
    path: str | Path,
    *,
    n_points: int | None = None,
    with_normals: bool = False,
    with_colors: bool = False,
    seed: int = 0,
):
    """Loads ``(N, 3)`` finite points from a point-cloud or mesh file.

    * ``.pcd``: `read_pcd`, NaN holes dropped. Normals come from ``normal_x/y/z``, colours
      from ``rgb``.
    * anything trimesh reads (``.ply``, ``.obj``, ``.stl``, ``.off``, ...): a point cloud
      (a PLY without faces) is read as is, with its ``nx/ny/nz`` vertex normals and
      ``red/green/blue`` colours; a mesh is sampled uniformly over its surface area and each
      sample gets its face's normal and the colour there (vertex colours, or a texture's at
      the vertices, interpolated over the face).

    Args:
        path: the file.
        n_points: for a mesh, the number of surface samples (default 10_000). For a point
            cloud, a random subset of this many points (all points when the cloud has fewer,
            or when ``None``).
        with_normals: also return ``(N, 3)`` unit normals; ValueError when the file has none.
        with_colors: also return ``(N, 3)`` uint8 sRGB colours (as
            :func:`jaxreg.estimate_pose`'s ``model_colors`` takes them); ValueError when the
            file has none.
        seed: seeds the mesh sampling and the subset choice.

    Returns:
        ``points`` ``(N, 3)``, or a tuple of ``points``, then ``normals`` and ``colors`` as
        asked. The points' dtype is the file's: float32 for PCD ``F 4`` data, float64 from
        trimesh.

    Raises:
        FileNotFoundError: the file does not exist.
        ValueError: the file is malformed, holds no points, or has no normals or colours
            when asked.
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
        if with_colors:
            if cloud.colors is None:
                raise ValueError(f"{path}: the file has no rgb field")
            arrays += (cloud.colors[mask],)
        arrays = _subsample(arrays, n_points, seed)
    else:
        arrays = _load_with_trimesh(path, n_points, with_normals, with_colors, seed)
    if len(arrays[0]) == 0:
        raise ValueError(f"{path}: the file holds no finite points")
    return arrays if with_normals or with_colors else arrays[0]


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
    _check_data(data, _pcd.DATA_KINDS)
    xyz, nxyz, rgb, grid = _flatten_inputs(points, colors, normals)
    named = [(name, xyz[:, k]) for k, name in enumerate("xyz")]
    if nxyz is not None:
        named += [(f"normal_{name}", nxyz[:, k]) for k, name in enumerate("xyz")]
    if rgb is not None:
        rgb = rgb.astype(np.uint32)
        named.append(("rgb", (rgb[:, 0] << 16) | (rgb[:, 1] << 8) | rgb[:, 2]))
    if viewpoint is None:
        viewpoint = _pcd.IDENTITY_VIEWPOINT
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

