"""Many frames in one call: :func:`estimate_poses`, the pipeline over a list of frames with
one frame per host core at a time.

A frame's pipeline is a chain of compiled programs (JAX) and compiled host loops (numba),
each on one core, with short Python steps between them; two frames in flight on a 2-core
CPU keep both cores busy. The first frame runs alone (its first call compiles or loads the
programs every later frame shares), the others on the pool of
:mod:`jaxreg.core._threads`. Each frame's answer is the one :func:`estimate_pose` gives it
alone.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from jaxtyping import Float

from jaxreg.camera.model import RGBDFrame
from jaxreg.core._threads import in_pieces
from jaxreg.pipeline.estimate import PoseEstimate, estimate_pose

__all__ = ["estimate_poses"]


def estimate_poses(
    frames: Sequence[RGBDFrame],
    model_points: Float[Any, "M 3"],
    *,
    masks: Sequence[Any] | None = None,
    **options,
) -> list[PoseEstimate]:
    """:func:`estimate_pose` of one model in every frame of ``frames``, frames running
    concurrently (one per host core); answers in the frames' order.

    Args:
        frames: the depth frames (:class:`jaxreg.RGBDFrame`), any sizes and cameras.
        model_points: ``(M, 3)`` the object's points (object frame, metres), shared.
        masks: one mask per frame (each ``(H, W)`` or ``None``), or ``None`` for none.
        **options: :func:`estimate_pose`'s other keyword arguments, the same for every frame.

    Returns:
        One :class:`PoseEstimate` per frame, in order: a frame where the object is not found
        has its refusal, as from :func:`estimate_pose`.

    Raises:
        ValueError: ``masks`` not one per frame, or a frame's bad input (the message names
            the frame's index).
    """
    frames = list(frames)
    masks = [None] * len(frames) if masks is None else list(masks)
    if len(masks) != len(frames):
        raise ValueError(f"masks must be one per frame: {len(masks)} masks, {len(frames)} frames")
    if "mask" in options or "progress" in options:
        raise ValueError("estimate_poses takes masks=[...] (one per frame) and no progress")

    def one(i: int) -> PoseEstimate:
        try:
            return estimate_pose(frames[i], model_points, mask=masks[i], **options)
        except ValueError as err:
            raise ValueError(f"frame {i}: {err}") from err

    if not frames:
        return []
    first = one(0)
    return [first, *in_pieces(one, [(i,) for i in range(1, len(frames))])]
