"""A BOP split's pose estimates scored as the BOP toolkit scores them (``eval_bop19_pose.py``:
6D localisation, VSD / MSSD / MSPD and their Average Recall).

For every image and object with targets (``BopSplit.targets``: the ``inst_count`` most visible
instances of BOP19's target list, or every instance), the ``inst_count`` highest-scoring
estimates of that object in that image are kept; each is scored against each target instance,
and, per metric and threshold, the estimates are matched greedily in order of decreasing
score, each to the not yet matched instance it fits best below the threshold. A target that no
estimate matches is missed. As in the toolkit, an estimate whose centre is a diameter or more
from the instance's has an infinite MSSD, and one whose bounding sphere's image does not
overlap the instance's has a VSD of 1 (nothing is rendered for it).

VSD renders the model at both poses with the library's ray caster (``jaxreg.synth.render``)
and compares them with the split's depth image; MSSD and MSPD use the model's vertices and
BOP's symmetry transforms (``BopModel``). Units are metres and pixels throughout.

A point model (``BopModel.mesh`` None, e.g. a YCB-Video split written by
:func:`jaxreg.io.ycbv_to_bop`) has no surface to render: its VSD is not scored (NaN), its
objects' AR is the mean of the MSSD and MSPD recalls, and ``BopScores.vsd_unavailable`` says so;
when any scored object is a point model, the split's VSD recall is NaN and its AR the same mean
of two.
"""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxreg.geometry.bop_metrics import (
    MSPD_REFERENCE_WIDTH,
    MSPD_THRESHOLDS,
    MSSD_THRESHOLDS,
    VSD_DELTA,
    VSD_TAUS,
    VSD_THRESHOLDS,
    BopRecall,
    mspd,
    mssd,
    vsd,
)
from jaxreg.io.bop import BopModel, BopResult, BopSplit, BopTarget
from jaxreg.synth.render import render

__all__ = ["BopScores", "TargetErrors", "bop_scores"]

_mssd, _mspd = jax.jit(mssd), jax.jit(mspd)
_vsd = jax.jit(vsd, static_argnames="normalized_by_diameter")


@dataclasses.dataclass(frozen=True, eq=False)
class TargetErrors:
    """One target's errors: the smallest any of its object's kept estimates in its image has
    against it (with one instance, the errors of the highest-scoring estimate).

    Attributes:
        target: the `BopTarget`.
        found: whether any estimate of its object in its image was kept.
        vsd: `(T,)` VSD per tau of `VSD_TAUS` (1 when not found, NaN for a point model).
        mssd: metres (inf when not found or a diameter away).
        mspd: pixels of the target's image (inf when not found).
    """

    target: BopTarget
    found: bool
    vsd: np.ndarray
    mssd: float
    mspd: float


@dataclasses.dataclass(frozen=True, eq=False)
class BopScores:
    """BOP's Average Recall of a split's estimates, overall and per object.

    Attributes:
        ar: the mean of `ar_vsd`, `ar_mssd` and `ar_mspd` (BOP19's score of a dataset); the
            mean of `ar_mssd` and `ar_mspd` when VSD is unavailable.
        ar_vsd, ar_mssd, ar_mspd: each metric's recall averaged over its thresholds (and, for
            VSD, its taus), over every target of the split; `ar_vsd` NaN when unavailable.
        per_object: `{obj_id: {"ar", "ar_vsd", "ar_mssd", "ar_mspd", "targets"}}`, the same
            over one object's targets (`targets` counts them).
        recall: the split's `BopRecall` (recall per threshold; `recall_vsd` NaN when VSD is
            unavailable).
        errors: one `TargetErrors` per target, in `split.targets()` order.
        vsd_unavailable: why VSD was not scored (the point models it needs a mesh for), or
            None when it was scored for every target.
    """

    ar: float
    ar_vsd: float
    ar_mssd: float
    ar_mspd: float
    per_object: dict[int, dict[str, float]]
    recall: BopRecall
    errors: list[TargetErrors]
    vsd_unavailable: str | None = None


def _depth(model: BopModel, camera_T_object: np.ndarray, intrinsics) -> np.ndarray:
    """The model's z-depth `(H, W)` at a pose (metres, NaN where it is not)."""
    return render([model.mesh], intrinsics, np.linalg.inv(camera_T_object)).depth


def _sphere_images_overlap(radius: float, t_a: np.ndarray, t_b: np.ndarray) -> bool:
    """Whether two spheres of `radius` centred at `t_a`, `t_b` (camera frame) overlap in the
    image, approximately: their centres' normalised projections are nearer than the sum of
    `radius / z` (the toolkit's test; no overlap when a centre has z = 0)."""
    if t_a[2] == 0 or t_b[2] == 0:
        return False
    gap = np.linalg.norm(t_a[:2] / t_a[2] - t_b[:2] / t_b[2])
    return bool(gap < radius * (1.0 / t_a[2] + 1.0 / t_b[2]))


def _pair_errors(split, model, instances, estimates):
    """`(E, K, T)` VSD, `(E, K)` MSSD and MSPD of `E` estimates against `K` instances."""
    scene_id, im_id = instances[0].scene_id, instances[0].im_id
    intrinsics = split.intrinsics(scene_id, im_id)
    K = np.asarray(intrinsics.K, np.float64)
    est = np.stack([r.camera_T_object for r in estimates])
    truth = np.stack([t.camera_T_object for t in instances])
    pairs = (est[:, None], truth[None])
    syms = model.symmetry_transforms
    mssd_e = np.asarray(_mssd(model.points, *pairs, syms), np.float64)
    mspd_e = np.asarray(_mspd(model.points, *pairs, syms, K), np.float64)
    centres = np.linalg.norm(est[:, None, :3, 3] - truth[None, :, :3, 3], axis=-1)
    mssd_e = np.where(centres < model.diameter, mssd_e, np.inf)
    vsd_e = np.ones((len(estimates), len(instances), len(VSD_TAUS)))
    if model.mesh is None:  # a point model: nothing to render
        return np.full_like(vsd_e, np.nan), mssd_e, mspd_e
    depth_test = split.depth(scene_id, im_id)
    rendered_truth = {}
    for i, e in enumerate(est):
        depth_est = None
        for j, t in enumerate(truth):
            if not _sphere_images_overlap(model.diameter / 2, e[:3, 3], t[:3, 3]):
                continue
            if depth_est is None:
                depth_est = _depth(model, e, intrinsics)
            if j not in rendered_truth:
                rendered_truth[j] = _depth(model, t, intrinsics)
            vsd_e[i, j] = _vsd(
                depth_est, rendered_truth[j], depth_test, K,
                delta=VSD_DELTA, taus=VSD_TAUS, diameter=model.diameter,
            )  # fmt: skip
    return vsd_e, mssd_e, mspd_e


def _kept(estimates: Sequence, count: int) -> list:
    """The `count` highest-scoring estimates (objects with a `score`), in decreasing score;
    equal scores keep their given order."""
    return sorted(estimates, key=lambda r: r.score, reverse=True)[:count]


def _greedy_hits(errors: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """`(K, C)`: whether each of `K` instances is matched at each of `C` thresholds, by the
    `E` estimates of `errors (E, K)` (rows in decreasing score), each taking the not yet
    matched instance with the smallest error below the threshold (the first on ties)."""
    hits = np.zeros((errors.shape[1], len(thresholds)), bool)
    for c, threshold in enumerate(thresholds):
        for row in errors:
            best, best_error = -1, threshold
            for k, error in enumerate(row):
                if not hits[k, c] and error < best_error:
                    best, best_error = k, error
            if best >= 0:
                hits[best, c] = True
    return hits


def bop_scores(split: BopSplit, results: Sequence[BopResult]) -> BopScores:
    """Score pose estimates of a split with BOP's VSD, MSSD, MSPD and Average Recall.

    Args:
        split: the dataset split (`jaxreg.io.read_bop`); its targets are what is scored.
        results: the estimates (`jaxreg.io.read_bop_results`, or the runner's); estimates of
            objects or images without targets are ignored, as the toolkit ignores them.

    Returns:
        `BopScores`. A split without targets raises `ValueError` (`read_bop` never returns
        one).
    """
    targets = split.targets()
    if not targets:
        raise ValueError("the split has no targets to score")
    groups: dict[tuple[int, int, int], list[int]] = defaultdict(list)
    for n, target in enumerate(targets):
        groups[(target.scene_id, target.im_id, target.obj_id)].append(n)
    by_key: dict[tuple[int, int, int], list[BopResult]] = defaultdict(list)
    for result in results:
        by_key[(int(result.scene_id), int(result.im_id), int(result.obj_id))].append(result)

    count = len(targets)
    vsd_hits = np.zeros((count, len(VSD_TAUS), len(VSD_THRESHOLDS)), bool)
    mssd_hits = np.zeros((count, len(MSSD_THRESHOLDS)), bool)
    mspd_hits = np.zeros((count, len(MSPD_THRESHOLDS)), bool)
    errors: list[TargetErrors | None] = [None] * count
    for key, members in groups.items():
        instances = [targets[n] for n in members]
        model = split.models[key[2]]
        kept = _kept(by_key.get(key, []), len(instances))
        if not kept:
            vsd_missed = np.full(len(VSD_TAUS), 1.0 if model.mesh is not None else np.nan)
            for n in members:
                errors[n] = TargetErrors(targets[n], False, vsd_missed, np.inf, np.inf)
            continue
        vsd_e, mssd_e, mspd_e = _pair_errors(split, model, instances, kept)
        width = split.intrinsics(key[0], key[1]).width
        mssd_hits[members] = _greedy_hits(mssd_e / model.diameter, MSSD_THRESHOLDS)
        scaled = mspd_e * (MSPD_REFERENCE_WIDTH / width)
        mspd_hits[members] = _greedy_hits(scaled, MSPD_THRESHOLDS)
        for tau in range(len(VSD_TAUS)):
            vsd_hits[members, tau] = _greedy_hits(vsd_e[:, :, tau], VSD_THRESHOLDS)
        for j, n in enumerate(members):
            errors[n] = TargetErrors(
                targets[n], True, vsd_e[:, j].min(axis=0), mssd_e[:, j].min(), mspd_e[:, j].min()
            )

    points_only = sorted(o for o in {t.obj_id for t in targets} if split.models[o].mesh is None)
    recall = _recall(vsd_hits, mssd_hits, mspd_hits, with_vsd=not points_only)
    per_object = {}
    for obj_id in sorted({t.obj_id for t in targets}):
        rows = [n for n, t in enumerate(targets) if t.obj_id == obj_id]
        with_vsd = obj_id not in points_only
        part = _recall(vsd_hits[rows], mssd_hits[rows], mspd_hits[rows], with_vsd=with_vsd)
        per_object[obj_id] = {**_ars(part), "targets": len(rows)}
    unavailable = None
    if points_only:
        unavailable = (
            f"objects {points_only} are point models (PLY without faces): VSD renders a mesh, so "
            "it is not scored, and AR is the mean of the MSSD and MSPD recalls"
        )
    return BopScores(
        **_ars(recall), per_object=per_object, recall=recall, errors=errors,
        vsd_unavailable=unavailable,
    )  # fmt: skip


def _recall(vsd_hits, mssd_hits, mspd_hits, *, with_vsd: bool) -> BopRecall:
    """`BopRecall.from_hits`, or without VSD: its recalls NaN and AR the mean of MSSD's and
    MSPD's."""
    recall = BopRecall.from_hits(vsd_hits, mssd_hits, mspd_hits)
    if with_vsd:
        return recall
    return BopRecall(
        ar=(recall.ar_mssd + recall.ar_mspd) / 2,
        ar_vsd=jnp.full_like(recall.ar_vsd, jnp.nan),
        ar_mssd=recall.ar_mssd,
        ar_mspd=recall.ar_mspd,
        recall_vsd=jnp.full_like(recall.recall_vsd, jnp.nan),
        recall_mssd=recall.recall_mssd,
        recall_mspd=recall.recall_mspd,
    )


def _ars(recall: BopRecall) -> dict[str, float]:
    return {
        "ar": float(recall.ar),
        "ar_vsd": float(recall.ar_vsd),
        "ar_mssd": float(recall.ar_mssd),
        "ar_mspd": float(recall.ar_mspd),
    }
