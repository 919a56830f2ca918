"""Synthetic clutter with the variety of real frames: YCB-Video objects touching, stacked, a
bowl, a marker, a target cut by the image's edge or hidden in part behind another, and a
Kinect-class camera, each posed from a mask, a box and no prompt.

Usage: python benchmarks/bench_variety.py [--data PATH] [--seeds A B] [--cases NAME ...]
       [--prompts NAME ...]

Objects: the 21 point models of PoseCNN (``jaxreg.io.read_ycbv_models``,
``$JAXREG_DATA/ycbv/models`` by default) given surfaces by ``bench_shapes.surface`` (Open3D's
Poisson reconstruction, resting on its convex hull's largest face unless a case turns it; the
bowl turned over onto its base), with the holes that reconstruction leaves where the points are
sparse filled where the scan has points nearby, so that no object shows the table through it,
and the bowl's and the mug's rims cut back to the scan (``Shapes``). Colours are random, the
target's of luminance 0.25-0.8, the others' from 0.05 (dark ones lose depth). The table is a
1.2 x 0.8 m box, its top at z = 0; the target stands within 5 cm of its centre at a random
heading. An object is put in place by moving it, from clear of everything, straight down (onto
the table or what lies on it) or sideways (against a neighbour) until it touches: the distance
is the shortest ray, along the move, from a vertex of either mesh to the other (Embree), so
nothing floats and nothing sinks in beyond the meshes' facets (edges 1-4 mm long; on the tuning
seeds, under 0.5 mm either way). An object set on another keeps its centre of mass (its points'
mean) over the one below and is no wider (footprint radius) than 1.2 times it. Two more YCB
objects (distractors) stand on the table up to 40 cm from the target, 1 cm clear of everything
and off the line of sight. The camera, held level, looks at the target's centre from 0.5-1.1 m
at 35-70 degrees above the table and a random azimuth; an Intel RealSense D435 at 848x480
(``jaxreg.synth.StereoSensor.d435``: its noise, holes, flying pixels and stereo shadows)
measures the exact render.

Cases (each a function of the seed: ``scene(case, seed)``):

* ``touching``: 1-2 YCB neighbours slid against the target until 0-2 mm apart, the first of
  about its height (within 25%) where one is left to draw.
* ``stacked_on``: the target lying on another object, a flat-topped one (the boxes, the wood
  block, the foam brick, the chef can and the tuna can): a box on a larger box, a banana across
  a block.
* ``stacked_under``: a small object (a gelatin or pudding box, a tuna, meat or soup can, the
  foam brick, the banana, scissors, the marker) resting on a flat-topped target, so that the
  target's segment holds what sits on it.
* ``bowl``: 024_bowl right side up on its base (concave: the camera sees into it), with 0-1
  touching neighbours.
* ``thin_upright`` and ``thin_lying``: 040_large_marker (18 mm across) standing on its end, and
  lying on the table like a pen at a random roll, 0.6-1.0 m from the camera.
* ``edge``: the camera turned (panned about the vertical, or tilted) until 20-40% of the
  target's pixels fall outside the image.
* ``mask_border``: another YCB object on the table between the camera and the target hiding
  10-60% of the target's pixels (the target's mask then borders the occluder's pixels).
* ``camera``: a Kinect v1 / PrimeSense-class structured-light camera, 640x480,
  fx = fy = 525, (cx, cy) = (319.5, 239.5) (see ``kinect``), told to the pipeline as
  ``DepthNoise.structured_light``.

``--cases stacked`` (or ``thin``) picks both of a pair.

Targets: drawn over the 21 objects where the case allows (the flat-topped ones for
``stacked_under``, the bowl and the marker for theirs). ``model_points`` is the target's point
model (about 2,620 points) in its mesh's frame, ``truth`` the mesh's ``base_T_object``.

Prompts, each ``jaxreg.estimate_pose(frame, model_points, depth_noise=noise, ...)`` with the
D435's ``depth_noise`` (or ``DepthNoise.structured_light((525, 525))``):

* ``mask``: the target's true visible mask dilated by 2-5 pixels (drawn per scene), so that its
  border holds background, table, neighbour and occluder pixels, as a segmenter's does.
* ``box``: the true mask's bounding box ``(u0, v0, u1, v1)`` (inclusive pixels) grown by 2-5
  pixels on each side and clipped to the image, as a detector gives it.
* ``table``: no prompt: the table plane, the clusters on it, and the model's fit choose.

Scores as ``bench_shapes.py``'s and ``bench_real.py``'s: posed means a success with ADD-S below
10% of the model's diameter, wrong a success with more, refused no success (the reason grouped
by its words before the first number, ``bench_real.reason_group``); for posed answers, whether
the model's box centre lies in the estimate's 95% region (``bench_real.centre_coverage``, no
allowance: the synthetic truth is exact, but the surface is the reconstruction's). The
per-estimate rows go to ``benchmarks/results/bench_variety.csv``.

Seeds: ``--seeds A B`` runs ``range(A, B)`` of every case (default 500 505). The scenes were
built and checked on seeds 400-404 (the tuning seeds); none from 500 up served in tuning.
"""

from __future__ import annotations

import argparse
import collections
import csv
import dataclasses
import functools
import time
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import trimesh
from _timing import DATA, print_table
from bench_real import centre_coverage, centre_error, diameter, open3d_unless, reason_group
from bench_shapes import surface
from scipy import ndimage
from scipy.spatial import cKDTree
from trimesh.ray.ray_pyembree import RayMeshIntersector

import jaxreg as jr
from jaxreg.synth import StereoSensor, look_at, render

CSV = Path(__file__).resolve().parent / "results" / "bench_variety.csv"
FIELDS = [
    "case", "seed", "object", "prompt", "outcome", "reason", "reason_group", "adds_mm",
    "diameter_mm", "centre_mm", "inside", "equivalent", "ms", "visible_px", "note",
]  # fmt: skip
PROMPTS = ("mask", "box", "table")
POSED = 0.1  # ADD-S below this fraction of the diameter
TABLE_SIZE = (1.2, 0.8, 0.04)  # metres; the top face is z = 0
TABLE_COLOR = (0.55, 0.42, 0.30)
REACH = 0.40  # metres from the target: how far distractors stand
CLEAR = 0.01  # metres between footprints of objects that do not touch
LIT = (0.25, 0.8)  # the target colour's luminance (the others' from 0.05: dark ones lose depth)
FLAT_TOPS = (
    "002_master_chef_can", "003_cracker_box", "004_sugar_box", "007_tuna_fish_can",
    "008_pudding_box", "009_gelatin_box", "036_wood_block", "061_foam_brick",
)  # fmt: skip
SMALL = (
    "005_tomato_soup_can", "007_tuna_fish_can", "008_pudding_box", "009_gelatin_box",
    "010_potted_meat_can", "011_banana", "037_scissors", "040_large_marker", "061_foam_brick",
)  # fmt: skip
BOWL, MARKER = "024_bowl", "040_large_marker"
FLARED = (BOWL, "025_mug")  # their Poisson surfaces flare out past the rim, 1-2 cm
_HALF_TURN_X = np.diag([1.0, -1.0, -1.0, 1.0])
_DOWN = np.array([0.0, 0.0, -1.0])


def kinect() -> tuple[StereoSensor, jr.Intrinsics]:
    """A Kinect v1 / PrimeSense-class structured-light camera in the stereo model's terms, and
    its 640x480 intrinsics (fx = fy = 525, centred principal point, no distortion).

    The projector stands 75 mm from the infrared camera (where the model's right imager is: its
    shadows are the holes beside every foreground object); disparity is matched in 1/8 pixel
    (Konolige and Mihelich, "Technical description of Kinect calibration"; Khoshelham and
    Oude Elberink, Sensors 2012); depth from 0.4 m (the largest disparity ``fx B / 0.4``). The
    disparity noise, 0.083 px, makes ``sigma_z`` 1.5 mm at 0.8 m, Nguyen, Izadi and Lovell's
    figure (``DepthNoise.structured_light``) at the middle of the scenes' distances; their
    constant term is not in a stereo model, so the sensor is quieter than stated nearer (0.6
    against 1.2 mm at 0.5 m) and noisier farther (2.8 against 2.1 mm at 1.1 m). Lateral noise
    0.8 px, as theirs."""
    focal, baseline = 525.0, 0.075
    sensor = StereoSensor(
        "Kinect v1 class structured light", hfov_deg=float(np.degrees(2 * np.arctan(320 / focal))),
        baseline_m=baseline, subpixel_rms_px=0.083, disparity_step_px=1 / 8,
        max_disparity_px=focal * baseline / 0.4, lateral_sigma_px=0.8,
    )  # fmt: skip
    return sensor, jr.Intrinsics(focal, focal, 319.5, 239.5, 640, 480)


class Shapes:
    """The YCB-Video objects of a ``models`` folder: point models, and surfaces made on first
    use (``bench_shapes.surface``, a few seconds each)."""

    def __init__(self, folder: Path):
        self.o3d = open3d_unless(False)
        if self.o3d is None:
            raise SystemExit("the scenes' surfaces need Open3D (Poisson reconstruction)")
        self.points = jr.io.read_ycbv_models(folder)
        self.names = tuple(self.points)
        self._made: dict[str, tuple[trimesh.Trimesh, np.ndarray]] = {}

    def get(self, name: str) -> tuple[trimesh.Trimesh, np.ndarray]:
        """``(mesh, model)``: the surface in its resting frame (z up, on its hull's largest
        face; the bowl turned over onto its base) and the ``(M, 3)`` float32 model points in
        that frame (metres). The reconstruction's flare past the open edge of the ``FLARED``
        objects (faces with a vertex over 5 mm from every model point) is cut off, and the
        holes it leaves where the points are sparse are filled (``_filled``; the bowl's only
        up to 1 cm across, not its mouth)."""
        if name not in self._made:
            mesh, turn = surface(self.o3d, self.points[name])
            if name == BOWL:
                mesh.apply_transform(_HALF_TURN_X)
                turn = _HALF_TURN_X[:3, :3] @ turn
            model = (self.points[name] @ turn.T).astype(np.float32)
            if name in FLARED:
                near = cKDTree(model).query(mesh.vertices)[0] <= 0.005
                mesh.update_faces(near[mesh.faces].all(axis=1))
                mesh.remove_unreferenced_vertices()
            mesh = self._filled(mesh, model, 0.01 if name == BOWL else 1.0)
            mesh.update_faces(mesh.nondegenerate_faces())
            self._made[name] = (mesh, model)
        return self._made[name]

    def _filled(self, mesh: trimesh.Trimesh, model: np.ndarray, radius: float) -> trimesh.Trimesh:
        """``mesh`` with its holes up to ``radius`` (metres, of the loop's bounding sphere)
        closed by faces between their own vertices (Open3D), less the new faces that lie over
        1 cm from every point of ``model`` ``(M, 3)`` (the mesh's frame, metres): a hole where
        the scan has points was a sparse stretch of surface, one where it has none is an
        opening (a clamp's jaws, a mug's mouth)."""
        legacy = self.o3d.geometry.TriangleMesh(
            self.o3d.utility.Vector3dVector(mesh.vertices),
            self.o3d.utility.Vector3iVector(mesh.faces),
        )
        closed = self.o3d.t.geometry.TriangleMesh.from_legacy(legacy).fill_holes(radius)
        added = closed.triangle.indices.numpy()[len(mesh.faces) :]  # appended after the mesh's
        corners = mesh.vertices[added]
        middle = corners.mean(1, keepdims=True)
        samples = np.concatenate([middle, (corners + middle) / 2], 1)  # (F, 4, 3)
        distance = cKDTree(model).query(samples.reshape(-1, 3))[0].reshape(-1, 4)
        kept = added[np.median(distance, axis=1) <= 0.01]
        return trimesh.Trimesh(mesh.vertices, np.concatenate([mesh.faces, kept]))

    def height(self, name: str) -> float:
        """The resting surface's height (metres)."""
        return float(np.ptp(self.get(name)[0].vertices[:, 2]))


@functools.cache
def shapes(folder: Path) -> Shapes:
    """One ``Shapes`` per folder for the process."""
    return Shapes(folder)


@dataclasses.dataclass(frozen=True)
class Placed:
    """One object in the scene: ``pose`` ``(4, 4)`` maps its mesh's frame into the base frame,
    ``mesh`` is there already (base frame, metres), ``color`` its linear RGB ``(3,)``."""

    name: str
    pose: np.ndarray
    mesh: trimesh.Trimesh
    color: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """``(2,)`` the middle of its footprint's bounding box (metres)."""
        return self.mesh.bounds[:, :2].mean(0)

    @property
    def radius(self) -> float:
        """The radius of the vertical cylinder about ``centre`` that holds it (metres)."""
        return float(np.linalg.norm(self.mesh.vertices[:, :2] - self.centre, axis=1).max())


@dataclasses.dataclass(frozen=True)
class VarietyScene:
    """One scene of a case and what ``estimate_pose`` is given for it.

    Attributes:
        case, seed: what made it (``scene(case, seed)`` makes it again).
        name: the target's YCB-Video name.
        frame: the ``RGBDFrame`` (noisy depth, shaded RGB, the camera's intrinsics and
            ``base_T_camera``).
        model_points: ``(M, 3)`` float32 target points in its mesh's frame (metres).
        truth: ``SE3`` ``base_T_object`` of that frame.
        visible: ``(H, W)`` bool, the pixels where the target is the first surface hit.
        mask: ``(H, W)`` bool, ``visible`` dilated by 2-5 pixels (the ``mask`` prompt).
        box: ``(u0, v0, u1, v1)`` inclusive pixels, ``visible``'s bounding box grown by 2-5
            pixels and clipped to the image (the ``box`` prompt).
        noise: the ``DepthNoise`` the pipeline is told.
        diameter: the model's largest point-to-point distance (metres).
        objects: every object's ``Placed``, the target first.
        note: what the case arranged (the support, the load, the share cut or hidden).
    """

    case: str
    seed: int
    name: str
    frame: jr.RGBDFrame
    model_points: np.ndarray
    truth: jr.SE3
    visible: np.ndarray
    mask: np.ndarray
    box: tuple[int, int, int, int]
    noise: jr.DepthNoise
    diameter: float
    objects: tuple[Placed, ...]
    note: str


# ---------------------------------------------------------------------------------------------
# placing objects


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _place(
    name: str, mesh: trimesh.Trimesh, rotation: np.ndarray, xy, z: float, rng, bright=(0.05, 0.8)
) -> Placed:
    """``mesh`` turned by ``rotation`` ``(3, 3)``, its footprint's box centred on ``xy`` and its
    lowest point at height ``z``; a random colour of luminance in ``bright``."""
    pose = np.eye(4)
    pose[:3, :3] = rotation
    turned = mesh.vertices @ rotation.T
    low, high = turned.min(0), turned.max(0)
    pose[:3, 3] = (xy[0] - (low[0] + high[0]) / 2, xy[1] - (low[1] + high[1]) / 2, z - low[2])
    color = rng.uniform(0.1, 1.0, 3)
    color *= rng.uniform(*bright) / (color @ (0.2126, 0.7152, 0.0722))
    return Placed(name, pose, mesh.copy().apply_transform(pose), color)


def _moved(item: Placed, shift) -> Placed:
    pose = item.pose.copy()
    pose[:3, 3] += shift
    return dataclasses.replace(item, pose=pose, mesh=item.mesh.copy().apply_translation(shift))


def _first_hit(mesh: trimesh.Trimesh, origins: np.ndarray, direction: np.ndarray) -> float:
    """The shortest distance from ``origins`` ``(N, 3)`` along ``direction`` ``(3,)`` to
    ``mesh`` (metres; inf when no ray meets it)."""
    directions = np.broadcast_to(direction, origins.shape)
    hits, rays, _ = RayMeshIntersector(mesh).intersects_location(
        origins, directions, multiple_hits=False
    )
    return float(((hits - origins[rays]) @ direction).min()) if len(rays) else np.inf


def _clearance(moving: Placed, fixed: Sequence[Placed], direction) -> float:
    """How far ``moving`` can travel along the unit ``direction`` ``(3,)`` before it touches
    one of ``fixed`` (metres; inf when never): the shortest ray along the move from a vertex of
    ``moving`` to ``fixed``, or back from a vertex of ``fixed``."""
    other = trimesh.util.concatenate([f.mesh for f in fixed])
    direction = np.asarray(direction, float)
    return min(
        _first_hit(other, moving.mesh.vertices, direction),
        _first_hit(moving.mesh, other.vertices, -direction),
    )


def _table() -> Placed:
    box = trimesh.creation.box(TABLE_SIZE).apply_translation((0.0, 0.0, -TABLE_SIZE[2] / 2))
    return Placed("table", np.eye(4), box, np.array(TABLE_COLOR))


def _dropped(item: Placed, below: Sequence[Placed]) -> Placed:
    """``item`` lowered onto ``below`` from 1 cm above their highest point."""
    top = max(b.mesh.bounds[1, 2] for b in below)
    lifted = _moved(item, (0.0, 0.0, top + 0.01 - item.mesh.bounds[0, 2]))
    return _moved(lifted, _clearance(lifted, below, _DOWN) * _DOWN)


def _over(item: Placed, support: Placed, model: np.ndarray, below: Sequence[Placed]) -> bool:
    """Whether ``item`` rests on ``support``: its points' mean ``model`` ``(M, 3)`` (its mesh's
    frame) lies over ``support`` first among ``below``, and it is no wider than 1.2 times
    ``support``."""
    centre = item.pose[:3, :3] @ model.mean(0) + item.pose[:3, 3]
    to_support = _first_hit(support.mesh, centre[None], _DOWN)
    to_any = min(_first_hit(b.mesh, centre[None], _DOWN) for b in below)
    return np.isfinite(to_support) and to_support <= to_any and item.radius <= 1.2 * support.radius


def _on_table(shapes: Shapes, name: str, rng, rotation=None, bright=(0.05, 0.8)) -> Placed:
    """``name`` at a random heading standing within 5 cm of the table's centre; ``rotation``
    ``(3, 3)`` turns its mesh first (default: resting on its hull's largest face); its colour's
    luminance in ``bright``."""
    turn = np.eye(3) if rotation is None else rotation
    mesh = shapes.get(name)[0]
    return _place(name, mesh, _yaw(rng.uniform(0, 2 * np.pi)) @ turn, rng.uniform(-0.05, 0.05, 2),
                  0.0, rng, bright)  # fmt: skip


def _toucher(shapes: Shapes, placed: list[Placed], rng, similar: bool) -> Placed:
    """A YCB object not yet in ``placed`` slid along the table against ``placed[0]`` until
    0-2 mm apart, meeting nothing else on the way; of ``placed[0]``'s height (within 25%) when
    ``similar`` and one is left."""
    target, used = placed[0], {p.name for p in placed}
    pool = [n for n in shapes.names if n not in used]
    height = shapes.height(target.name)
    alike = [n for n in pool if abs(shapes.height(n) - height) <= 0.25 * height]
    for _ in range(100):
        name = str(rng.choice(alike if similar and alike else pool))
        azimuth = rng.uniform(0, 2 * np.pi)
        way = np.array([np.cos(azimuth), np.sin(azimuth), 0.0])
        item = _place(name, shapes.get(name)[0], _yaw(rng.uniform(0, 2 * np.pi)), (0.0, 0.0),
                      0.0, rng)  # fmt: skip
        start = target.centre + way[:2] * (target.radius + item.radius + 0.05)
        item = _moved(item, (*(start - item.centre), 0.0))
        if any(np.linalg.norm(item.centre - p.centre) < item.radius + p.radius for p in placed[1:]):
            continue
        to_target = _clearance(item, [target], -way)
        if np.isfinite(to_target) and _clearance(item, placed, -way) >= to_target - 1e-4:
            return _moved(item, -way * (to_target - rng.uniform(0.0, 0.002)))
    raise RuntimeError(f"no neighbour fits beside {target.name}")


# ---------------------------------------------------------------------------------------------
# cases: each returns the objects (the target first) and a note


def _touching(shapes: Shapes, rng) -> tuple[list[Placed], str]:
    placed = [_on_table(shapes, str(rng.choice(shapes.names)), rng, bright=LIT)]
    for k in range(rng.integers(1, 3)):
        placed.append(_toucher(shapes, placed, rng, similar=k == 0))
    return placed, "touching " + " ".join(p.name for p in placed[1:])


def _stacked_on(shapes: Shapes, rng) -> tuple[list[Placed], str]:
    table = _table()
    for _ in range(100):
        name = str(rng.choice(shapes.names))
        support = _on_table(shapes, str(rng.choice([s for s in FLAT_TOPS if s != name])), rng)
        mesh, model = shapes.get(name)
        xy = support.centre + rng.uniform(-0.02, 0.02, 2)
        turn = _yaw(rng.uniform(0, 2 * np.pi))
        target = _dropped(_place(name, mesh, turn, xy, 0.0, rng, LIT), [table, support])
        if _over(target, support, model, [table, support]):
            return [target, support], f"on {support.name}"
    raise RuntimeError("no stack found")


def _stacked_under(shapes: Shapes, rng) -> tuple[list[Placed], str]:
    table = _table()
    for _ in range(100):
        target = _on_table(shapes, str(rng.choice(FLAT_TOPS)), rng, bright=LIT)
        name = str(rng.choice([s for s in SMALL if s != target.name]))
        mesh, model = shapes.get(name)
        xy = target.centre + rng.uniform(-0.015, 0.015, 2)
        load = _dropped(_place(name, mesh, _yaw(rng.uniform(0, 2 * np.pi)), xy, 0.0, rng),
                        [table, target])  # fmt: skip
        if _over(load, target, model, [table, target]):
            return [target, load], f"under {name}"
    raise RuntimeError("no stack found")


def _bowl(shapes: Shapes, rng) -> tuple[list[Placed], str]:
    placed = [_on_table(shapes, BOWL, rng, bright=LIT)]
    for _ in range(rng.integers(0, 2)):
        placed.append(_toucher(shapes, placed, rng, similar=False))
    return placed, " ".join(["touching", *(p.name for p in placed[1:])]) if placed[1:] else ""


def _marker_axis(shapes: Shapes) -> np.ndarray:
    """``(3, 3)`` a rotation taking the marker's long axis (its points' principal axis) to z."""
    model = shapes.get(MARKER)[1]
    axis = np.linalg.eigh(np.cov(model.T))[1][:, -1]
    return trimesh.geometry.align_vectors(axis, (0.0, 0.0, 1.0))[:3, :3]


def _thin_upright(shapes: Shapes, rng) -> tuple[list[Placed], str]:
    flip = _HALF_TURN_X[:3, :3] if rng.random() < 0.5 else np.eye(3)
    return [
        _on_table(shapes, MARKER, rng, rotation=flip @ _marker_axis(shapes), bright=LIT)
    ], "on its end"


def _thin_lying(shapes: Shapes, rng) -> tuple[list[Placed], str]:
    roll = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]) @ _yaw(
        rng.uniform(0, 2 * np.pi)
    )  # the long axis (z) to x, after a random turn about it
    return [
        _on_table(shapes, MARKER, rng, rotation=roll @ _marker_axis(shapes), bright=LIT)
    ], "lying"


def _alone(shapes: Shapes, rng) -> tuple[list[Placed], str]:
    return [_on_table(shapes, str(rng.choice(shapes.names)), rng, bright=LIT)], ""


@dataclasses.dataclass(frozen=True)
class Case:
    """How a case builds its scenes: ``build(shapes, rng)`` gives the objects (the target
    first) and a note; ``distance`` the camera's range (metres); ``occluder``, ``cut`` and
    ``kinect`` the case's own step (see the module docstring)."""

    build: Callable[[Shapes, np.random.Generator], tuple[list[Placed], str]]
    distance: tuple[float, float] = (0.5, 1.1)
    occluder: bool = False
    cut: bool = False
    kinect: bool = False


CASES = {
    "touching": Case(_touching),
    "stacked_on": Case(_stacked_on),
    "stacked_under": Case(_stacked_under),
    "bowl": Case(_bowl),
    "thin_upright": Case(_thin_upright, distance=(0.6, 1.0)),
    "thin_lying": Case(_thin_lying, distance=(0.6, 1.0)),
    "edge": Case(_alone, cut=True),
    "mask_border": Case(_alone, occluder=True),
    "camera": Case(_alone, kinect=True),
}


# ---------------------------------------------------------------------------------------------
# the view


def _quarter(intrinsics: jr.Intrinsics, margin: int = 0) -> jr.Intrinsics:
    """``intrinsics`` at a quarter of the resolution, widened by ``margin`` (full-resolution)
    pixels on every side: the same camera, for cheap trial renders."""
    fx, fy = float(intrinsics.fx) / 4, float(intrinsics.fy) / 4
    cx = (float(intrinsics.cx) + margin + 0.5) / 4 - 0.5
    cy = (float(intrinsics.cy) + margin + 0.5) / 4 - 0.5
    width, height = (intrinsics.width + 2 * margin) // 4, (intrinsics.height + 2 * margin) // 4
    return jr.Intrinsics(fx, fy, cx, cy, width, height)


def _distractors(shapes: Shapes, placed: list[Placed], toward: np.ndarray, count: int, rng):
    """``count`` YCB objects not yet in ``placed`` on the table, ``CLEAR`` apart from
    everything, within ``REACH`` of the target and off its line of sight (``toward`` ``(2,)``
    the unit horizontal direction to the camera)."""
    target = placed[0]
    across = np.array([-toward[1], toward[0]])
    out = []
    for _ in range(count):
        pool = [n for n in shapes.names if n not in {p.name for p in placed + out}]
        for _ in range(200):
            item = _on_table(shapes, str(rng.choice(pool)), rng)
            reach = rng.uniform(target.radius + item.radius + CLEAR, REACH)
            azimuth = rng.uniform(0, 2 * np.pi)
            spot = target.centre + reach * np.array([np.cos(azimuth), np.sin(azimuth)])
            item = _moved(item, (*(spot - item.centre), 0.0))
            offset = spot - target.centre
            blocks = offset @ toward > -item.radius and abs(offset @ across) < (
                target.radius + item.radius + CLEAR
            )
            on_table = np.all(np.abs(spot) + item.radius < np.array(TABLE_SIZE[:2]) / 2)
            apart = all(
                np.linalg.norm(spot - p.centre) > item.radius + p.radius + CLEAR
                for p in placed + out
            )
            if on_table and apart and not blocks:
                out.append(item)
                break
        else:
            raise RuntimeError("no room on the table for the distractors")
    return out


def _occluder(shapes: Shapes, placed: list[Placed], intrinsics, pose, toward, rng):
    """A YCB object on the table in front of the target (toward the camera, ``toward``
    ``(2,)``) hiding 10-60% of its pixels, and the share it hides (the try nearest 30% when
    none of 100 does): the rays of a quarter-resolution render's target pixels that meet the
    object before the target."""
    target = placed[0]
    seen = render([_table().mesh, *(p.mesh for p in placed)], _quarter(intrinsics), pose)
    points = seen.camera_points()[seen.labels == 1] @ pose[:3, :3].T + pose[:3, 3]
    eye = pose[:3, 3]
    reach = np.linalg.norm(points - eye, axis=1)
    rays = (points - eye) / reach[:, None]
    across = np.array([-toward[1], toward[0]])
    pool = [n for n in shapes.names if n not in {p.name for p in placed}]
    best, best_hidden = None, -1.0
    for _ in range(100):
        item = _on_table(shapes, str(rng.choice(pool)), rng)
        apart = target.radius + item.radius + CLEAR
        spot = target.centre + toward * rng.uniform(apart, apart + 0.12)
        spot += across * rng.uniform(-0.8, 0.8) * apart
        item = _moved(item, (*(spot - item.centre), 0.0))
        if any(np.linalg.norm(spot - p.centre) < item.radius + p.radius + CLEAR for p in placed):
            continue
        hits, index, _ = RayMeshIntersector(item.mesh).intersects_location(
            np.broadcast_to(eye, rays.shape), rays, multiple_hits=False
        )
        nearer = np.linalg.norm(hits - eye, axis=1) < reach[index]
        hidden = nearer.sum() / len(rays)
        if 0.1 <= hidden <= 0.6:
            return item, hidden
        if abs(hidden - 0.3) < abs(best_hidden - 0.3):
            best, best_hidden = item, hidden
    return best, best_hidden


def _cut(objects: Sequence[Placed], intrinsics, pose: np.ndarray, rng):
    """``pose`` turned about the camera's centre, panned about the vertical or tilted about
    the image's x axis (the camera stays level), until 20-40% of the target's pixels lie
    outside the image; the share is judged by mapping the pixels of a widened quarter-resolution
    render through the turn. Returns the turned pose and that share."""
    margin = 400
    wide = _quarter(intrinsics, margin)
    labels = render([_table().mesh, *(o.mesh for o in objects)], wide, pose).labels
    rows, cols = np.nonzero(labels == 1)
    rays = np.stack([(cols - float(wide.cx)) / float(wide.fx),
                     (rows - float(wide.cy)) / float(wide.fy), np.ones(len(cols))], -1)  # fmt: skip
    base = rays @ pose[:3, :3].T
    pan = rng.random() < 0.5
    sign = rng.choice([-1.0, 1.0])
    fx, fy, cx, cy = (
        float(v) for v in (intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    )

    def turned(angle: float) -> np.ndarray:
        out = pose.copy()
        c, s = np.cos(sign * angle), np.sin(sign * angle)
        if pan:
            out[:3, :3] = _yaw(sign * angle) @ pose[:3, :3]
        else:
            out[:3, :3] = pose[:3, :3] @ np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
        return out

    def outside(angle: float) -> float:
        seen = base @ turned(angle)[:3, :3]
        ahead = seen[:, 2] > 0
        u = fx * seen[:, 0] / np.where(ahead, seen[:, 2], 1.0) + cx
        v = fy * seen[:, 1] / np.where(ahead, seen[:, 2], 1.0) + cy
        inside = ahead & (u > -0.5) & (u < intrinsics.width - 0.5)
        inside &= (v > -0.5) & (v < intrinsics.height - 0.5)
        return 1 - inside.mean()

    goal = rng.uniform(0.2, 0.4)
    low, high = 0.0, np.radians(60.0)
    for _ in range(30):
        middle = (low + high) / 2
        low, high = (middle, high) if outside(middle) < goal else (low, middle)
    return turned(high), outside(high)


# ---------------------------------------------------------------------------------------------
# a scene


def scene(case: str, seed: int, folder: Path = DATA / "ycbv" / "models") -> VarietyScene:
    """The scene ``seed`` of ``case`` (one of ``CASES``), made from the YCB-Video models in
    ``folder``; the same arguments give the same scene, noise included."""
    if case not in CASES:
        raise ValueError(f"unknown case {case!r}: choose from {', '.join(CASES)}")
    spec, library = CASES[case], shapes(Path(folder))
    stream = zlib.crc32(case.encode())
    rng = np.random.default_rng([seed, stream, 0])
    placed, note = spec.build(library, rng)
    target = placed[0]
    if spec.kinect:
        sensor, intrinsics = kinect()
        noise = jr.DepthNoise.structured_light((float(intrinsics.fx), float(intrinsics.fy)))
    else:
        sensor = StereoSensor.d435()
        intrinsics = sensor.intrinsics(848, 480)
        noise = sensor.depth_noise(intrinsics)

    look = target.mesh.bounds.mean(0)
    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = np.radians(rng.uniform(35.0, 70.0))
    toward = np.array([np.cos(azimuth), np.sin(azimuth)])
    eye = look + rng.uniform(*spec.distance) * np.array(
        [*(np.cos(elevation) * toward), np.sin(elevation)]
    )
    pose = look_at(eye, look)
    if spec.occluder:
        occluder, hidden = _occluder(library, placed, intrinsics, pose, toward, rng)
        placed.append(occluder)
        note = f"behind {occluder.name}, {hidden:.0%} hidden"
    placed += _distractors(library, placed, toward, 2, rng)
    if spec.cut:
        pose, share = _cut(placed, intrinsics, pose, rng)
        note = f"{share:.0%} outside"

    meshes = [_table(), *placed]
    rendering = render(
        [m.mesh for m in meshes], intrinsics, pose, np.stack([m.color for m in meshes])
    )
    depth = sensor.measure(rendering, np.random.default_rng([seed, stream, 1]))
    frame = jr.RGBDFrame(
        depth.astype(np.float32), intrinsics, rgb=rendering.shade(),
        base_T_camera=pose.astype(np.float32),
    )  # fmt: skip
    visible = rendering.labels == 1
    mask = ndimage.binary_dilation(visible, iterations=int(rng.integers(2, 6)))
    rows, cols = np.nonzero(visible)
    grow = int(rng.integers(2, 6))
    box = (
        max(int(cols.min()) - grow, 0), max(int(rows.min()) - grow, 0),
        min(int(cols.max()) + grow, intrinsics.width - 1),
        min(int(rows.max()) + grow, intrinsics.height - 1),
    )  # fmt: skip
    model = library.get(target.name)[1]
    return VarietyScene(
        case, seed, target.name, frame, model, jr.SE3.from_matrix(target.pose.astype(np.float32)),
        visible, mask, box, noise, diameter(model), tuple(placed), note,
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------
# the bench


def run(s: VarietyScene, prompt: str) -> dict:
    """One estimate of ``s``'s target with ``prompt`` (one of ``PROMPTS``), scored."""
    given = {"mask": {"mask": s.mask}, "box": {"box": s.box}, "table": {}}[prompt]
    row = {
        "case": s.case, "seed": s.seed, "object": s.name, "prompt": prompt, "note": s.note,
        "diameter_mm": f"{s.diameter * 1e3:.1f}", "visible_px": int(s.visible.sum()),
    }  # fmt: skip
    start = time.perf_counter()
    try:
        est = jr.estimate_pose(s.frame, s.model_points, depth_noise=s.noise, **given)
    except ValueError as error:  # a refusal by exception still answers the user
        reason = f"ValueError: {error}"
        ms = (time.perf_counter() - start) * 1e3
        return row | {"outcome": "refused", "reason": reason, "reason_group": reason_group(reason),
                      "ms": ms}  # fmt: skip
    row["ms"] = (time.perf_counter() - start) * 1e3
    if not est.success:
        return row | {"outcome": "refused", "reason": est.reason,
                      "reason_group": reason_group(est.reason)}  # fmt: skip
    adds = float(jr.add_s(s.model_points, est.pose, s.truth))
    found, truth = (np.asarray(p.as_matrix(), np.float64) for p in (est.pose, s.truth))
    centre = 0.5 * (s.model_points.min(0) + s.model_points.max(0)).astype(np.float64)
    error = centre_error(found, truth, centre)
    _, inside, _ = centre_coverage(error, found[:3, :3], np.asarray(est.covariance), centre)
    return row | {
        "outcome": "posed" if adds < POSED * s.diameter else "wrong",
        "adds_mm": adds * 1e3,
        "centre_mm": float(np.linalg.norm(error)) * 1e3,
        "inside": inside,
        "equivalent": len(est.equivalent_poses),
    }


def _summary(case: str, prompt: str, rows: list[dict]) -> list[object]:
    posed = [r for r in rows if r["outcome"] == "posed"]
    inside = sum(r["inside"] for r in posed)
    return [
        case, prompt, len(rows), len(posed), sum(r["outcome"] == "wrong" for r in rows),
        sum(r["outcome"] == "refused" for r in rows),
        f"{inside}/{len(posed)}" if posed else "-", f"{np.median([r['ms'] for r in rows]):.0f}",
    ]  # fmt: skip


def _chosen(asked: list[str] | None, known: Sequence[str], what: str) -> list[str]:
    """``known`` names that ``asked`` names, each exactly or as the part before ``_``."""
    if asked is None:
        return list(known)
    unknown = [a for a in asked if not any(k == a or k.startswith(a + "_") for k in known)]
    if unknown:
        raise SystemExit(f"unknown {what} {', '.join(unknown)}: choose from {', '.join(known)}")
    return [k for k in known if any(k == a or k.startswith(a + "_") for a in asked)]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA / "ycbv" / "models")
    parser.add_argument("--seeds", type=int, nargs=2, default=(500, 505), metavar=("A", "B"))
    parser.add_argument("--cases", nargs="+", help=f"of {', '.join(CASES)} (default all)")
    parser.add_argument("--prompts", nargs="+", help=f"of {', '.join(PROMPTS)} (default all)")
    parser.add_argument("--csv", type=Path, default=CSV, help=f"per-estimate rows (default {CSV})")
    args = parser.parse_args()
    if not args.data.exists():
        raise SystemExit(f"no YCB-Video models at {args.data}: pass --data or set JAXREG_DATA")
    cases = _chosen(args.cases, list(CASES), "case")
    prompts = _chosen(args.prompts, PROMPTS, "prompt")
    sensor, intrinsics = kinect()
    depths = np.array([0.5, 0.8, 1.1])
    stated = np.asarray(jr.DepthNoise.structured_light((525.0, 525.0)).axial_sigma(depths))
    print("Kinect-class camera's sigma_z at 0.5/0.8/1.1 m: "
          + "/".join(f"{v * 1e3:.1f}" for v in sensor.axial_sigma(depths, 525.0))
          + " mm (stated: " + "/".join(f"{v * 1e3:.1f}" for v in stated) + " mm)")  # fmt: skip
    rows = []
    for case in cases:
        for seed in range(*args.seeds):
            s = scene(case, seed, args.data)
            mine = [run(s, prompt) for prompt in prompts]
            rows += mine
            outcomes = ", ".join(
                f"{r['prompt']} {r['outcome']}"
                + (f" {r['adds_mm']:.1f} mm" if "adds_mm" in r else f" ({r['reason_group']})")
                for r in mine
            )
            print(f"{case} {seed} {s.name} [{s.note}]: {outcomes}", flush=True)
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with args.csv.open("w", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        for r in rows:
            writer.writerow({k: f"{v:.2f}" if isinstance(v, float) else v for k, v in r.items()})
    table = [
        _summary(case, prompt, [r for r in rows if r["case"] == case and r["prompt"] == prompt])
        for case in cases
        for prompt in prompts
    ]
    table += [_summary("all", p, [r for r in rows if r["prompt"] == p]) for p in prompts]
    print_table(
        f"Synthetic clutter, seeds {args.seeds[0]}-{args.seeds[1] - 1} "
        "(posed: ADD-S < 10% of the diameter)",
        ["case", "prompt", "scenes", "posed", "wrong", "refused", "centre inside 95%", "median ms"],
        table,
    )
    refusals = collections.Counter(
        (r["case"], r["prompt"], r["reason_group"]) for r in rows if r["outcome"] == "refused"
    )
    print_table(
        "Refusals by case, prompt and reason",
        ["case", "prompt", "reason", "count"],
        [[*key, count] for key, count in sorted(refusals.items())],
    )


if __name__ == "__main__":
    main()
