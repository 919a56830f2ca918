"""Projective data association: ICP against an organized target, one point per pixel of a
camera's image, where a source point's match is found by projecting it into that image.

A depth camera's lifted frame is such a target: pixel ``(u, v)`` of a ``height`` x ``width``
image is row ``v * width + u`` (NaN where the pixel has no depth). At the current pose each
moved source point is carried into the camera's frame, projected through the intrinsics (with
their distortion, :meth:`jaxreg.camera.model.Intrinsics.project`) and rounded to a pixel; its
match is the nearest valid target point among the ``(2 window + 1)^2`` pixels around that one,
within the correspondence distance. The work per point is constant (no neighbour grid, no
candidate lists), as KinectFusion-style trackers associate; the price is that a match is the
nearest in the window, not in the cloud: exact when the source lies near the sensed surface
(the last iterations of a registration that starts close), not when the start is far, or where
the surface is seen at a grazing angle (its points a pixel apart lie far apart in depth).

:func:`jaxreg.icp` and every ICP entry point take it as ``association=`` (a field of
:class:`jaxreg.ICPOptions`); rejection, trimming, kernels, statuses, the viewpoint's facing
test and the implicit gradients are those of the nearest-neighbour association.
:func:`organized_normals` gives such a target its normals for point-to-plane.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

__all__ = ["ProjectiveAssociation", "organized_normals"]


class ProjectiveAssociation(eqx.Module):
    """How ICP finds a source point's match in an organized target (see the module).

    Attributes:
        intrinsics: the :class:`~jaxreg.camera.model.Intrinsics` of the image the target's
            rows come from (row ``v * width + u`` is pixel ``(u, v)``); anything with its
            ``width``, ``height`` and ``project`` serves (this package imports no camera).
        target_T_camera: ``SE3`` the camera in target coordinates (the identity when the
            target is the frame lifted in the camera's own frame; a robot base's
            ``base_T_camera`` when it is lifted into the base frame).
        window: half-width (pixels) of the square searched around each projection: 0 the
            pixel hit, 1 (default) the 3 x 3 around it; static (a new value compiles anew).
    """

    intrinsics: eqx.Module
    target_T_camera: SE3
    window: int = eqx.field(static=True)

    def __init__(self, intrinsics, target_T_camera: SE3 | None = None, window: int = 1):
        if not all(hasattr(intrinsics, name) for name in ("width", "height", "fx", "project")):
            raise TypeError(
                "ProjectiveAssociation needs the image's jaxreg.camera.Intrinsics, got "
                f"{type(intrinsics).__name__}"
            )
        if int(window) != window or window < 0:
            raise ValueError(f"window must be a whole number of pixels >= 0, got {window}")
        if target_T_camera is None:
            target_T_camera = SE3(jnp.array([1.0, 0, 0, 0, 0, 0, 0], intrinsics.fx.dtype))
        elif not isinstance(target_T_camera, SE3):
            raise TypeError(
                f"target_T_camera must be a jaxlie.SE3, got {type(target_T_camera).__name__}"
            )
        self.intrinsics = intrinsics
        self.target_T_camera = target_T_camera
        self.window = int(window)

    @property
    def pixels(self) -> int:
        """The target's row count: ``width * height``."""
        return self.intrinsics.width * self.intrinsics.height


def projective_match(
    association: ProjectiveAssociation,
    moved: Float[Array, "N 3"],
    target: Float[Array, "M 3"],
    allowed: Bool[Array, " M"],
    distance: Float[Array, ""],
    rows_allowed: tuple[Bool[Array, " N"], Bool[Array, " M"]] | None = None,
) -> Int[Array, " N"]:
    """Row of each ``moved`` point's match (target coordinates): the nearest ``allowed``
    target row within ``distance`` among the window's pixels around its projection; ``M``
    (one past the last row) when none. ``rows_allowed = (rows, facing)``: the ``rows`` match
    only target rows that are also ``facing`` (the viewpoint's test)."""
    intrinsics, size = association.intrinsics, target.shape[0]
    camera_T_target = association.target_T_camera.inverse()
    rotation = camera_T_target.rotation().as_matrix().astype(moved.dtype)
    in_camera = moved @ rotation.T + camera_T_target.translation().astype(moved.dtype)
    depth = in_camera[:, 2]
    front = jnp.isfinite(depth) & (depth > 0)
    safe = jnp.where(front[:, None], in_camera, jnp.array([0.0, 0.0, 1.0], moved.dtype))
    pixel = jnp.round(intrinsics.project(safe))
    span = np.arange(-association.window, association.window + 1)
    du, dv = (offsets.reshape(-1) for offsets in np.meshgrid(span, span))
    limit = float(max(intrinsics.width, intrinsics.height) + 2 * association.window + 1)
    pixel = jnp.clip(jnp.where(jnp.isfinite(pixel), pixel, -limit), -limit, limit)
    u = pixel[:, :1].astype(jnp.int32) + du
    v = pixel[:, 1:].astype(jnp.int32) + dv  # (N, C) the window's pixels
    inside = (u >= 0) & (u < intrinsics.width) & (v >= 0) & (v < intrinsics.height)
    inside &= front[:, None]
    index = jnp.where(inside, v * intrinsics.width + u, 0)
    ok = inside & allowed[index]
    if rows_allowed is not None:
        rows, facing = rows_allowed
        ok &= ~rows[:, None] | facing[index]
    gap = target[index] - moved[:, None, :]
    squared = gap[..., 0] ** 2 + gap[..., 1] ** 2 + gap[..., 2] ** 2
    squared = jnp.where(ok & (squared <= distance * distance), squared, jnp.inf)
    best = jnp.argmin(squared, axis=1)
    found = jnp.isfinite(jnp.min(squared, axis=1))
    chosen = jnp.take_along_axis(index, best[:, None], axis=1)[:, 0]
    return jnp.where(found, chosen, size).astype(jnp.int32)


def organized_normals(
    points: Float[ArrayLike, "H W 3"], viewpoint: Float[ArrayLike, " 3"] | None = None
) -> Float[Array, "H W 3"]:
    """Unit normals of an organized cloud ``(H, W, 3)`` from its neighbouring pixels: the cross
    product of the central differences across the row and down the column, turned to face
    ``viewpoint`` (default the origin: a cloud in its camera's frame). A pixel without finite
    neighbours on both sides of an axis (an edge, a hole) falls back to the one-sided
    difference; where neither gives a normal it is zero, which ICP treats as unusable."""
    points = jnp.asarray(points)
    if points.ndim != 3 or points.shape[-1] != 3:
        raise ValueError(f"organized_normals takes an (H, W, 3) cloud, got {points.shape}")
    eye = jnp.zeros(3, points.dtype) if viewpoint is None else jnp.asarray(viewpoint, points.dtype)

    def along(axis: int) -> Array:
        ahead = jnp.roll(points, -1, axis)
        behind = jnp.roll(points, 1, axis)
        last = points.shape[axis] - 1
        position = jnp.arange(points.shape[axis]).reshape((-1, 1) if axis == 0 else (1, -1))
        ahead = jnp.where((position == last)[..., None], jnp.nan, ahead)
        behind = jnp.where((position == 0)[..., None], jnp.nan, behind)
        central = 0.5 * (ahead - behind)
        forward, backward = ahead - points, points - behind
        step = jnp.where(jnp.isfinite(central), central, forward)
        return jnp.where(jnp.isfinite(step), step, backward)

    normal = jnp.cross(along(1), along(0))
    length = jnp.linalg.norm(normal, axis=-1, keepdims=True)
    usable = jnp.isfinite(length) & (length > 0)
    normal = jnp.where(usable, normal / jnp.where(usable, length, 1.0), 0.0)
    toward = jnp.sum(normal * (eye - points), -1, keepdims=True)
    return jnp.where(toward < 0, -normal, normal)
