"""Object meshes of the synthetic tabletop scenes and their symmetry groups.

Every object is a `trimesh.Trimesh` in its own frame: metres, z up, origin on the object's
vertical axis halfway up its body, so an upright object resting on a table top at z = 0 has
`base_T_object` translation z = `height / 2`. The meshes need not be watertight (the mug and
the container are open at the top); only ray casting and surface sampling use them.
"""

from __future__ import annotations

import numpy as np
import trimesh

from jaxreg.geometry.metrics import Symmetry

__all__ = [
    "MODEL_SAMPLES",
    "OBJECTS",
    "distractor_mesh",
    "object_mesh",
    "surface_points",
    "surface_samples",
]

OBJECTS = ("box", "mug", "cylinder", "container")
_SECTIONS = 64  # facets around a round object: 0.1 mm sagitta at 4 cm radius


def _rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


_IDENTITY = np.eye(3)[None]
_FLIP_X = np.diag([1.0, -1.0, -1.0])  # half turn about x: swaps top and bottom
_FLIP_Y = np.diag([-1.0, 1.0, -1.0])
_FLIP_Z = np.diag([-1.0, -1.0, 1.0])


def _tube(path: np.ndarray, radius: float, sections: int = 16) -> trimesh.Trimesh:
    """An open tube of `radius` around a polyline `(M, 3)` lying in the xz plane."""
    tangents = np.gradient(path, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    binormal = np.array([0.0, 1.0, 0.0])
    normals = np.cross(binormal, tangents)
    angles = np.linspace(0.0, 2.0 * np.pi, sections, endpoint=False)
    rings = path[:, None, :] + radius * (
        np.cos(angles)[None, :, None] * normals[:, None, :]
        + np.sin(angles)[None, :, None] * binormal[None, None, :]
    )
    index = np.arange(len(path) * sections).reshape(len(path), sections)
    a, b = index[:-1], np.roll(index[:-1], -1, axis=1)
    c, d = index[1:], np.roll(index[1:], -1, axis=1)
    faces = np.concatenate(
        [np.stack([a, b, d], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)]
    )
    return trimesh.Trimesh(rings.reshape(-1, 3), faces, process=False)


def _mug(radius=0.04, height=0.095, wall=0.004, base=0.006) -> trimesh.Trimesh:
    """A cup (open top, flat bottom) with a C-shaped handle on its +x side."""
    body = trimesh.creation.annulus(radius - wall, radius, height, sections=_SECTIONS)
    bottom = trimesh.creation.cylinder(radius - wall, base, sections=_SECTIONS)
    bottom.apply_translation((0.0, 0.0, (base - height) / 2))
    # the handle's arc leaves and re-enters the wall; 3 mm stubs bury its open ends in it
    arc = np.linspace(-np.pi / 2, np.pi / 2, 24)
    reach = 0.028
    arc_points = np.stack([radius + reach * np.cos(arc), 0 * arc, reach * np.sin(arc)], -1)
    stub_low = [[radius - 0.003, 0.0, -reach]]
    stub_high = [[radius - 0.003, 0.0, reach]]
    handle = _tube(np.concatenate([stub_low, arc_points, stub_high]), 0.006)
    return trimesh.util.concatenate([body, bottom, handle])


def _container(side=0.10, height=0.07, wall=0.004) -> trimesh.Trimesh:
    """An open-top tray with a square footprint: a floor and four walls."""
    floor = trimesh.creation.box((side, side, wall))
    floor.apply_translation((0.0, 0.0, (wall - height) / 2))
    parts = [floor]
    for quarter in range(4):
        panel = trimesh.creation.box((wall, side, height))
        panel.apply_translation(((side - wall) / 2, 0.0, 0.0))
        transform = np.eye(4)
        transform[:3, :3] = _rotation_z(quarter * np.pi / 2)
        parts.append(panel.apply_transform(transform))
    return trimesh.util.concatenate(parts)


def object_mesh(name: str) -> tuple[trimesh.Trimesh, Symmetry]:
    """The mesh of one target object and its symmetry.

    `name` is one of `OBJECTS`:

    * `"box"`: 80 x 50 x 120 mm carton; half turns about x, y, z (4 poses fit equally).
    * `"mug"`: 80 mm diameter, 95 mm tall cup with a handle on +x; no symmetry.
    * `"cylinder"`: 70 mm diameter, 120 mm tall closed can; any turn about z, and a half
      turn about x.
    * `"container"`: open tray, 100 x 100 mm footprint, 70 mm tall; quarter turns about z.

    Raises `ValueError` for another name.
    """
    if name == "box":
        return trimesh.creation.box((0.08, 0.05, 0.12)), Symmetry(
            np.stack([np.eye(3), _FLIP_X, _FLIP_Y, _FLIP_Z])
        )
    if name == "mug":
        return _mug(), Symmetry(_IDENTITY)
    if name == "cylinder":
        mesh = trimesh.creation.cylinder(0.035, 0.12, sections=_SECTIONS)
        return mesh, Symmetry(np.stack([np.eye(3), _FLIP_X]), axis=np.array([0.0, 0.0, 1.0]))
    if name == "container":
        quarters = np.stack([_rotation_z(k * np.pi / 2) for k in range(4)])
        return _container(), Symmetry(quarters)
    raise ValueError(f"unknown object {name!r}: choose one of {', '.join(OBJECTS)}")


def distractor_mesh(rng: np.random.Generator) -> trimesh.Trimesh:
    """A random clutter object in the same frame convention: a box, a can or a ball."""
    kind = rng.integers(3)
    if kind == 0:
        return trimesh.creation.box(rng.uniform((0.04, 0.04, 0.03), (0.10, 0.10, 0.15)))
    if kind == 1:
        return trimesh.creation.cylinder(
            rng.uniform(0.02, 0.045), rng.uniform(0.05, 0.15), sections=_SECTIONS
        )
    return trimesh.creation.icosphere(subdivisions=3, radius=rng.uniform(0.025, 0.05))


MODEL_SAMPLES = 20_000  # points a mesh model is sampled to (the pose and bop commands, demo)


def surface_points(mesh: trimesh.Trimesh, count: int = MODEL_SAMPLES) -> np.ndarray:
    """``(count, 3)`` float32 points sampled uniformly on ``mesh``'s surface (by area), in
    the mesh's frame and units; the same points for the same mesh on every run (seed 0)."""
    return surface_samples(mesh, count)[0]


def surface_samples(
    mesh: trimesh.Trimesh, count: int = MODEL_SAMPLES
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`surface_points` and the unit normal of the face each lies on ``(count, 3)``
    (float32; outward where the mesh's faces wind consistently, as ``object_mesh``'s do): a
    model's ``model_normals``."""
    samples, faces = trimesh.sample.sample_surface(mesh, count, seed=0)
    return samples.astype(np.float32), mesh.face_normals[faces].astype(np.float32)
