"""The model as the register stage takes it, prepared once per distinct model array: voxelled,
with normals and two neighbour grids, every array padded to a size class so that a new model
runs the programs compiled for the one before; and a symmetry as arrays of fixed shapes.

Frames: the model's points are in the object frame (metres).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math

import numpy as np
from scipy.spatial import ConvexHull, cKDTree
from scipy.spatial.transform import Rotation

from jaxreg.geometry.metrics import Symmetry, diameter
from jaxreg.search.neighbors import (
    NeighborGrid,
    build_grid,
    cell_codes,
    pad_grid,
    voxel_downsample,
)
from jaxreg.search.normals import estimate_normals


@dataclasses.dataclass(frozen=True, eq=False)
class _Model:
    points: np.ndarray  # (R, 3) object frame, voxelled; NaN rows pad it to a size of _ROWS
    normals: np.ndarray  # (R, 3), zero on the padding rows
    grid: NeighborGrid  # exact to the coarse registration's largest distance
    fine_grid: NeighborGrid  # exact to the refinement's: shorter candidate lists, faster
    radius: float  # largest distance from the centroid
    diameter: float  # largest distance between two points
    centroid: np.ndarray
    axes: np.ndarray  # (3, 3) principal axes as columns, largest extent first
    bounds: np.ndarray  # (2, 3) least and greatest coordinate along each axis (given points)
    screen: np.ndarray  # (R1, 3) voxelled at 3 voxels: the coarse starts' first judgement
    sampling: tuple[float, float]  # (rms, gap) metres: see _sampling
    plane_offset: float  # metres: see _plane_offset
    self_misfits: np.ndarray  # (3, len(PROBE_ANGLES_DEG)) metres: see _self_misfits
    centre: np.ndarray  # (3,) the centre of the given points' bounding box (object frame)
    hull: np.ndarray  # (F, 4) the voxelled points' convex hull: facets' outward normal, offset
    oriented: bool  # normals given (a mesh's, pointing out): ICP matches only faces seen
    key: tuple = ()  # the model's digest, shape and the settings it was prepared with
    # _coarse_problem's, per schedule (not in the repr that keys stored programs)
    coarse: dict = dataclasses.field(default_factory=dict, repr=False)


_MODELS: dict[tuple, _Model] = {}

# A model's sizes are program shapes: every array the compiled programs take from a model is
# padded to the first of a few sizes that holds it (doubling), so that a new model of a size
# class already met runs the programs compiled before. Rows: NaN points (normals zero), never
# matched or judged. The first class holds ~6,000 voxels (0.1 m^2 of surface at 4 mm: the
# synthetic box, mug, cylinder and container at any sampling have 2.1k-4.6k, in leaves of up
# to 128 candidates), so that a process meets a new model of that range without compiling;
# padding costs the box ~15% of a frame (the judgement reads every row, the coarse scan every
# slot).
_ROWS = 6144  # model points
_SCREEN_ROWS = 512  # the coarse judgement's sparse points
_SYMMETRY_ROWS = 8  # rotations of a Symmetry (a box's 4, a square tray's 8)
# The turns of the model about each of its principal axes (degrees) that the register stage
# examines: the answer turned by each and refined (probes), and the model against itself
# turned by each (_self_misfits).
PROBE_ANGLES_DEG = (
    -150.0, -120.0, -90.0, -60.0, -40.0, -25.0, -12.0, 12.0, 25.0, 40.0, 60.0, 90.0, 120.0,
    150.0, 180.0,
)
# Grid tables (pad_grid's sizes). The coarse grid's leaf map is capped at its size: refining
# a concave model (a mug's handle) deeper costs megabytes for a few candidates less per leaf.
_COARSE_TABLES = {"cells": 1 << 9, "entries": 1 << 20, "leaves": 1 << 14, "capacity": 128}
_FINE_TABLES = {"cells": 1 << 12, "entries": 1 << 17, "leaves": 1 << 14, "capacity": 16}


def _size(n: int, first: int) -> int:
    """The first of ``first``, ``2 first``, ``4 first``, ... that is at least ``n``."""
    return first << max(0, math.ceil(math.log2(max(n, 1) / first)))


def _padded_rows(values: np.ndarray, first: int, fill: float) -> np.ndarray:
    """``values`` ``(N, 3)`` float32 with rows of ``fill`` after them, to ``_size(N, first)``."""
    out = np.full((_size(len(values), first), 3), fill, np.float32)
    out[: len(values)] = values
    return out


def _padded_grid(grid: NeighborGrid, tables: dict) -> NeighborGrid:
    """``grid``'s tables padded to the first sizes of ``tables`` that hold them (each doubled
    as often as it needs)."""
    built = {
        "cells": grid.cells.shape[0],
        "entries": grid.leaf_map.shape[0],
        "leaves": grid.num_leaves,
        "capacity": grid.capacity,
    }
    return pad_grid(grid, **{name: _size(built[name], first) for name, first in tables.items()})


def _voxel_normals(points: np.ndarray, normals: np.ndarray, voxel: float):
    """Voxel centroids of ``points`` and the normalised mean normal of each voxel (zero
    where the normals cancel, as on the two faces of a thin wall)."""
    key = cell_codes(np.floor((points - points.min(0)) / voxel))
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(counts), 6))
    np.add.at(sums, inverse, np.concatenate([points, normals], axis=1))
    mean_normal = sums[:, 3:] / counts[:, None]
    length = np.linalg.norm(mean_normal, axis=1, keepdims=True)
    unit = np.where(length > 0.5, mean_normal / np.maximum(length, 1e-12), 0.0)
    return sums[:, :3] / counts[:, None], unit


def _prepare_model(
    model_points, model_normals, voxel_size: float, grid_distance: float, fine_distance: float
):
    """The model voxelled, with normals and neighbour grids (cached per model array and
    settings): ``grid`` exact to ``grid_distance``, ``fine_grid`` to ``fine_distance``; every
    array a compiled program takes is padded to its size class (``_ROWS`` and the tables)."""
    arrays = [model_points] + ([] if model_normals is None else [model_normals])
    digest = hashlib.sha1(b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)).hexdigest()
    key = (digest, model_points.shape, voxel_size, grid_distance, fine_distance)
    if key in _MODELS:
        return _MODELS[key]
    if model_normals is None:
        points = voxel_downsample(model_points, voxel_size)
    else:
        points, normals = _voxel_normals(model_points, model_normals, voxel_size)
    if len(points) < 10:
        raise ValueError(
            f"the model has {len(points)} points at a {voxel_size * 1e3:g} mm voxel: give at "
            "least a few hundred points on its surface (metres)"
        )
    points = points.astype(np.float32)
    centroid = points.mean(0)
    if model_normals is None:
        normals = np.asarray(estimate_normals(points, k=20, viewpoint=centroid))
    rows = _padded_rows(points, _ROWS, np.nan)
    row_normals = _padded_rows(normals, _ROWS, 0.0)
    usable = np.linalg.norm(row_normals, axis=1) > 0.5
    grid = build_grid(rows, grid_distance, mask=usable, max_map=_COARSE_TABLES["entries"])
    # leaves of at most 16 candidates: queries ~2x faster than the default 48, built once;
    # the default where the model's shape needs longer lists (exact either way)
    fine_grid = build_grid(rows, fine_distance, capacity=16, mask=usable)
    if bool(fine_grid.overflow):
        fine_grid = build_grid(rows, fine_distance, mask=usable)
    grid, fine_grid = _padded_grid(grid, _COARSE_TABLES), _padded_grid(fine_grid, _FINE_TABLES)
    _, vectors = np.linalg.eigh(np.cov((points - centroid).T))
    axes = vectors[:, ::-1]
    given = (model_points - centroid) @ axes  # voxel centroids lie up to half a voxel inside
    given_centre = 0.5 * (given.min(0) + given.max(0))  # the principal box's centre
    model = _Model(
        points=rows,
        normals=row_normals,
        grid=grid,
        fine_grid=fine_grid,
        radius=float(np.linalg.norm(points - centroid, axis=1).max()),
        diameter=diameter(points),
        centroid=centroid,
        axes=axes,
        bounds=np.stack([given.min(0), given.max(0)]),
        screen=_padded_rows(voxel_downsample(points, 3 * voxel_size), _SCREEN_ROWS, np.nan),
        sampling=_sampling(points),
        plane_offset=_plane_offset(points, normals),
        self_misfits=_self_misfits(points, centroid + axes @ given_centre, axes),
        centre=0.5 * (model_points.min(0) + model_points.max(0)).astype(np.float64),
        hull=ConvexHull(points.astype(np.float64)).equations,
        oriented=model_normals is not None,
        key=key,
    )
    if len(_MODELS) > 8:
        _MODELS.clear()
    _MODELS[key] = model
    return model


def viewpoint(model: _Model, frame) -> np.ndarray | None:
    """The camera's centre ``(3,)`` in ``frame``'s base frame, the ICP ``viewpoint`` of
    registrations into an ``oriented`` model (its back faces take no pairs); ``None`` for a
    model whose normals were estimated (their sign on a concave part is a guess)."""
    if not model.oriented:
        return None
    return np.asarray(frame.base_T_camera.translation(), np.float32)


def _sampling(points: np.ndarray, k: int = 6) -> tuple[float, float]:
    """How far a point of the surface lies from the nearest of the model's ``points``
    ``(R, 3)`` (metres), from the area each point stands for (``pi r_k^2 / k``, ``r_k`` the
    distance to its ``k``-th neighbour: a uniform grid of spacing ``h`` gives ``h^2``): the
    RMS distance of a surface point drawn uniformly to its nearest model point
    (``sqrt(sum a^2 / (2 pi sum a))``: the sparse parts weigh by their area), and the gap
    (the radius of the 95th percentile's area). A sparse or unevenly sampled model (a few
    thousand points on a large object) has larger ones than a dense scan voxelled finely."""
    distances, _ = cKDTree(points).query(points, k=k + 1)
    area = np.pi * distances[:, k].astype(np.float64) ** 2 / k
    rms = float(np.sqrt(np.sum(area**2) / (2 * np.pi * np.sum(area))))
    return rms, float(np.sqrt(np.quantile(area, 0.95) / np.pi))


def _plane_offset(points: np.ndarray, normals: np.ndarray) -> float:
    """How far the model's tangent planes miss its own surface (metres): the RMS distance of
    each of ``points`` ``(R, 3)`` from the plane (``normals`` ``(R, 3)``) of its nearest other
    point. Zero on a flat face; the curvature between neighbouring points, edges and corners,
    and noise in a scanned model make it grow: what a point-to-plane residual against this
    model shows even where the sensed surface is the model's own."""
    usable = np.linalg.norm(normals, axis=1) > 0.5
    points, normals = points[usable].astype(np.float64), normals[usable].astype(np.float64)
    _, index = cKDTree(points).query(points, k=2)
    nearest = index[:, 1]
    offset = np.einsum("ij,ij->i", normals[nearest], points - points[nearest])
    return float(np.sqrt(np.mean(offset**2)))


def _self_misfits(points: np.ndarray, centre: np.ndarray, axes: np.ndarray) -> np.ndarray:
    """How far the model lies from itself turned about each of its principal ``axes``
    ``(3, 3)`` (columns) through ``centre`` ``(3,)`` (its principal box's centre) by each of
    ``PROBE_ANGLES_DEG``: the RMS distance of each of ``points`` ``(R, 3)``, turned, to the
    nearest model point (metres, ``(3, A)``, axis-major). About the sampling's RMS for a box's
    or a can's half turns and a can's spin (the turned points fall between the model's own),
    several millimetres where a part moves (a handle, a nozzle): a turn that the view's depth
    cannot tell from the model where it is within the fit's residual gate."""
    points = np.asarray(points, np.float64)
    tree = cKDTree(points)
    angles = np.radians(PROBE_ANGLES_DEG)
    vectors = np.asarray(axes, np.float64).T[:, None, :] * angles[None, :, None]
    turns = Rotation.from_rotvec(vectors.reshape(-1, 3)).as_matrix()  # (3 A, 3, 3)
    turned = np.einsum("tij,nj->tni", turns, points - centre) + centre
    distances, _ = tree.query(turned.reshape(-1, 3))
    rms = np.sqrt(np.mean(distances.reshape(len(turns), -1) ** 2, axis=1))
    return rms.reshape(3, len(angles))


def _bucketed_symmetry(symmetry: Symmetry | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``symmetry`` (``None``: the identity alone) as the arrays :func:`_finish` takes:
    rotations padded to a size of ``_SYMMETRY_ROWS`` by copies of the identity (which select
    nothing new), the continuous axis (``(0, 0, 1)`` without one) and whether it applies, so
    that objects of every symmetry group share one program."""
    if symmetry is None:
        symmetry = Symmetry(np.eye(3)[None])
    rotations = np.asarray(symmetry.rotations, np.float32)
    extra = np.repeat(rotations[:1], _size(len(rotations), _SYMMETRY_ROWS) - len(rotations), 0)
    continuous = symmetry.axis is not None
    axis = np.asarray(symmetry.axis if continuous else (0.0, 0.0, 1.0), np.float32)
    return np.concatenate([rotations, extra]), axis, np.bool_(continuous)
