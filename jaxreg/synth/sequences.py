"""Synthetic tracking sequences: a target pushed across the table in front of a still camera,
frame after frame, with its truth in every frame.

`tracking_sequence(seed)` renders the seed's tabletop scene (`tabletop_scene`) and moves the
target between frames by a step drawn from `step_translation` (metres, along a heading that
wanders and turns back toward the start so the target stays on the table and in view) and a
turn about the vertical drawn from `step_rotation_deg` (either sense). Frames listed in
`occluded` get a board in front of part of the target (a band of the image `occluder_fraction`
of the target's width, 10 cm nearer the camera than the target); from frame `leaves_at` on the
target is gone from the view. Each frame has its own noise draw.

Frames: as `tabletop_scene`'s (base frame z up, the table top at z = 0; `truth` is
`base_T_object`). The camera stays at the first frame's `base_T_camera`.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxlie import SE3

from jaxreg.camera.model import RGBDFrame
from jaxreg.synth.scenes import TabletopScene, tabletop_scene

__all__ = ["TrackingSequence", "tracking_sequence"]

_REACH = 0.12  # metres: the target turns back toward its start beyond this
_GONE = np.array([0.0, 0.0, -5.0])  # metres: where a target that left the view is put
_OCCLUDER_GAP = 0.10  # metres between the occluding board and the target's nearest point


@dataclasses.dataclass(frozen=True)
class TrackingSequence:
    """A rendered sequence of one target moving on a table.

    Attributes:
        scenes: ``N`` :class:`~jaxreg.synth.TabletopScene` (frame, truth, mask of the target's
            visible pixels, ...), in order.
        steps: ``(N - 1, 2)`` the motion from each frame to the next: the target's origin's
            displacement (metres) and its turn (degrees).
        occluded: ``(N,)`` bool, frames with a board in front of part of the target.
        in_view: ``(N,)`` bool, frames in which the target is on the table in view.
    """

    scenes: tuple[TabletopScene, ...]
    steps: np.ndarray
    occluded: np.ndarray
    in_view: np.ndarray


def tracking_sequence(
    seed: int = 0,
    *,
    object: str = "box",
    frames: int = 8,
    step_translation: tuple[float, float] = (0.01, 0.05),
    step_rotation_deg: tuple[float, float] = (2.0, 10.0),
    occluded: tuple[int, ...] = (),
    occluder_fraction: float = 0.4,
    leaves_at: int | None = None,
    **scene_options,
) -> TrackingSequence:
    """``frames`` frames of the seed's target moving across the table (module docstring).

    Args:
        seed: the scene (as `tabletop_scene`'s), the path and the noise draws.
        object: the target, one of `OBJECTS`.
        frames: number of frames (at least 2).
        step_translation: ``(min, max)`` metres the target's origin moves between frames.
        step_rotation_deg: ``(min, max)`` degrees it turns about the vertical between frames.
        occluded: indices of the frames with a board in front of part of the target.
        occluder_fraction: the share of the target's image width the board covers (0-1).
        leaves_at: from this frame on the target is out of view (``None``: never).
        **scene_options: `tabletop_scene`'s other options (``sensor``, ``distance``,
            ``distractors``: clutter keeps its place beside the target, as on a tray).

    Returns:
        A :class:`TrackingSequence`.
    """
    if frames < 2:
        raise ValueError(f"a sequence needs at least 2 frames, got {frames}")
    low, high = step_translation
    if not 0 <= low <= high:
        raise ValueError(f"step_translation must be (min, max) with 0 <= min <= max: {low, high}")
    if not 0 <= step_rotation_deg[0] <= step_rotation_deg[1]:
        raise ValueError(
            f"step_rotation_deg must be (min, max) with 0 <= min <= max: {step_rotation_deg}"
        )
    if not 0 < occluder_fraction < 1:
        raise ValueError(f"occluder_fraction must lie in (0, 1), got {occluder_fraction}")
    if any(not 0 <= k < frames for k in occluded):
        raise ValueError(f"occluded frames must be indices below {frames}, got {occluded}")
    scene_options.setdefault("distractors", 0)
    first = tabletop_scene(seed, object=object, **scene_options)
    camera = np.asarray(first.frame.base_T_camera.as_matrix(), np.float64)
    start = np.asarray(first.truth.as_matrix(), np.float64)
    rng = np.random.default_rng([seed, 2])
    poses, steps = [start], []
    heading = rng.uniform(0, 2 * np.pi)
    for _ in range(frames - 1):
        previous = poses[-1]
        offset = previous[:2, 3] - start[:2, 3]
        if np.linalg.norm(offset) > _REACH:  # turn back toward the start
            heading = np.arctan2(-offset[1], -offset[0])
        heading += rng.normal(0.0, 0.5)
        distance = rng.uniform(low, high)
        turn = np.radians(rng.uniform(*step_rotation_deg)) * rng.choice([-1.0, 1.0])
        c, s = np.cos(turn), np.sin(turn)
        pose = previous.copy()
        pose[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ previous[:3, :3]
        pose[:2, 3] += distance * np.array([np.cos(heading), np.sin(heading)])
        poses.append(pose)
        steps.append((distance, np.degrees(abs(turn))))
    in_view = np.array([leaves_at is None or k < leaves_at for k in range(frames)])
    scenes = []
    for k, pose in enumerate(poses):
        placed = pose if in_view[k] else _away(pose)
        scene = (
            first
            if k == 0 and in_view[0]
            else tabletop_scene(
                seed, object=object, base_T_object=placed, base_T_camera=camera,
                noise_seed=seed * 1000 + k, **scene_options,
            )
        )  # fmt: skip
        if not in_view[k]:
            scene = dataclasses.replace(scene, truth=SE3.from_matrix(pose.astype(np.float32)))
        if k in occluded:
            scene = _occluded(scene, occluder_fraction)
        scenes.append(scene)
    return TrackingSequence(
        scenes=tuple(scenes),
        steps=np.asarray(steps, np.float64).reshape(-1, 2),
        occluded=np.isin(np.arange(frames), occluded),
        in_view=in_view,
    )


def _away(pose: np.ndarray) -> np.ndarray:
    """``pose`` moved far below the table: the target out of the camera's view."""
    moved = pose.copy()
    moved[:3, 3] = _GONE
    return moved


def _occluded(scene: TabletopScene, fraction: float) -> TabletopScene:
    """``scene`` with a board in front of the target: the image columns of the left
    ``fraction`` of the target's width, over its rows and a margin, take the depth of a plane
    ``_OCCLUDER_GAP`` nearer the camera than the target's nearest point (noise-free; the
    colour image is left as rendered); the mask keeps the target's pixels still seen, and the
    board's pixels are labelled -2."""
    mask = scene.mask
    if not mask.any():
        return scene
    rows, cols = np.nonzero(mask)
    left = cols.min()
    right = left + max(1, int(round(fraction * (cols.max() - left + 1))))
    margin = max(2, (rows.max() - rows.min()) // 5)
    top, bottom = max(rows.min() - margin, 0), rows.max() + margin + 1
    depth = np.array(scene.frame.depth, np.float32)
    nearest = float(np.nanmin(np.where(mask, scene.exact_depth, np.nan)))
    depth[top:bottom, left:right] = nearest - _OCCLUDER_GAP
    board = np.zeros_like(mask)
    board[top:bottom, left:right] = True
    frame = RGBDFrame(depth, scene.frame.intrinsics, scene.frame.rgb, scene.frame.base_T_camera)
    labels = np.where(board, -2, scene.labels)
    return dataclasses.replace(scene, frame=frame, mask=mask & ~board, labels=labels)
