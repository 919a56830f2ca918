"""The PCD file format, read side: header grammar and the three DATA decoders.

Public through :func:`jaxreg.io.read_pcd`, whose module docstring lists the variants accepted
and which builds the `jaxreg.io.PointCloud`; `decode` turns a file's bytes into its `Header`
and one column per field. Host-side numpy only.

Conventions: a field is a little-endian scalar dtype (``TYPE``/``SIZE``) repeated ``COUNT``
times; its column is ``(POINTS, COUNT)`` in that dtype, one per header field in header order,
padding fields ``_`` included. ``binary`` data interleaves the fields point by point
(``Header.point_step`` bytes each), ``binary_compressed`` stores them column-major after LZF
(:mod:`jaxreg.io._lzf`). ``Header.viewpoint`` is in jaxlie's ``wxyz_xyz`` order (the file's is
``tx ty tz qw qx qy qz``). Errors are ``ValueError`` (``OverflowError`` from numpy on absurd
sizes) without the file name, which the caller adds.
"""

from __future__ import annotations

import dataclasses
import struct

import numpy as np

from jaxreg.io import _lzf

IDENTITY_VIEWPOINT = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # jaxlie wxyz_xyz
DATA_KINDS = ("ascii", "binary", "binary_compressed")
COLOR_FIELDS = ("rgb", "rgba")
_HEADER_KEYS = frozenset(
    "VERSION FIELDS COLUMNS SIZE TYPE COUNT WIDTH HEIGHT VIEWPOINT POINTS DATA".split()
)
_TYPE_SIZES = {"F": (4, 8), "U": (1, 2, 4, 8), "I": (1, 2, 4, 8)}
_NUMPY_KIND = {"F": "f", "U": "u", "I": "i"}


@dataclasses.dataclass(frozen=True)
class Field:
    name: str
    dtype: np.dtype  # little-endian scalar dtype
    count: int

    @property
    def nbytes(self) -> int:
        return self.dtype.itemsize * self.count


@dataclasses.dataclass(frozen=True)
class Header:
    fields: tuple[Field, ...]
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


def _parse_header(raw: bytes) -> tuple[Header, int]:
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
        fields.append(Field(name, np.dtype(f"<{_NUMPY_KIND[kind]}{size}"), count))
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

    viewpoint = np.array(IDENTITY_VIEWPOINT)
    if "VIEWPOINT" in entries:
        try:
            values = [float(v) for v in entries["VIEWPOINT"]]
        except ValueError:
            values = []
        if len(values) != 7:
            raise ValueError("VIEWPOINT needs 7 numbers: tx ty tz qw qx qy qz")
        viewpoint = np.array(values[3:] + values[:3])

    data = entries["DATA"][0] if entries["DATA"] else ""
    if data not in DATA_KINDS:
        raise ValueError(
            f"unknown DATA kind {data[:32]!r} (expected one of {', '.join(DATA_KINDS)})"
        )
    return Header(tuple(fields), width, height, points, viewpoint, data), pos


def _parse_ascii_values(tokens: list[bytes], field: Field) -> np.ndarray:
    """Converts one component's tokens (one per point) to the field's dtype.

    Python's ``float``/``int`` parse each token, so a very long token costs its own length
    only (a fixed-width numpy string table would cost it for every token).
    """
    if field.dtype.kind != "f":
        return np.array([int(t) for t in tokens], field.dtype)
    values = np.array([float(t) for t in tokens], field.dtype)
    if field.name in COLOR_FIELDS and field.dtype == np.float32:
        # PCL writes a float rgb as its uint32 bit pattern in decimal; older files print the float.
        integer = np.array([t.isdigit() for t in tokens], bool)
        bits = values.view(np.uint32)
        bits[integer] = np.array([int(t) for t in tokens if t.isdigit()], np.uint32)
    return values


def _read_ascii(body: bytes, header: Header) -> list[np.ndarray]:
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


def _read_binary(body: memoryview, header: Header) -> list[np.ndarray]:
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


def _read_compressed(body: memoryview, header: Header) -> list[np.ndarray]:
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


def decode(raw: bytes) -> tuple[Header, list[np.ndarray]]:
    """The header of a whole PCD file's bytes and its columns, one ``(POINTS, COUNT)`` array
    per field (see the module docstring)."""
    if not raw:
        raise ValueError("the file is empty")
    header, offset = _parse_header(raw)
    body = memoryview(raw)[offset:]
    if header.data == "ascii":
        return header, _read_ascii(bytes(body), header)
    if header.data == "binary":
        return header, _read_binary(body, header)
    return header, _read_compressed(body, header)
