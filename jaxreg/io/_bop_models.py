"""BOP object models: ``models/obj_<id:06d>.ply`` meshes in millimetres and
``models/models_info.json`` (diameter, symmetries), read into metres.

A PLY without faces is a point model (as :func:`jaxreg.io.ycbv_to_bop` writes PoseCNN's
points): its vertices serve MSSD, MSPD and the pipeline, and its ``mesh`` is ``None`` (VSD,
which renders a surface, cannot score it).

``models_info.json`` maps each object id (a string) to an object with ``diameter`` (mm, the
largest distance between two vertices), optional ``symmetries_discrete`` (a list of row-major
4x4 transforms, translation in mm, the identity not listed) and optional
``symmetries_continuous`` (a list of ``{"axis": [3], "offset": [3 mm]}``: any turn about the
axis through the offset point).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from jaxreg.geometry.bop_metrics import bop_symmetry_transforms
from jaxreg.geometry.metrics import Symmetry
from jaxreg.io._bop_files import load_json, numbers

if TYPE_CHECKING:
    import trimesh

__all__ = ["BopModel", "read_models"]

MM = 1e-3  # metres per millimetre


@dataclasses.dataclass(frozen=True, eq=False)
class BopModel:
    """One BOP object model, in metres.

    Attributes:
        obj_id: the dataset's object id.
        mesh: the model's `trimesh.Trimesh` in its own frame, metres, vertices in file order;
            `None` for a point model (a PLY without faces).
        points: `(N, 3)` float64 the model's vertices (metres): the points BOP's MSSD and MSPD
            are computed on.
        diameter: metres, from models_info's `diameter`.
        symmetry: the library's `Symmetry`: the identity then the discrete rotations, and the
            continuous axis if any (translations of the symmetries are dropped: `Symmetry`
            turns about the origin).
        symmetry_transforms: `(S, 4, 4)` float64 BOP's own discretised set (metres), the
            identity first: the listed discrete transforms as the file gives them, each
            composed with each of the 315 turns about the continuous axis through its offset
            (`jaxreg.geometry.bop_symmetry_transforms`, the toolkit's
            `get_symmetry_transformations(info, max_sym_disc_step=0.01)`).
    """

    obj_id: int
    mesh: trimesh.Trimesh | None
    points: np.ndarray
    diameter: float
    symmetry: Symmetry
    symmetry_transforms: np.ndarray


def _nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(matrix)
    fix = np.diag([1.0, 1.0, np.linalg.det(u @ vt)])
    return u @ fix @ vt


def _transforms(path: Path, where: str, info: dict):
    """The discrete `(D, 4, 4)` (identity first; rotations made exactly orthonormal), the
    same as listed in the file (`(D - 1, 4, 4)`, no identity) and the continuous
    `[(axis, offset)]` symmetries of one models_info entry, metres."""
    discrete, listed_transforms = [np.eye(4)], []
    listed = info.get("symmetries_discrete", [])
    if not isinstance(listed, list):
        raise ValueError(f"{path}: {where}: symmetries_discrete must be a list of 4x4 transforms")
    for k, flat in enumerate(listed):
        matrix = numbers(path, f"{where}: symmetries_discrete[{k}]", flat, 16).reshape(4, 4)
        rotation = matrix[:3, :3]
        if np.abs(rotation.T @ rotation - np.eye(3)).max() > 1e-3 or np.linalg.det(rotation) < 0:
            raise ValueError(
                f"{path}: {where}: symmetries_discrete[{k}] is not a rotation (row-major 4x4, "
                "translation in mm)"
            )
        transform = np.eye(4)
        transform[:3, :3] = _nearest_rotation(rotation)
        transform[:3, 3] = matrix[:3, 3] * MM
        discrete.append(transform)
        as_listed = np.vstack([matrix[:3], [0.0, 0.0, 0.0, 1.0]])
        as_listed[:3, 3] *= MM
        listed_transforms.append(as_listed)
    continuous = []
    listed = info.get("symmetries_continuous", [])
    if not isinstance(listed, list):
        raise ValueError(f"{path}: {where}: symmetries_continuous must be a list")
    for entry in listed:
        if not isinstance(entry, dict):
            raise ValueError(f"{path}: {where}: a continuous symmetry is an axis and an offset")
        axis = numbers(path, f"{where}: continuous axis", entry.get("axis"), 3)
        offset = numbers(path, f"{where}: continuous offset", entry.get("offset"), 3) * MM
        if not np.linalg.norm(axis) > 0:
            raise ValueError(f"{path}: {where}: a continuous symmetry's axis is zero")
        continuous.append((axis / np.linalg.norm(axis), offset))
    return np.stack(discrete), np.reshape(listed_transforms, (-1, 4, 4)), continuous


def _symmetry(path: Path, where: str, discrete: np.ndarray, continuous) -> Symmetry:
    if len(continuous) > 1:
        raise ValueError(
            f"{path}: {where}: {len(continuous)} continuous symmetry axes; jaxreg's Symmetry "
            "holds one (a sphere-like object: list its axes' discretised turns instead)"
        )
    axis = continuous[0][0] if continuous else None
    return Symmetry(discrete[:, :3, :3], axis=axis)


def _read_model(path: Path) -> tuple[np.ndarray, trimesh.Trimesh | None]:
    """`(vertices (N, 3) metres, mesh or None)` of a PLY in millimetres: a mesh, or a point
    model (vertices without faces)."""
    import trimesh  # imported here so that `import jaxreg` stays light

    if not path.is_file():
        raise ValueError(
            f"{path}: no such file (the object's model); BOP names models obj_<id:06d>.ply"
        )
    try:
        loaded = trimesh.load(path, process=False)
    except Exception as error:  # noqa: BLE001 (trimesh's loaders raise many types)
        raise ValueError(f"{path}: not a readable PLY mesh ({error})") from None
    if not isinstance(loaded, trimesh.PointCloud | trimesh.Trimesh) or not len(loaded.vertices):
        raise ValueError(f"{path}: the PLY has no vertices")
    if isinstance(loaded, trimesh.PointCloud) or len(loaded.faces) == 0:
        return np.asarray(loaded.vertices, dtype=np.float64) * MM, None
    mesh = trimesh.Trimesh(loaded.vertices * MM, loaded.faces, process=False)
    return np.asarray(mesh.vertices, dtype=np.float64), mesh


def read_models(models_dir: Path, obj_ids) -> dict[int, BopModel]:
    """The models of `obj_ids` (all of models_info's when None) from `models_dir`."""
    info_path = models_dir / "models_info.json"
    infos = load_json(info_path, "models' sizes and symmetries")
    if not isinstance(infos, dict):
        raise ValueError(f"{info_path}: expected an object mapping object ids to their info")
    try:
        by_id = {int(key): value for key, value in infos.items()}
    except ValueError:
        raise ValueError(f"{info_path}: keys must be object ids (integers)") from None
    wanted = sorted(by_id) if obj_ids is None else sorted(obj_ids)
    models = {}
    for obj_id in wanted:
        where = f"object {obj_id}"
        if obj_id not in by_id:
            raise ValueError(
                f"{info_path}: no entry for object {obj_id} (it has {sorted(by_id)}); check "
                "--objects or the dataset's models folder"
            )
        info = by_id[obj_id]
        if not isinstance(info, dict):
            raise ValueError(f"{info_path}: {where}: expected an object with a diameter")
        diameter = info.get("diameter")
        if isinstance(diameter, bool) or not isinstance(diameter, int | float) or not diameter > 0:
            raise ValueError(
                f"{info_path}: {where}: diameter must be a positive number of millimetres, got "
                f"{diameter!r}"
            )
        discrete, listed, continuous = _transforms(info_path, where, info)
        points, mesh = _read_model(models_dir / f"obj_{obj_id:06d}.ply")
        models[obj_id] = BopModel(
            obj_id=obj_id,
            mesh=mesh,
            points=points,
            diameter=float(diameter) * MM,
            symmetry=_symmetry(info_path, where, discrete, continuous),
            symmetry_transforms=bop_symmetry_transforms(listed, continuous),
        )
    return models
