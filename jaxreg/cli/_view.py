"""The 3D view of ``jaxreg demo --view`` and ``jaxreg pose --view``, served to a browser by
viser (imported only here, only when a view is served).

:func:`view_scene` turns an estimate into what is drawn (host numpy, base frame, metres):

* the frame's points, one cloud per segment: the table (within :data:`TABLE_DISTANCE` of the
  plane the segment stage found), the object's segment (the lifted pixels,
  ``PoseEstimate.mask``) and the rest;
* the model at the estimated pose, and at the true pose where it is known (``demo``);
* the pose's error region: the :data:`REGION_LEVEL` ellipsoid of the translation block of
  ``PoseEstimate.covariance`` (every source of the budget), at the object frame's origin;
* the parallel gripper's jaws of the report's grasp (``report["grasp"]``): two pads
  ``opening`` apart across the model's narrowest axis, around the model's centre.

:func:`serve` draws a :class:`ViewScene` and serves it until its ``until`` hook returns
(default: until Ctrl-C).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
import time
from collections.abc import Callable

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

__all__ = ["COLORS", "REGION_LEVEL", "TABLE_DISTANCE", "ViewScene", "serve", "view_scene"]

# RGB of each layer; the points are drawn flat (unshaded): their pixels show these colours.
COLORS = {
    "table": (150, 150, 150),
    "object": (40, 190, 70),
    "rest": (70, 110, 220),
    "model": (255, 140, 0),
    "truth": (220, 40, 220),
    "region": (230, 30, 30),
    "jaws": (45, 45, 45),
}
SEGMENTS = ("table", "object", "rest")
TABLE_DISTANCE = 0.008  # metres from the table plane drawn as table (estimate_pose's default)
REGION_LEVEL = 0.95
PAD = (0.008, 0.022, 0.022)  # metres: a jaw pad's thickness (along the jaw axis) and its sides
MAX_MODEL_POINTS = 5_000


@dataclasses.dataclass(frozen=True)
class ViewScene:
    """What the view draws (host numpy, base frame, metres).

    Attributes:
        points: ``{segment: (N_s, 3)}`` the frame's points of each of ``"table"``,
            ``"object"``, ``"rest"``.
        point_size: the points' drawn size (metres): about one lifted pixel's footprint.
        model: ``(M, 3)`` model points at the estimated pose, or ``None`` without a pose.
        truth: ``(M, 3)`` model points at the true pose, or ``None`` when it is unknown.
        region: ``(center (3,), axes (3, 3) columns, radii (3,))`` of the error ellipsoid, or
            ``None`` without a pose.
        jaws: ``[(center (3,), axes (3, 3) columns, sides (3,)), ...]`` the two pads, or
            ``[]`` without a grasp.
        up: ``(3,)`` the scene's up (the table's normal, else the camera's up).
        eye, look_at: ``(3,)`` the initial viewpoint and the point it looks at.
        fov: the initial vertical field of view (radians): the camera's own.
        notes: markdown shown beside the scene: the legend and the numbers drawn.
    """

    points: dict[str, np.ndarray]
    point_size: float
    model: np.ndarray | None
    truth: np.ndarray | None
    region: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    jaws: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    up: np.ndarray
    eye: np.ndarray
    look_at: np.ndarray
    fov: float
    notes: str


def _segments(frame, estimate, stride: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Every ``stride``-th pixel's base-frame point by segment, and the rows' depths."""
    points = np.asarray(frame.points())[::stride, ::stride].reshape(-1, 3)
    depth = np.asarray(frame.depth)[::stride, ::stride].reshape(-1)
    valid = np.isfinite(points).all(-1)
    segment = np.full(len(points), 2, np.int8)
    if estimate.table is not None:
        height = points @ np.asarray(estimate.table.normal) + float(estimate.table.offset)
        segment[np.abs(height) < TABLE_DISTANCE] = 0
    segment[np.asarray(estimate.mask)[::stride, ::stride].reshape(-1)] = 1
    clouds = {
        name: points[valid & (segment == i)].astype(np.float32) for i, name in enumerate(SEGMENTS)
    }
    return clouds, depth[valid]


def _region(pose: np.ndarray, covariance: np.ndarray, size: float):
    """The :data:`REGION_LEVEL` ellipsoid of the translation block of ``covariance`` (object
    axes, metres) at ``pose``'s origin, in the base frame; a free axis is drawn ``size`` long.
    Returns ``(center, axes, radii, free)``."""
    block = np.array(covariance, np.float64)[:3, :3]
    free = ~np.isfinite(np.diag(block))
    block = np.where(np.isfinite(block), block, 0.0)
    scale = chi2.ppf(REGION_LEVEL, 3)
    block[free, free] = size**2 / scale
    values, vectors = np.linalg.eigh(0.5 * (block + block.T))
    radii = np.sqrt(scale * np.clip(values, 0.0, None))
    return pose[:3, 3], pose[:3, :3] @ vectors, radii, free


def _jaws(pose: np.ndarray, model_points: np.ndarray, grasp: dict, up: np.ndarray):
    """The two jaw pads of ``grasp`` (the report's grasp: ``axis`` in object axes,
    ``gripper_opening_mm``) around the model's centre, their sides along the base's ``up``."""
    rotation = pose[:3, :3]
    axis = rotation @ np.asarray(grasp["axis"], np.float64)
    side = np.cross(up, axis)
    if np.linalg.norm(side) < 1e-6:  # jaws closing along the up direction
        side = np.cross(axis, np.eye(3)[np.argmin(np.abs(axis))])
    side /= np.linalg.norm(side)
    axes = np.stack([axis, side, np.cross(axis, side)], 1)
    centre = rotation @ model_points.mean(0) + pose[:3, 3]
    offset = 0.5 * grasp["gripper_opening_mm"] * 1e-3 + 0.5 * PAD[0]
    return [(centre + s * offset * axis, axes, np.asarray(PAD)) for s in (-1.0, 1.0)]


def _notes(report: dict, region) -> str:
    """The legend and the numbers of ``report`` that the scene draws (markdown)."""
    lines = ["**grey** table, **green** the object's segment, **blue** the rest of the frame"]
    if report.get("pose") is None:
        lines.append(f"no pose: {report.get('failed_stage')} failed: {report.get('reason')}")
        return "\n\n".join(lines)
    lines.append("**orange** the model at the estimated pose")
    if report.get("add_s_mm") is not None:
        lines.append(
            f"**magenta** the model at the true pose: {report['translation_error_mm']:.2f} mm, "
            f"{report['rotation_error_deg']:.2f} deg, ADD-S {report['add_s_mm']:.2f} mm"
        )
    _, _, radii, free = region
    text = ", ".join(f"{2 * r * 1e3:.1f}" for r in radii)
    lines.append(
        f"**red** the {REGION_LEVEL:.0%} region of the object's origin (every source of the "
        f"error budget): axes {text} mm"
        + (" (a free axis drawn at the model's size)" if free.any() else "")
    )
    grasp = report.get("grasp")
    if grasp is not None:
        chance = "unknown" if grasp["probability"] is None else f"{grasp['probability']:.1%}"
        lines.append(
            f"**dark** the jaws: {grasp['gripper_opening_mm']:.0f} mm opening across "
            f"{grasp['object_width_mm']:.0f} mm, {grasp['margin_per_side_mm']:.1f} mm per side, "
            f"predicted success {chance}"
        )
    return "\n\n".join(lines)


def view_scene(
    frame, estimate, model_points: np.ndarray, report: dict, truth=None, stride: int = 2
) -> ViewScene:
    """The :class:`ViewScene` of an estimate.

    Args:
        frame: the :class:`jaxreg.RGBDFrame` the estimate came from.
        estimate: its :class:`jaxreg.PoseEstimate` (``mask``, ``table``, ``pose``,
            ``covariance``).
        model_points: ``(M, 3)`` model points (object frame, metres).
        report: the command's report (``jaxreg.cli._report.build_report``): its ``grasp``
            places the jaws, its numbers go in the notes.
        truth: ``SE3`` ``base_T_object`` of the true pose, or ``None``.
        stride: every ``stride``-th pixel of every ``stride``-th row is drawn.
    """
    model_points = np.asarray(model_points, np.float64)
    model_points = model_points[:: max(1, len(model_points) // MAX_MODEL_POINTS)]
    clouds, depth = _segments(frame, estimate, stride)
    typical_depth = float(np.median(depth)) if len(depth) else 1.0  # metres
    point_size = 1.5 * stride * typical_depth / float(frame.intrinsics.fx)
    base_T_camera = np.asarray(frame.base_T_camera.as_matrix(), np.float64)
    if estimate.table is not None:
        up = np.asarray(estimate.table.normal, np.float64)
    else:
        up = base_T_camera[:3, :3] @ np.array([0.0, -1.0, 0.0])
    model = truth_points = region = None
    jaws = []
    if estimate.pose is not None:
        pose = np.asarray(estimate.pose.as_matrix(), np.float64)
        model = (model_points @ pose[:3, :3].T + pose[:3, 3]).astype(np.float32)
        size = float(np.ptp(model_points, axis=0).max())
        region = _region(pose, estimate.covariance, size)
        if report.get("grasp") is not None:
            jaws = _jaws(pose, model_points, report["grasp"], up)
        look_at = pose[:3, :3] @ model_points.mean(0) + pose[:3, 3]
    else:  # the frame's middle point, or straight ahead of the camera at a typical depth
        look_at = base_T_camera[:3, :3] @ np.array([0.0, 0.0, typical_depth])
        look_at = look_at + base_T_camera[:3, 3]
        seen = np.concatenate(list(clouds.values()))
        look_at = np.median(seen, axis=0) if len(seen) else look_at
    if truth is not None:
        matrix = np.asarray(truth.as_matrix(), np.float64)
        truth_points = (model_points @ matrix[:3, :3].T + matrix[:3, 3]).astype(np.float32)
    # From the camera's side, nearer and a little higher, so the depth's relief shows.
    sight = base_T_camera[:3, 3] - look_at
    eye = look_at + 0.3 * sight + 0.2 * np.linalg.norm(sight) * up
    height = np.asarray(frame.depth).shape[0]
    fov = 2.0 * np.arctan(0.5 * height / float(frame.intrinsics.fy))
    return ViewScene(
        points=clouds, point_size=point_size, model=model, truth=truth_points,
        region=None if region is None else region[:3], jaws=jaws, up=up, eye=eye,
        look_at=look_at, fov=float(fov), notes=_notes(report, region),
    )  # fmt: skip


def _wxyz(axes: np.ndarray) -> np.ndarray:
    """Scalar-first quaternion of the rotation whose columns are ``axes`` (made right-handed)."""
    axes = axes * np.array([1.0, 1.0, np.sign(np.linalg.det(axes)) or 1.0])
    return Rotation.from_matrix(axes).as_quat(scalar_first=True)


def _draw(server, scene: ViewScene) -> None:
    server.scene.set_up_direction(tuple(scene.up))
    # The object's segment is drawn finer than the other points so that the model, which lies
    # on the same surface, shows between them.
    sizes = {"object": 0.6, "truth": 0.5, "model": 0.6}
    layers = {f"frame/{name}": (name, points) for name, points in scene.points.items()}
    layers.update(truth=("truth", scene.truth), model=("model", scene.model))
    for node, (name, points) in layers.items():
        if points is not None:
            server.scene.add_point_cloud(
                f"/{node}", points, np.array(COLORS[name], np.uint8),
                point_size=sizes.get(name, 1.0) * scene.point_size, point_shading="flat",
            )  # fmt: skip
    if scene.region is not None:
        center, axes, radii = scene.region
        server.scene.add_icosphere(
            "/error_region", radius=1.0, color=COLORS["region"], opacity=0.6,
            scale=tuple(np.maximum(radii, 1e-5)), wxyz=_wxyz(axes), position=center,
        )  # fmt: skip
    for i, (center, axes, sides) in enumerate(scene.jaws):
        server.scene.add_box(
            f"/jaws/{i}", COLORS["jaws"], tuple(sides), wxyz=_wxyz(axes), position=center
        )
    server.initial_camera.position = scene.eye
    server.initial_camera.look_at = scene.look_at
    server.initial_camera.up = scene.up
    server.initial_camera.fov = scene.fov
    server.gui.add_markdown(scene.notes)


@contextlib.contextmanager
def _quiet():
    """viser's banner and its stop message (printed to stdout) silenced."""
    with open(os.devnull, "w") as devnull, contextlib.redirect_stdout(devnull):
        yield


def _until_interrupted(url: str) -> None:
    """Returns at Ctrl-C. Short sleeps: the signal may land on one of viser's threads, and the
    main thread only runs Python's handler between sleeps."""
    try:
        while True:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass


def serve(
    scene: ViewScene,
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    until: Callable[[str], object] | None = None,
    log=None,
) -> str:
    """Serves ``scene`` at ``http://host:port`` (the next free port if ``port`` is taken; 0: any
    free port), prints the URL to ``log`` (default stderr), and stops when ``until(url)``
    returns (default: at Ctrl-C). Returns the URL. viser's own banner is silenced, so a
    command's stdout stays its report."""
    import viser

    log = sys.stderr if log is None else log
    with _quiet():
        server = viser.ViserServer(host=host, port=port, verbose=False)
    try:
        _draw(server, scene)
        url = f"http://{host}:{server.get_port()}"
        print(f"3D view at {url} (Ctrl-C to stop)", file=log, flush=True)
        (until or _until_interrupted)(url)
    finally:
        with _quiet():
            server.stop()
    return url
