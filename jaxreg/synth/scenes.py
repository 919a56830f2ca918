"""Synthetic RGB-D tabletop scenes whose truth is known exactly, with a real sensor's noise.

`tabletop_scene(seed)` builds a table, a target object (`box`, `mug`, `cylinder` or
`container`, see `object_mesh`) and distractors, places a camera 0.5-0.7 m from the target
looking down at the table, ray casts every pixel of an 848x480 depth image (Embree), shades an
RGB image, and passes the exact depth through a stereo sensor model (`StereoSensor`, an Intel
RealSense D435 by default; its docstring describes the model and names the source of every
coefficient). The same seed gives the same scene, noise included; the geometry and the noise
draw from separate streams, so `noise=False` renders the same scene exactly.

Frames: the base frame is the robot's, z up, with the table top at z = 0 and the table centred
on the origin; `base_T_camera` maps camera coordinates (OpenCV: z forward, x right, y down)
into it, and `truth = base_T_object` maps the object's mesh frame into it. Depth is z-depth in
metres (NaN holes); all host-side arrays are numpy, the frame's are JAX.

Ray casting uses Embree (through embreex): it picks the triangle each ray hits first, and the
depth is solved in float64 on that triangle's plane, so noise-free pixels lie on the meshes to
float64 precision. A noisy frame casts a second set of rays, from the right imager, to find
the pixels it cannot see. `benchmarks/bench_render.py` times both.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh
from jaxlie import SE3

from jaxreg.camera.model import Intrinsics, RGBDFrame
from jaxreg.core._program_cache import persistent_jit
from jaxreg.geometry.lie import se3_from_matrix
from jaxreg.geometry.metrics import Symmetry
from jaxreg.synth._depth_noise import StereoSensor
from jaxreg.synth._meshes import OBJECTS, distractor_mesh, object_mesh
from jaxreg.synth.render import LUMA, Rendering, display_color, render

__all__ = [
    "OBJECTS",
    "Rendering",
    "StereoSensor",
    "TabletopScene",
    "look_at",
    "object_mesh",
    "render",
    "tabletop_scene",
]

_TABLE_SIZE = (1.2, 0.8, 0.04)  # metres; the top face is z = 0 in the base frame
_TABLE_COLOR = (0.55, 0.42, 0.30)  # light wood
_PLACEMENT_REACH = 0.34  # metres from the target: the table is 0.8 m deep, the target within 5 cm


@persistent_jit
def _poses(base_T_camera: np.ndarray, base_T_object: np.ndarray) -> tuple[SE3, SE3]:
    """`se3_from_matrix` of two `(4, 4)` float32 poses, as one stored program."""
    return se3_from_matrix(base_T_camera), se3_from_matrix(base_T_object)


def look_at(eye, target) -> np.ndarray:
    """`(4, 4)` `base_T_camera` of a camera at `eye` `(3,)` looking at `target` `(3,)` (base
    frame, metres): optical axis (z) toward the target, image x horizontal (the roll of a camera
    held level), y pointing down the image. The view must not be vertical."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, (0.0, 0.0, 1.0))
    if np.linalg.norm(right) < 1e-6:
        raise ValueError("look_at: the view is vertical; tilt the camera")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = eye
    return pose


@dataclasses.dataclass(frozen=True, eq=False)
class TabletopScene:
    """A rendered tabletop scene with its truth.

    Attributes:
        frame: the `RGBDFrame` (depth with the sensor's noise unless `noise=False`, shaded
            RGB, the scene's intrinsics and `base_T_camera`).
        model: the target's `trimesh.Trimesh` in its own frame (see `object_mesh`).
        model_points: `(N, 3)` float32 points sampled uniformly on `model`'s surface.
        truth: `SE3` `base_T_object` (float32, like the frame).
        mask: `(H, W)` bool, the pixels where the target is the first surface hit (the exact
            segmentation; noisy depth may still have holes inside it).
        symmetry: the target's `Symmetry`.
        exact_depth: `(H, W)` float64 noise-free z-depth (metres, NaN where nothing is hit).
        labels: `(H, W)` int32 per pixel: 0 table, 1 target, 2... distractors, -1 nothing.
        model_colors: `(N, 3)` float32 sRGB in [0, 1], the target's paint at each of
            `model_points` (as a textured model's vertex colours give it:
            `estimate_pose(..., model_colors=)`).
    """

    frame: RGBDFrame
    model: trimesh.Trimesh
    model_points: np.ndarray
    truth: SE3
    mask: np.ndarray
    symmetry: Symmetry
    exact_depth: np.ndarray
    labels: np.ndarray
    model_colors: np.ndarray


def _as_matrix(pose: SE3 | np.ndarray, name: str) -> np.ndarray:
    matrix = np.asarray(pose.as_matrix() if isinstance(pose, SE3) else pose, dtype=np.float64)
    if matrix.shape != (4, 4):
        raise ValueError(f"{name} must be an SE3 or (4, 4), got shape {matrix.shape}")
    return matrix


def _placed(mesh: trimesh.Trimesh, pose: np.ndarray) -> trimesh.Trimesh:
    return mesh.copy().apply_transform(pose)


def _resting_pose(xy, yaw: float, half_height: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    pose = np.eye(4)
    pose[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = (xy[0], xy[1], half_height)
    return pose


def _random_color(rng: np.random.Generator, lo: float, hi: float) -> np.ndarray:
    """A saturated-ish random colour whose luminance (albedo) lies in [lo, hi]."""
    color = rng.uniform(0.1, 1.0, 3)
    return color * rng.uniform(lo, hi) / (color @ LUMA)


def _footprint_radius(mesh: trimesh.Trimesh) -> float:
    """Radius (metres) of the smallest vertical cylinder about the mesh's z axis holding it."""
    return float(np.linalg.norm(mesh.vertices[:, :2], axis=1).max())


def _distractors(rng, count: int, toward_camera: np.ndarray, target_radius: float):
    """`count` clutter meshes and their table positions relative to the target's, each at
    least 1 cm clear of the target and of each other, on the table, and never between the
    camera and the target: a distractor reaching nearer the camera than the target's centre
    keeps its footprint out of the band of half-width `target_radius` about the horizontal
    line of sight `toward_camera` `(2,)` (unit), so no ray to the target can meet it."""
    placed: list[tuple[trimesh.Trimesh, np.ndarray, float]] = []
    for _ in range(count):
        for _attempt in range(200):
            mesh = distractor_mesh(rng)
            radius = _footprint_radius(mesh)
            azimuth = rng.uniform(0, 2 * np.pi)
            reach = rng.uniform(target_radius + radius + 0.01, _PLACEMENT_REACH - radius)
            spot = reach * np.array([np.cos(azimuth), np.sin(azimuth)])
            along = spot @ toward_camera
            across = abs(spot @ (-toward_camera[1], toward_camera[0]))
            blocks_view = along > -radius and across < target_radius + radius + 0.01
            apart = all(np.linalg.norm(spot - xy) > radius + r + 0.01 for _, xy, r in placed)
            if apart and not blocks_view:
                placed.append((mesh, spot, radius))
                break
        else:
            raise ValueError(f"no room on the table for {count} distractors: ask for fewer")
    return [(mesh, spot) for mesh, spot, _ in placed]


def tabletop_scene(
    seed: int = 0,
    *,
    object: str = "box",
    noise: bool = True,
    distractors: int = 2,
    sensor: StereoSensor | None = None,
    intrinsics: Intrinsics | None = None,
    distance: tuple[float, float] = (0.5, 0.7),
    elevation_deg: tuple[float, float] = (35.0, 70.0),
    model_points: int = 2048,
    base_T_object: SE3 | np.ndarray | None = None,
    base_T_camera: SE3 | np.ndarray | None = None,
    noise_seed: int | None = None,
    mesh: trimesh.Trimesh | None = None,
    symmetry: Symmetry | None = None,
) -> TabletopScene:
    """A random tabletop scene, reproducible from `seed`.

    The target stands upright at a random spot within 5 cm of the table's centre with a
    random yaw; `distractors` clutter objects (boxes, cans, balls) stand around it, never on
    the line of sight. The camera, held level, looks at the target's centre from a random
    `distance` (metres) and `elevation_deg` above the table plane, at a random azimuth.

    Args:
        seed: the scene (geometry, colours, camera) and its noise draw.
        object: the target, one of `OBJECTS`.
        noise: pass the exact depth through `sensor`; False keeps the exact render.
        distractors: number of clutter objects (0-8).
        sensor: the depth camera (default `StereoSensor.d435()`).
        intrinsics: default `sensor.intrinsics(848, 480)`.
        distance, elevation_deg: `(min, max)` of the uniform draws of the view.
        model_points: number of surface samples in `model_points`.
        base_T_object: `SE3` or `(4, 4)`: put the target here instead of at the seed's spot
            (a repeatability study's re-placements); distractors keep their positions
            relative to it. The seed's random draws are made either way, so colours and
            clutter stay the seed's.
        base_T_camera: `SE3` or `(4, 4)`: put the camera here instead of at the seed's view
            (a study's viewpoints); distractors stay off its line of sight.
        noise_seed: seed of the sensor-noise draw (default `seed`): the same scene
            re-measured, as a frozen scene is by repeated captures.
        mesh: a user's own target (metres, its frame's z up; it rests on its lowest
            point) instead of `object`'s, with its `symmetry` (default none).

    Returns:
        A `TabletopScene`.
    """
    if mesh is None and object not in OBJECTS:
        raise ValueError(f"unknown object {object!r}: choose one of {', '.join(OBJECTS)}")
    if not 0 <= distractors <= 8:
        raise ValueError(f"distractors must be 0..8 (room on the table), got {distractors}")
    sensor = StereoSensor.d435() if sensor is None else sensor
    intrinsics = sensor.intrinsics() if intrinsics is None else intrinsics
    rng = np.random.default_rng([seed, 0])  # geometry; noise draws from [seed, 1]

    if mesh is None:
        model, symmetry = object_mesh(object)
    else:
        model = mesh
        symmetry = Symmetry(np.eye(3)[None]) if symmetry is None else symmetry
    half_height = -model.bounds[0, 2]  # the origin's height when it rests on its lowest point
    target_xy = rng.uniform(-0.05, 0.05, 2)
    truth = _resting_pose(target_xy, rng.uniform(0, 2 * np.pi), half_height)
    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = np.radians(rng.uniform(*elevation_deg))
    view = rng.uniform(*distance) * np.array(
        [
            np.cos(elevation) * np.cos(azimuth),
            np.cos(elevation) * np.sin(azimuth),
            np.sin(elevation),
        ]
    )
    if base_T_object is not None:
        truth = _as_matrix(base_T_object, "base_T_object")
        target_xy = truth[:2, 3]
    centre = truth[:3, 3]
    if base_T_camera is None:
        base_T_camera = look_at(centre + view, centre)
        toward_camera = np.array([np.cos(azimuth), np.sin(azimuth)])
    else:
        base_T_camera = _as_matrix(base_T_camera, "base_T_camera")
        toward_camera = base_T_camera[:2, 3] - centre[:2]
        toward_camera /= max(np.linalg.norm(toward_camera), 1e-9)

    table = trimesh.creation.box(_TABLE_SIZE)
    table.apply_translation((0.0, 0.0, -_TABLE_SIZE[2] / 2))
    meshes = [table, _placed(model, truth)]
    colors = [np.array(_TABLE_COLOR), _random_color(rng, 0.25, 0.8)]
    for clutter, spot in _distractors(rng, distractors, toward_camera, _footprint_radius(model)):
        pose = _resting_pose(target_xy + spot, rng.uniform(0, 2 * np.pi), clutter.bounds[1, 2])
        meshes.append(_placed(clutter, pose))
        colors.append(_random_color(rng, 0.05, 0.8))

    rendering = render(meshes, intrinsics, base_T_camera, np.stack(colors))
    depth = rendering.depth
    if noise:
        noise_seed = seed if noise_seed is None else noise_seed
        depth = sensor.measure(rendering, np.random.default_rng([noise_seed, 1]))
    camera_pose, truth_pose = _poses(base_T_camera.astype(np.float32), truth.astype(np.float32))
    frame = RGBDFrame(
        depth.astype(np.float32), intrinsics, rgb=rendering.shade(), base_T_camera=camera_pose
    )
    samples, _ = trimesh.sample.sample_surface(model, model_points, seed=seed)
    return TabletopScene(
        frame=frame,
        model=model,
        model_points=samples.astype(np.float32),
        truth=truth_pose,
        mask=rendering.labels == 1,
        symmetry=symmetry,
        exact_depth=rendering.depth,
        labels=rendering.labels,
        model_colors=np.tile(display_color(colors[1]), (model_points, 1)).astype(np.float32),
    )
