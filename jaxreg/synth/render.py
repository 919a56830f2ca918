"""Exact rendering of meshes: the first surface each pixel's ray hits (Embree through embreex,
the hit distance solved in float64 on the triangle's plane), its normal, label and shading.

Frames: `base_T_camera` maps camera coordinates (OpenCV: z forward, x right, y down) into the
base frame; depth is z-depth in metres, NaN where a ray hits nothing. Host numpy throughout.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
import trimesh
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from jaxlie import SE3

from jaxreg.camera.model import Intrinsics
from jaxreg.core._program_cache import persistent_jit

__all__ = ["Rendering", "render"]

_BACKGROUND_RGB = (40, 40, 46)
_AMBIENT = 0.35
_LIGHT_BASE = np.array([0.3, -0.4, 1.0]) / np.linalg.norm([0.3, -0.4, 1.0])  # toward the light
LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance of linear RGB
DISPLAY_GAMMA = 1 / 2.2  # linear RGB to the image's display values


def display_color(colors: np.ndarray) -> np.ndarray:
    """Linear RGB ``(..., 3)`` (clipped to [0, 1]) as display (sRGB-like) values in [0, 1]:
    a fully lit paint's colour in :meth:`Rendering.shade`'s images."""
    return np.clip(np.asarray(colors, float), 0.0, 1.0) ** DISPLAY_GAMMA

# One stored program, not the dozens of small ones `pixel_rays` compiles op by op when called
# eagerly (the same XLA arithmetic: bitwise the same rays; numpy's division rounds otherwise).
_pixel_rays = persistent_jit(Intrinsics.pixel_rays)


class _RayCaster:
    """First hits of rays on a triangle soup: Embree (float32, through embreex) picks the
    triangle, the hit distance is solved in float64 on that triangle's plane."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self.centre = (vertices.min(axis=0) + vertices.max(axis=0)) / 2  # float32 origin
        self.scene = rtcore_scene.EmbreeScene()
        TriangleMesh(
            scene=self.scene,
            vertices=(vertices - self.centre).astype(np.float32),
            indices=faces.astype(np.int32),
        )
        corners = vertices[faces]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        # one extra row, read by the miss index -1: no plane
        self.normals = np.vstack([normals, np.full((1, 3), np.nan)])
        self.anchors = np.vstack([corners[:, 0], np.full((1, 3), np.nan)])

    def cast(self, origin: np.ndarray, directions: np.ndarray):
        """Rays from `origin` `(3,)` along `directions` `(N, 3)` (any length): the `(N,)`
        index of the first face hit (-1 on a miss), the `(N,)` parameter `s` where
        `origin + s * direction` meets that face's plane and its `(N, 3)` unit normal (NaN
        on a miss)."""
        start = np.broadcast_to((origin - self.centre).astype(np.float32), directions.shape)
        faces = self.scene.run(np.ascontiguousarray(start), directions.astype(np.float32))
        normals = np.take(self.normals, faces, axis=0)
        offsets = np.einsum("ij,ij->i", self.normals, self.anchors - origin)
        along = np.take(offsets, faces) / np.einsum("ij,ij->i", normals, directions)
        return faces, along, normals


@dataclasses.dataclass(frozen=True, eq=False)
class Rendering:
    """The exact image of a set of meshes: what every pixel's ray hits first. Host numpy.

    Attributes:
        intrinsics: the camera's `Intrinsics` (shape `(H, W)`).
        base_T_camera: `(4, 4)` float64 camera -> base.
        depth: `(H, W)` float64 exact z-depth in metres, NaN where the ray hits nothing.
        labels: `(H, W)` int32 index of the mesh hit (order of `render`'s `meshes`), -1 none.
        normals: `(H, W, 3)` camera-frame unit normals of the faces hit, turned toward the
            camera; NaN where nothing is hit.
        rays: `(H, W, 3)` float64 unit-depth rays `(x/z, y/z, 1)` of the pixel centres.
        albedo: `(H, W)` luminance in [0, 1] of the mesh hit (NaN where nothing is hit).
        colors: `(M, 3)` float linear RGB in [0, 1] of every mesh.
    """

    intrinsics: Intrinsics
    base_T_camera: np.ndarray
    depth: np.ndarray
    labels: np.ndarray
    normals: np.ndarray
    rays: np.ndarray
    albedo: np.ndarray
    colors: np.ndarray
    _caster: _RayCaster = dataclasses.field(repr=False)

    def camera_points(self) -> np.ndarray:
        """`(H, W, 3)` exact camera-frame hit points (metres), NaN where nothing is hit."""
        return self.depth[..., None] * self.rays

    def visible_from(self, origin_camera: np.ndarray) -> np.ndarray:
        """`(H, W)` bool: the pixel's hit point is seen, unobstructed, from `origin_camera`
        `(3,)` (camera frame, metres), e.g. a stereo pair's second imager. False on misses."""
        surface = np.isfinite(self.depth)
        segments = self.camera_points()[surface] - origin_camera  # s = 1 at the hit point
        faces, reach, _ = self._caster.cast(np.asarray(origin_camera, float), segments)
        slack = 1e-5 / np.linalg.norm(segments, axis=-1)  # 10 um for the hit point itself
        visible = np.zeros(self.depth.shape, dtype=bool)
        visible[surface] = (faces < 0) | (reach >= 1 - slack)
        return visible

    def shade(self) -> np.ndarray:
        """`(H, W, 3)` uint8 RGB: Lambertian shading of each mesh's colour under one distant
        light above the table plus ambient light; background where nothing is hit."""
        light_camera = self.base_T_camera[:3, :3].T @ _LIGHT_BASE
        lambert = np.clip(np.nan_to_num(self.normals @ light_camera), 0.0, None)
        shading = _AMBIENT + (1 - _AMBIENT) * lambert
        # display gamma: (colour * shading)^g = colour^g * shading^g, one power per pixel
        palette = np.vstack([display_color(self.colors), np.zeros(3)])
        srgb = np.minimum(palette[self.labels] * (shading**DISPLAY_GAMMA)[..., None], 1.0)
        rgb = np.rint(255 * srgb).astype(np.uint8)
        rgb[self.labels < 0] = _BACKGROUND_RGB
        return rgb


def render(
    meshes: Sequence[trimesh.Trimesh],
    intrinsics: Intrinsics,
    base_T_camera: SE3 | np.ndarray,
    colors: np.ndarray | None = None,
) -> Rendering:
    """Ray cast `meshes` (base frame, metres) from a camera: the exact depth image.

    Args:
        meshes: M triangle meshes in the base frame.
        intrinsics: the camera; distortion, if any, is honoured (each pixel casts its
            undistorted ray).
        base_T_camera: `SE3` or `(4, 4)` camera -> base.
        colors: `(M, 3)` linear RGB in [0, 1] per mesh (for `shade` and the sensor's dark-
            surface holes); default mid grey.

    Returns:
        A `Rendering`.
    """
    if len(meshes) == 0:
        raise ValueError("render needs at least one mesh")
    colors = np.full((len(meshes), 3), 0.5) if colors is None else np.asarray(colors, float)
    if colors.shape != (len(meshes), 3):
        raise ValueError(f"colors must be (M, 3) = ({len(meshes)}, 3), got {colors.shape}")
    pose = base_T_camera.as_matrix() if isinstance(base_T_camera, SE3) else base_T_camera
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"base_T_camera must be an SE3 or (4, 4), got shape {pose.shape}")
    # cast in the camera frame: the meshes move (few vertices), the rays (every pixel) do not
    merged = trimesh.util.concatenate(list(meshes))
    camera_T_base = np.linalg.inv(pose)
    vertices = merged.vertices @ camera_T_base[:3, :3].T + camera_T_base[:3, 3]
    caster = _RayCaster(vertices, merged.faces)
    rays = np.asarray(_pixel_rays(intrinsics), dtype=np.float64)
    flat = rays.reshape(-1, 3)
    faces, depth, normals = caster.cast(np.zeros(3), flat)  # unit-depth rays: s is z
    normals *= np.where(np.einsum("ij,ij->i", normals, flat) > 0, -1.0, 1.0)[:, None]  # to camera

    face_counts = [len(mesh.faces) for mesh in meshes]
    face_labels = np.append(np.repeat(np.arange(len(meshes), dtype=np.int32), face_counts), -1)
    face_albedo = np.append((colors @ LUMA)[face_labels[:-1]], np.nan)
    shape = rays.shape[:2]
    return Rendering(
        intrinsics=intrinsics,
        base_T_camera=pose,
        depth=depth.reshape(shape),
        labels=np.take(face_labels, faces).reshape(shape),
        normals=normals.reshape(*shape, 3),
        rays=rays,
        albedo=np.take(face_albedo, faces).reshape(shape),
        colors=colors,
        _caster=caster,
    )
