"""The pipeline on a BOP split: one `estimate_pose` per target, as BOP results.

`run_bop` estimates every target of its share of the split's images (image `i` of
`split.images` belongs to process `i % process_count`), with the target's visible mask
(mask_visib) as the segment when `use_masks` and the split has masks, else by the table route.
A target whose estimate makes no pose claim gets no row: BOP counts it as missed, as it counts
a missing estimate. The model is `MODEL_SAMPLES` points sampled on the object's mesh, or a point
model's own vertices (`BopModel.mesh` None). `gather_bop_results` collects every process's rows
on every process (`jax.distributed` processes; exact: the float64 rows travel as their bits).

Each estimate is converted to BOP's convention: `camera_T_object = inverse(base_T_camera) @
base_T_object`; its score is the fraction of the segment the model explains
(`PoseEstimate.inlier_fraction`), and its time the seconds spent on its whole image (frame
reading included), the same on every row of an image as BOP requires.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from jaxreg.io.bop import BopResult, BopSplit
from jaxreg.pipeline.estimate import estimate_pose
from jaxreg.synth import surface_points

__all__ = ["gather_bop_results", "run_bop"]

_FIELDS = 17  # scene_id, im_id, obj_id, score, R (9), t (3), time: float64 each


def run_bop(
    split: BopSplit,
    *,
    objects: Iterable[int] | None = None,
    use_masks: bool = True,
    process_index: int = 0,
    process_count: int = 1,
    progress: Callable[[int, int], object] | None = None,
    **options,
) -> list[BopResult]:
    """Estimate the pose of every target in this process's share of `split`'s images.

    Args:
        split: the dataset split (`jaxreg.io.read_bop`).
        objects: only the targets of these object ids (default all of the split's).
        use_masks: segment with each target's mask_visib when the split has it; False (or a
            split without masks) uses the table route, which finds one object per call.
        process_index, process_count: this process's share: images `process_index`,
            `process_index + process_count`, ... of `split.images`.
        progress: called as `progress(done, total)` after each of this share's images.
        **options: passed to `estimate_pose` (e.g. `num_starts`, `voxel_size`).

    Returns:
        This share's `BopResult`s, in image order, each image's in target order.
    """
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index must lie in 0 .. {process_count - 1}, got {process_index}")
    wanted = None if objects is None else {int(o) for o in objects}
    unknown = sorted((wanted or set()) - set(split.models))
    if unknown:
        raise ValueError(
            f"objects {unknown} have no targets in this split (it has {sorted(split.models)})"
        )
    points = {}
    images = split.images[process_index::process_count]
    results = []
    for done, (scene_id, im_id) in enumerate(images, start=1):
        start = time.perf_counter()
        frame = split.frame(scene_id, im_id)
        camera_T_base = np.linalg.inv(np.asarray(frame.base_T_camera.as_matrix(), np.float64))
        rows = []
        for target in split.targets(scene_id, im_id):
            if wanted is not None and target.obj_id not in wanted:
                continue
            model = split.models[target.obj_id]
            if target.obj_id not in points:
                points[target.obj_id] = (
                    model.points.astype(np.float32)
                    if model.mesh is None
                    else surface_points(model.mesh)
                )
            mask = split.mask(target) if use_masks else None
            if mask is not None and not mask.any():
                continue  # nothing of the object is visible: no estimate, a miss
            estimate = estimate_pose(
                frame, points[target.obj_id], mask=mask, symmetry=model.symmetry, **options
            )
            if estimate.pose is None:
                continue
            pose = camera_T_base @ np.asarray(estimate.pose.as_matrix(), np.float64)
            rows.append((target, pose, float(estimate.inlier_fraction)))
        seconds = time.perf_counter() - start
        results += [
            BopResult(t.scene_id, t.im_id, t.obj_id, score, pose[:3, :3], pose[:3, 3], seconds)
            for t, pose, score in rows
        ]
        if progress is not None:
            progress(done, len(images))
    return results


def _encode(results: Sequence[BopResult]) -> np.ndarray:
    rows = np.zeros((len(results), _FIELDS), np.float64)
    for k, r in enumerate(results):
        rows[k] = [r.scene_id, r.im_id, r.obj_id, r.score, *np.ravel(r.R), *np.ravel(r.t), r.time]
    return rows


def _decode(rows: np.ndarray) -> list[BopResult]:
    return [
        BopResult(
            int(r[0]),
            int(r[1]),
            int(r[2]),
            float(r[3]),
            r[4:13].reshape(3, 3).copy(),
            r[13:16].copy(),
            float(r[16]),
        )
        for r in rows
    ]


GATHER_TIMEOUT_MS = 24 * 3600 * 1000  # how long a process waits for the others' shares


def gather_bop_results(results: Sequence[BopResult]) -> list[BopResult]:
    """Every process's `results` on every process (call it in all of them), in image order
    (each image's rows in the order its process made them). One process: `results` as given.
    """
    import jax
    from jax.experimental import multihost_utils

    if jax.process_count() == 1:
        return list(results)
    # The processes finish their images minutes apart; the collectives' transport (gloo on a
    # CPU) gives up on a peer after 30 s, so they meet first at the coordination service's
    # barrier, which waits as long as the slowest share takes.
    from jax._src.distributed import global_state

    global_state.client.wait_at_barrier("jaxreg_gather_bop_results", GATHER_TIMEOUT_MS)
    rows = _encode(results)
    counts = np.asarray(multihost_utils.process_allgather(np.int32(len(rows))))
    padded = np.zeros((int(counts.max()), _FIELDS), np.float64)
    padded[: len(rows)] = rows
    # int32 views of the float64 bits: exact whatever jax_enable_x64 says
    bits = multihost_utils.process_allgather(padded.view(np.int32))
    shares = [
        np.asarray(share).view(np.float64)[:count]
        for share, count in zip(np.asarray(bits), counts, strict=True)
    ]
    gathered = _decode(np.concatenate(shares))
    return sorted(gathered, key=lambda r: (r.scene_id, r.im_id))
