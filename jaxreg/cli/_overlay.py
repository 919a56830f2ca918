"""``model_overlay.png`` of ``jaxreg pose --out`` and ``jaxreg demo --out``: the model's visible
surface at the estimate, drawn over the frame's picture so that a user reads it at a glance.

:func:`model_overlay` draws, over the colour image (or the depth's false colour):

* the estimate as a filled, outlined silhouette in :data:`ESTIMATE` with the object's axes from
  its origin (x red, y green, z blue, each as long as the model's farthest point from it);
* where the truth is known, its silhouette's outline in :data:`TRUTH`;
* for a refused estimate, the register stage's best hypothesis
  (``RegisterRecord.hypothesis``), filled and outlined in :data:`REFUSED`, with its axes;
* a legend at the top: what each colour is, the errors against the truth, and for a refused
  estimate the failed stage and its reason.

A silhouette (:func:`silhouette`) is the part of the model a camera would see at that pose:
the model's points are projected, each splatted as a disk of half the point spacing's
footprint at its depth, and a point counts where no nearer model point covers its pixel (a
z-buffer of those disks) and the measured depth does not lie more than
:data:`HIDDEN_BEHIND` in front of it (an occluder, or the object's own front seen through a
wrong pose). The visible points' disks, closed morphologically over the gaps the sampling
leaves, fill it. A pose whose model lies mostly behind the measured surface (a refused
hypothesis sunk into the table) is drawn whole, and the legend says so, as it says when a pose
falls outside the image.
"""

from __future__ import annotations

import dataclasses
import textwrap

import numpy as np
from PIL import Image, ImageDraw, ImageFont
from scipy import ndimage
from scipy.spatial import cKDTree

from jaxreg.cli._view import COLORS
from jaxreg.core._program_cache import persistent_jit
from jaxreg.core._sizes import pad_rows, power_of_two

__all__ = [
    "AXES",
    "ESTIMATE",
    "HIDDEN_BEHIND",
    "REFUSED",
    "TRUTH",
    "Overlay",
    "model_overlay",
    "silhouette",
]

ESTIMATE = COLORS["model"]  # the same colours as the 3D view's (jaxreg.cli._view)
TRUTH = COLORS["truth"]
REFUSED = (205, 205, 205)
AXES = ((235, 35, 35), (40, 215, 40), (50, 110, 255))  # x, y, z
FILL_ALPHA = 0.45
# metres the measured depth lies in front of a model point to hide it: beyond a few sigma of a
# depth camera's noise at 1-2 m and an estimate's error of a few millimetres, within the
# thickness of most occluders
HIDDEN_BEHIND = 0.02
MOSTLY_BEHIND = 0.8  # share of the model's own visible side hidden by the scene: drawn whole
MAX_POINTS = 20_000  # more model points are thinned to this many (a stride)


@dataclasses.dataclass(frozen=True)
class Overlay:
    """The drawn picture and what it says.

    Attributes:
        image: ``(H, W, 3)`` uint8.
        legend: the legend's lines, top to bottom, as written on the image.
        filled: ``{layer: (H, W) bool}`` the silhouette drawn for each pose (``"estimate"``,
            ``"hypothesis"``, ``"truth"``), of the poses drawn.
    """

    image: np.ndarray
    legend: list[str]
    filled: dict[str, np.ndarray]


@persistent_jit
def _project(intrinsics, camera_points):
    """Pixels ``(P, 2)`` of camera-frame points ``(P, 3)``: one stored program per padded
    length."""
    return intrinsics.project(camera_points)


def project_points(frame, camera_points: np.ndarray) -> np.ndarray:
    """Pixels ``(P, 2)`` (u, v; float64) of camera-frame points ``(P, 3)`` (metres, z > 0)
    through ``frame``'s intrinsics and their distortion, in a list padded to a bucketed length
    (a few stored programs serve every count)."""
    count = len(camera_points)
    # the padding rows (1, 1, 1) lie in front of the camera: a finite projection
    padded = pad_rows(np.asarray(camera_points, np.float32), power_of_two(count, 1024), 1.0)
    return np.asarray(_project(frame.intrinsics, padded), np.float64)[:count]


def _disk(radius: int) -> np.ndarray:
    """``(K, 2)`` integer offsets (rows, columns) of a disk of this radius (pixels)."""
    r = np.arange(-radius, radius + 1)
    dv, du = np.meshgrid(r, r, indexing="ij")
    inside = dv**2 + du**2 <= radius**2 + radius
    return np.stack([dv[inside], du[inside]], -1)


def _splat(shape, rows, cols, radii):
    """Flat pixel indices ``(P,)`` of the disks at ``(rows, cols)`` with ``radii`` (ints),
    and for each the index of its point ``(P,)``; disks are clipped to the image."""
    height, width = shape
    pixels, owners = [], []
    for radius in np.unique(radii):
        which = np.flatnonzero(radii == radius)
        offsets = _disk(int(radius))
        vv = rows[which, None] + offsets[None, :, 0]
        uu = cols[which, None] + offsets[None, :, 1]
        inside = (vv >= 0) & (vv < height) & (uu >= 0) & (uu < width)
        pixels.append((vv * width + uu)[inside])
        owners.append(np.broadcast_to(which[:, None], vv.shape)[inside])
    if not pixels:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(pixels), np.concatenate(owners)


def _spacing(points: np.ndarray) -> float:
    """The model's point spacing (metres): the median distance to a point's fourth nearest
    neighbour, about the spacing of a uniform sampling of the same density (the nearest
    neighbour's is smaller, more so where the sampling clusters)."""
    distances, _ = cKDTree(points).query(points, k=min(5, len(points)))
    spacing = float(np.median(distances[:, -1]))
    return spacing if spacing > 0 else 1e-3


def _close(mask: np.ndarray, footprint: float) -> np.ndarray:
    """``mask`` closed morphologically by a disk of radius ``footprint`` (pixels: the point
    spacing's at the model's depth), padded so the image's border does not erode it, and its
    holes smaller than a disk of 1.5 footprints filled: the gaps a random sampling leaves,
    not a mug's handle."""
    radius = int(np.clip(round(footprint), 1, 15))
    if not mask.any():
        return mask
    offsets = _disk(radius)
    structure = np.zeros((2 * radius + 1,) * 2, bool)
    structure[offsets[:, 0] + radius, offsets[:, 1] + radius] = True
    padded = np.pad(mask, radius + 1)
    closed = ndimage.binary_closing(padded, structure)
    closed = closed[radius + 1 : -radius - 1, radius + 1 : -radius - 1]
    holes, count = ndimage.label(ndimage.binary_fill_holes(closed) & ~closed)
    if count:
        sizes = np.bincount(holes.ravel(), minlength=count + 1)
        small = sizes <= np.pi * (1.5 * footprint) ** 2
        small[0] = False
        closed = closed | small[holes]
    return closed


def silhouette(
    frame, model_points: np.ndarray, base_T_object: np.ndarray, spacing: float | None = None
) -> tuple[np.ndarray, bool]:
    """The model's visible surface at a pose, as pixels.

    Args:
        frame: the :class:`jaxreg.RGBDFrame` (its depth, intrinsics and ``base_T_camera``).
        model_points: ``(M, 3)`` model points (object frame, metres).
        base_T_object: ``(4, 4)`` the pose.
        spacing: the model's point spacing (metres); default measured on ``model_points``.

    Returns:
        ``(H, W)`` bool the filled silhouette of the points the camera sees at that pose (see
        the module docstring), and whether it is drawn whole because the measured surface
        lies in front of most of it (``True``) or with the scene's occlusions.
    """
    points = np.asarray(model_points, np.float64)
    points = points[:: max(1, -(-len(points) // MAX_POINTS))]
    spacing = _spacing(points) if spacing is None else spacing
    depth = np.asarray(frame.depth, np.float64)
    shape = depth.shape
    camera_T_base = np.linalg.inv(np.asarray(frame.base_T_camera.as_matrix(), np.float64))
    camera_T_object = camera_T_base @ np.asarray(base_T_object, np.float64)
    cam = points @ camera_T_object[:3, :3].T + camera_T_object[:3, 3]
    cam = cam[cam[:, 2] > 1e-3]
    empty = np.zeros(shape, bool)
    if len(cam) == 0:
        return empty, False
    pix = project_points(frame, cam)
    fx = float(frame.intrinsics.fx)
    footprints = spacing * fx / cam[:, 2]  # pixels: the point spacing at each point's depth
    radii = np.clip(np.rint(0.5 * footprints), 1, 30).astype(np.int64)
    keep = (
        np.isfinite(pix).all(-1)
        & (pix[:, 0] > -radii) & (pix[:, 0] < shape[1] + radii)
        & (pix[:, 1] > -radii) & (pix[:, 1] < shape[0] + radii)
    )  # fmt: skip
    if not keep.any():
        return empty, False
    cam, pix, radii, footprints = cam[keep], pix[keep], radii[keep], footprints[keep]
    cols, rows = np.rint(pix[:, 0]).astype(np.int64), np.rint(pix[:, 1]).astype(np.int64)
    z = cam[:, 2]
    # the model's own z-buffer: each point's disk at its depth, the nearest kept per pixel
    flat, owner = _splat(shape, rows, cols, radii)
    zbuffer = np.full(depth.size, np.inf)
    np.minimum.at(zbuffer, flat, z[owner])
    on_image = (rows >= 0) & (rows < shape[0]) & (cols >= 0) & (cols < shape[1])
    at = np.where(on_image, rows, 0) * shape[1] + np.where(on_image, cols, 0)
    front = z <= np.where(on_image, zbuffer[at], np.inf) + 2.5 * spacing
    # a pixel without depth takes the nearest measured depth within a disk's reach: an
    # occluder's edge, where the sensor often has no return, still hides the points behind it
    reach = int(np.median(radii))
    nearest = ndimage.minimum_filter(np.where(np.isfinite(depth), depth, np.inf), 2 * reach + 1)
    measured = np.where(np.isfinite(depth), depth, nearest).reshape(-1)
    behind = np.where(on_image, measured[at], np.inf) < z - HIDDEN_BEHIND
    seen = front & ~behind
    whole = seen.sum() < (1 - MOSTLY_BEHIND) * front.sum()
    drawn = front if whole else seen
    mask = np.zeros(depth.size, bool)
    mask[flat[drawn[owner]]] = True
    mask = mask.reshape(shape)
    footprint = float(np.median(footprints[drawn])) if drawn.any() else 1.0
    return _close(mask, footprint), whole


def _outline(mask: np.ndarray, width: int) -> np.ndarray:
    """The pixels of ``mask`` within ``width`` pixels of its edge."""
    return mask & ~ndimage.binary_erosion(mask, iterations=width, border_value=1)


def _blend(image: np.ndarray, where: np.ndarray, colour, alpha: float) -> None:
    image[where] = (1 - alpha) * image[where] + alpha * np.asarray(colour, np.float64)


def _axes(frame, base_T_object: np.ndarray, length: float):
    """The origin's and the three axis ends' pixels ``(4, 2)`` of a pose, or ``None`` when one
    lies behind the camera."""
    camera_T_base = np.linalg.inv(np.asarray(frame.base_T_camera.as_matrix(), np.float64))
    camera_T_object = camera_T_base @ np.asarray(base_T_object, np.float64)
    ends = np.vstack([np.zeros(3), length * np.eye(3)])
    cam = ends @ camera_T_object[:3, :3].T + camera_T_object[:3, 3]
    if (cam[:, 2] <= 1e-3).any():
        return None
    return project_points(frame, cam)


def _font(size: int):
    return ImageFont.load_default(size=size)


def _legend_lines(estimate, truth_known: bool, report: dict | None, whole: dict, filled) -> list:
    """``[(text, colour)]`` of the legend; ``whole`` and ``filled`` by layer, as
    :func:`silhouette` returned them."""
    report = report or {}

    def where(name: str) -> str:
        if not filled[name].any():
            return ", outside the image"
        return ", drawn whole: it lies behind the measured surface" if whole[name] else ""

    lines = []
    if estimate.pose is not None:
        text = "orange: the estimate"
        if report.get("add_s_mm") is not None:
            text += (
                f" (ADD-S {report['add_s_mm']:.1f} mm; {report['translation_error_mm']:.1f} mm, "
                f"{report['rotation_error_deg']:.1f} deg from the truth)"
            )
        lines.append((text + where("estimate"), ESTIMATE))
    else:
        refused = f"REFUSED at {estimate.failed_stage}: {estimate.reason}"
        lines.append((refused, (255, 255, 255)))
        if "hypothesis" in whole:
            text = "grey: the best hypothesis, refused" + where("hypothesis")
        else:
            text = "no hypothesis to draw: the refinement did not run"
        lines.append((text, REFUSED))
    if truth_known:
        lines.append(("magenta outline: the truth" + where("truth"), TRUTH))
    if estimate.pose is not None or "hypothesis" in whole:
        lines.append(("axes from the origin: x red, y green, z blue", (235, 235, 235)))
    return lines


def _draw_legend(image: Image.Image, lines: list) -> list[str]:
    """Writes ``lines`` (``[(text, colour)]``) at the image's top on a dark band, wrapped to
    its width; returns the written lines."""
    width, height = image.size
    size = max(11, height // 36)
    font = _font(size)
    draw = ImageDraw.Draw(image, "RGBA")
    per_line = max(20, int(width / (0.55 * size)))
    written = [
        (part, colour)
        for text, colour in lines
        for part in textwrap.wrap(text, per_line, subsequent_indent="  ")
    ]
    step = int(size * 1.25)
    margin = max(4, size // 3)
    band = max(draw.textlength(text, font=font) for text, _ in written) if written else 0
    draw.rectangle(
        (0, 0, min(width, band + 2 * margin), 2 * margin + step * len(written)),
        fill=(0, 0, 0, 170),
    )
    for k, (text, colour) in enumerate(written):
        draw.text((margin, margin + k * step), text, fill=tuple(colour), font=font)
    return [text for text, _ in written]


def model_overlay(
    base: np.ndarray, frame, estimate, model_points: np.ndarray, truth=None, report=None
) -> Overlay:
    """The model drawn at an estimate over ``base`` (see the module docstring).

    Args:
        base: ``(H, W, 3)`` the picture drawn on (the colour image, or the depth's false
            colour), uint8 or float 0-255.
        frame: the :class:`jaxreg.RGBDFrame` the estimate came from.
        estimate: its :class:`jaxreg.PoseEstimate`; without a pose, its register record's
            ``hypothesis`` (``None`` when the refinement did not run) is drawn in grey.
        model_points: ``(M, 3)`` model points (object frame, metres).
        truth: ``SE3`` ``base_T_object`` of the true pose, or ``None``.
        report: the command's report (``jaxreg.cli._report.build_report``): its errors
            against the truth, where present, are written in the legend.
    """
    image = np.array(base, np.float64)
    outline_width = max(2, image.shape[0] // 240)
    points = np.asarray(model_points, np.float64)
    spacing = _spacing(points[:: max(1, -(-len(points) // MAX_POINTS))])
    length = float(np.linalg.norm(points, axis=1).max())
    layers = {}  # name: (base_T_object, colour, filled)
    if truth is not None:
        layers["truth"] = (np.asarray(truth.as_matrix(), np.float64), TRUTH, False)
    if estimate.pose is not None:
        layers["estimate"] = (np.asarray(estimate.pose.as_matrix(), np.float64), ESTIMATE, True)
    else:
        record = estimate.stages.get("register")
        hypothesis = getattr(record, "hypothesis", None)
        if hypothesis is not None:
            layers["hypothesis"] = (np.asarray(hypothesis, np.float64), REFUSED, True)
    filled, whole = {}, {}
    for name, (pose, _, _) in layers.items():
        filled[name], whole[name] = silhouette(frame, points, pose, spacing)
    # the fill and a dark rim outside it, the truth's outline just outside its silhouette, and
    # the estimate's just inside its own: where the two agree, both show side by side
    for name, (_, colour, fill) in layers.items():
        if fill:
            _blend(image, filled[name], colour, FILL_ALPHA)
            rim = ndimage.binary_dilation(filled[name], iterations=outline_width)
            _blend(image, rim & ~filled[name], (0, 0, 0), 0.6)
    if "truth" in layers:
        ring = ndimage.binary_dilation(filled["truth"], iterations=outline_width)
        image[ring & ~filled["truth"]] = TRUTH
    for name, (_, colour, fill) in layers.items():
        if fill:
            image[_outline(filled[name], outline_width)] = colour
    picture = Image.fromarray(np.clip(np.rint(image), 0, 255).astype(np.uint8))
    draw = ImageDraw.Draw(picture)
    axis_width = max(2, image.shape[0] // 160)
    for name in ("estimate", "hypothesis"):
        if name not in layers:
            continue
        ends = _axes(frame, layers[name][0], length)
        if ends is None:
            continue
        origin = tuple(ends[0])
        for end, colour in zip(ends[1:], AXES, strict=True):
            draw.line([origin, tuple(end)], fill=(0, 0, 0), width=axis_width + 2)
            draw.line([origin, tuple(end)], fill=colour, width=axis_width)
    lines = _legend_lines(estimate, truth is not None, report, whole, filled)
    legend = _draw_legend(picture, lines)
    return Overlay(np.asarray(picture), legend, filled)
