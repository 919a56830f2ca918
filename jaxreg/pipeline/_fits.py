"""A candidate segment's fits and how they compare, for the register stage
(:mod:`jaxreg.pipeline._register_stage`):

- :func:`coarse_scores`: every candidate registered from many starts in one compiled call and
  scored at its best coarse pose that keeps its points within the model's span;
- :func:`joined_pieces` and :func:`twin_of`: the pieces of the winner's object, and the rival
  the winner cannot be told from (refined and probed beside it where the coarse scores come
  close);
- :func:`refit`: a segment's coarse poses refined and judged as the refinement judges its
  starts;
- :func:`frame_bounds`, :func:`keeps_within` and :func:`judged_beyond`: a pose against what the
  frame allows (the segment's span beyond the model, the table) and the evidence of the
  segment's points beyond the model (:mod:`jaxreg.pipeline._evidence`).

Conventions of :mod:`jaxreg.pipeline.estimate`: base-frame points, ``object_T_base`` wxyz_xyz
poses as ICP returns them; ``gates`` a segment's
:class:`~jaxreg.pipeline._register_stage.Tolerances`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxreg.core._threads import lane_pieces, split_lanes
from jaxreg.pipeline._answer import _distinct, _onto_table, _probe
from jaxreg.pipeline._coarse import (
    _Coarse,
    _coarse_problem,
    _score_candidates,
    _starts_in_pieces,
)
from jaxreg.pipeline._evidence import beyond_model, camera_depths, overhang, z_score
from jaxreg.pipeline._judge import (
    CONTESTED_WITHIN,
    EQUAL_WITHIN,
    TOLERANCE,
    _lowest,
    _near_model,
    _support,
    evidence_gap,
    fit_order,
    judged_fits,
    passes_gates,
    patch_count,
    sunk,
    underneath,
)
from jaxreg.pipeline._model import viewpoint
from jaxreg.pipeline._stages import _padded
from jaxreg.pipeline.records import Candidate, Segmented
from jaxreg.pipeline.settings import PipelineSettings

__all__ = [
    "Refit",
    "candidate_record",
    "coarse_scores",
    "frame_bounds",
    "joined_pieces",
    "judged_beyond",
    "keeps_within",
    "refit",
    "twin_of",
]


def joined_pieces(model, segmented: Segmented, chosen: int, pose: np.ndarray) -> list[int] | None:
    """On the table route, the winner's clusters (slot ``chosen``) and every cluster its
    coarse ``pose`` ``(7,)`` (object_T_base) explains (60% of its grid points within 1 cm of
    the model): pieces the clustering split off the object. ``None`` on the mask route."""
    if segmented.clusters is None:
        return None
    seg = segmented.clusters
    grid_points = np.asarray(seg.points)
    labels = np.asarray(seg.clusters.labels)
    sizes = np.asarray(seg.clusters.sizes)
    live = [k for k in range(len(sizes)) if sizes[k] > 0]
    members = labels >= 0  # the whole grid, non-members NaN: one shape for every frame
    points = np.where(members[..., None], grid_points, np.nan).astype(np.float32)
    near = np.asarray(_near_model(model.fine_grid, pose, points, np.float32(0.01)))
    near, member_labels = near[members], labels[members]
    group = segmented.candidates[chosen][0]
    return sorted({*group, *(k for k in live if near[member_labels == k].mean() >= 0.6)})


def twin_of(frame, model, segmented: Segmented, coarse, scored, joined, gates, settings, noise):
    """The slot of a candidate the winner (``scored[0]``) cannot be told from, or None.

    Rivals are the candidates that share no cluster with the winner nor with the pieces its pose
    explains (``joined``, :func:`joined_pieces`: parts of one object are no rivals) and whose coarse
    score, or share shown occlusion aside (:func:`_shown`), is within ``CONTESTED_WITHIN``
    standard errors of the winner's (or above it; :func:`evidence_gap` over the winner's
    ``PATCH`` cubes), in the order of ``scored``. Both are refined and probed
    (:func:`_rival_fit`); a rival that no fit of the model passes the answer's gates and
    evidence on is no twin (a coarse score on 128 points says little: a mug's coarse pose fits a
    brick's corner), and one that does is a twin unless the winner's fit keeps to it and is
    better by more than ``EQUAL_WITHIN`` both in score and in how well the model fits what the
    segment shows (:func:`_clearly_better`), or the rival's fits all go beyond it where its
    coarse span did too. A coarse pose a few degrees off (a mug's handle where the image sees
    through it) can put the object behind a neighbour that only resembles it, or make its
    segment seem to span beyond the model. Refined fits never make a rival the winner: a failed
    search on the object itself (a handle ICP cannot find) would hand the win to the neighbour.

    A candidate that spans beyond the model (ranked after those that keep within it: the
    object merged with a neighbour it touches, or a larger object of a similar shape) is a
    rival without refinement when the lower bounds (:func:`_lower_bound`, over its own
    ``PATCH`` cubes) of its coarse score and of its share shown are both above the winner's:
    a fragment whose pose hides most of the model is not claimed while the model fits a
    cluster holding a neighbour clearly better; a whole view of the object beside a larger
    look-alike is.
    """
    candidates = segmented.candidates
    score, *_, chosen = scored[0]
    group = set(candidates[chosen][0]) | set(joined or ())
    patches = patch_count(candidates[chosen][1])
    draws = np.random.default_rng(2)  # the stage's own draws stay as without a rival
    eye = viewpoint(model, frame)
    fits = {}

    def fit(slot):
        if slot not in fits:
            fits[slot] = _rival_fit(
                frame, model, segmented.plane, candidates[slot][1], np.asarray(coarse.poses[slot]),
                float(coarse.explained[slot, 0]), gates, settings, noise, draws, eye,
            )  # fmt: skip
        return fits[slot]

    ours_within = scored[0][3][0] <= gates.max_overhang
    for item in scored[1:]:
        other, *_, bounds, slot = item
        if group & set(candidates[slot][0]):
            continue
        within = bounds[0] <= gates.max_overhang
        if ours_within and not within:  # its evidence's lower bounds against the winner's
            count = patch_count(candidates[slot][1])
            lower = (_lower_bound(other, count), _lower_bound(_shown(item), count))
            if lower[0] > score and lower[1] > _shown(scored[0]):
                return slot
        gap = min(
            evidence_gap([other], np.ones(1), score, 1.0, patches)[0],
            evidence_gap([_shown(item)], np.ones(1), _shown(scored[0]), 1.0, patches)[0],
        )
        if not gap <= CONTESTED_WITHIN:
            continue
        ours, theirs = fit(chosen), fit(slot)
        if not theirs[3] or not (within or theirs[2]):
            continue
        if not (ours[2] and _clearly_better(ours[:2], theirs[:2], patches)):
            return slot
    return None


def _shown(scored) -> float:
    """A coarse candidate's ``(score, explained, contradicted, ...)`` (:func:`coarse_scores`) as the
    share of its points the model explains times the share of the judged model surface not
    seen through, occlusion aside: an object half hidden behind a neighbour scores low for
    the view alone, and is as good a rival as a fragment fully in view."""
    score, explained, contradicted = scored[:3]
    confirmed = score / max(explained, 1e-9)
    return explained * confirmed / max(confirmed + contradicted, 1e-9)


def _clearly_better(fit, other, patches: int) -> bool:
    """Whether ``fit`` ``(score, shown)`` (:func:`_rival_fit`) is better than ``other``'s by
    more than ``EQUAL_WITHIN`` standard errors (:func:`evidence_gap` over ``patches``) both
    in score and in ``shown``: a segment partly hidden by a neighbour or seen edge-on scores
    lower for the view alone; only the image seeing through the model, or points the model
    does not explain, tell a different object. Residuals are not compared: segments at
    different depths differ in noise."""
    return all(
        evidence_gap([theirs], np.ones(1), ours, 1.0, patches)[0] > EQUAL_WITHIN
        for ours, theirs in zip(fit, other, strict=True)
    )


def _rival_fit(frame, model, plane, points, poses, explained, gates, settings, noise, rng, eye):
    """A candidate's best fit ``(score, shown, within, fits)``: its coarse poses refined
    (:func:`refit`), and the best of them probed as an answer is
    (:func:`~jaxreg.pipeline._answer._probe`: a mug whose coarse poses all put the handle where
    the image sees through it may find it); the best one's score, ``shown``, the share of the
    segment it explains times the share of the judged model surface not seen through (occlusion
    aside), and whether that fit keeps to what the frame allows (:func:`frame_bounds`,
    :func:`keeps_within`, placed on the table where it rests on it). The best is among the fits that
    keep to it where there are any: a mug turned about its axis spans its handle beyond the
    model. ``fits``: whether any of its refined or probed fits passes the gates an answer must
    pass (residual, explained, confirmed and contradicted shares), and the best one the
    evidence an answer must on its ``points`` (:func:`~jaxreg.pipeline._evidence.beyond_model`,
    its runs-on count in the segment grid's cells: the share explained, the span and the
    surface running on past the model): a segment that no fit of the model passes is no rival,
    however its coarse score compares (a mug's fit on a brick explains its top and its sides
    run on)."""
    fit = refit(frame, model, plane, points, poses, explained, gates, settings, noise, rng, eye)
    first = fit.ranked[:1]
    best = np.asarray(fit.results.pose.wxyz_xyz[first[0]])
    poses, scores, rmses, passes, seen = _probe(
        frame, plane, model, fit.source, best, fit.trim, noise, gates.distances, gates.max_rmse,
        eye, settings,
    )  # fmt: skip
    first_passes = passes_gates(
        np.asarray(fit.results.inlier_fraction)[first], fit.rmses[first], fit.seen[first],
        gates.max_rmse, settings.register,
    )  # fmt: skip
    poses = np.concatenate([_onto_table(model, best[None], plane, settings)[0], poses])
    seen = np.concatenate([fit.seen[first], seen]).astype(np.float64)
    scores = np.concatenate([fit.scores[first], scores])
    rmses = np.concatenate([fit.rmses[first], rmses])
    passes = np.concatenate([first_passes, passes])
    within = np.array(
        [keeps_within(frame_bounds(model, plane, pose, points), gates) for pose in poses]
    )
    kept = np.flatnonzero(within) if within.any() else np.arange(len(poses))
    top = kept[fit_order(scores[kept], rmses[kept])[0]]
    # score = explained * confirmed / judged, so explained * confirmed / (confirmed +
    # contradicted) = score * judged / (confirmed + contradicted)
    shown = scores[top] * seen[top, :3].sum() / max(seen[top, :2].sum(), 1.0)
    fits = bool(passes.any())
    if fits:  # the evidence an answer must pass, on the candidate's grid points
        depth = float(np.median(camera_depths(frame, points)))
        spacing = depth * settings.segment.stride / float(frame.intrinsics.fx)
        cell = max(settings.voxel_size, spacing)
        beyond = judged_beyond(
            frame, model, plane, poses[top], poses[top], points, gates, noise, settings, cell
        )
        fits = not beyond.problems
    return float(scores[top]), float(shown), bool(within[top]), fits


def judged_beyond(
    frame, model, plane, answer, refined, points, gates, noise, settings, cell, masked=(None, 0)
):
    """:func:`~jaxreg.pipeline._evidence.beyond_model` of the segment ``points`` ``(N, 3)``
    at the answer ``answer`` ``(7,)`` (object_T_base, placed on the table where it rests) and
    ICP's ``refined`` pose ``(7,)``, judged at the refinement's final distance, the segment's
    ``gates`` and the register settings' false-refusal rate, the runs-on count taken in
    ``cell``-sized cells (metres: the lift's voxels, or a candidate grid's spacing);
    ``masked``: a caller's mask's region ``(H, W)`` and the pixels of its border that may hold
    its neighbours (``(None, 0)`` for clusters)."""
    r = settings.register
    return beyond_model(
        frame, model, plane, answer, refined, points, float(gates.distances[-1]), noise,
        z_score(r.false_refusal), r.min_inlier_fraction, cell,
        None if plane is None else _lowest(model, plane, answer), *masked,
    )  # fmt: skip


@dataclasses.dataclass(frozen=True, eq=False)
class Refit:
    """A segment's coarse poses refined and judged (:func:`refit`): the padded ``source``
    ``(max_points, 3)``, the ``trim`` fraction, the number of ``starts``, ICP's ``results``
    ``(S,)``, their ``scores``, ``rmses`` and image counts ``seen`` (:func:`judged_fits`),
    and the indices ``ranked`` best first (:func:`fit_order`; see :func:`refit`)."""

    source: np.ndarray
    trim: np.float32
    starts: int
    results: object
    scores: np.ndarray
    rmses: np.ndarray
    seen: np.ndarray
    ranked: np.ndarray


def refit(frame, model, plane, points, poses, explained, gates, settings, noise, rng, eye):
    """The best distinct of a segment's coarse ``poses`` ``(K, 7)`` (object_T_base, best
    first) refined on its ``points`` ``(N, 3)`` (base frame; subsampled to the register
    settings' ``max_points``), trimmed to the share its best coarse pose ``explained``
    (0.6-0.95), and judged as the refinement judges its starts (``eye`` the ICP viewpoint);
    the fits that keep to what the frame allows (:func:`keeps_within`, once moved onto the table
    where they rest on it, as answers are) rank before the others."""
    s = settings.register
    source = _padded(points, s.max_points, rng)
    picks = _distinct(poses, s.refined_starts)
    trim = np.float32(np.clip(explained, 0.6, 0.95))  # an argument: one program for all
    results = _starts_in_pieces(
        source, model.points, model.normals, model.fine_grid, poses[picks], gates.distances,
        trim, 30, eye, per_piece=2,
    )  # fmt: skip
    fitted = np.asarray(results.pose.wxyz_xyz)
    scores, rmses, seen = judged_fits(frame, plane, fitted, model.points, results, noise)
    ranked = fit_order(scores, rmses)
    if len(ranked) > 1:  # (one fit ranks first whatever it keeps to)
        placed, _ = _onto_table(model, fitted, plane, settings)  # as answers are placed
        within = np.array(
            [keeps_within(frame_bounds(model, plane, p, points), gates) for p in placed]
        )
        ranked = np.concatenate([ranked[within[ranked]], ranked[~within[ranked]]])
    return Refit(source, trim, len(picks), results, scores, rmses, seen, ranked)


def coarse_scores(frame, plane, model, settings: PipelineSettings, clouds, rng, noise, gates):
    """Coarse registration of the candidate ``clouds`` (each ``(N, 3)``, base frame) in one
    compiled call, and each one's evidence, best first: tuples ``(score, explained,
    contradicted, bounds, slot)`` (:func:`frame_bounds`) of its best coarse pose that keeps its
    points within ``max_overhang`` of the model's span (a mug turned about its axis spans its
    handle beyond the model), or of its best pose when none does; that pose leads the
    candidate's poses of the returned ``_Coarse``. A candidate with no such pose (a larger
    object of a similar shape, or a span that cannot be measured) ranks after those with one;
    among the others the higher lower bound of the score ranks first (:func:`_lower_bound`).
    The heights are not judged here: a coarse pose may sit several millimetres off the table (an
    open tray's). ``noise``: the camera's ``DepthNoise`` (the image's judgement allows 4 sigma_z
    at each depth)."""
    s = settings.register
    padded = np.full((settings.segment.max_candidates, s.coarse_points, 3), np.nan, np.float32)
    for i, cloud in enumerate(clouds):
        padded[i] = _padded(cloud, s.coarse_points, rng)
    used = np.arange(settings.segment.max_candidates) < len(clouds)
    problem, *rounds = _coarse_problem(
        model, s.coarse_points, settings.coarse_distances, (s.coarse_screen, s.coarse_first)
    )
    # one concurrent call per core, each on every pieces-th slot (the used slots come first,
    # so each call gets its share of them), the slots padded with unused ones to fill them
    pieces = lane_pieces(len(clouds), per_piece=1)
    slots = -(-len(used) // pieces) * pieces
    extra = np.full((slots - len(used),) + padded.shape[1:], np.nan, padded.dtype)
    padded = np.concatenate([padded, extra])
    used = np.concatenate([used, np.zeros(slots - len(used), bool)])
    order = np.concatenate([np.arange(k, slots, pieces) for k in range(pieces)])
    coarse = split_lanes(
        lambda part: _score_candidates(
            frame, plane, problem, tuple(rounds), model.fine_grid, padded[part], used[part],
            model.points, model.screen, model.axes, TOLERANCE, noise.coefficients,
            gates.distances[-1], s.num_starts, s.resting_yaws, s.coarse_survivors,
            s.coarse_keep,
        ),
        order, pieces,
    )  # fmt: skip
    back = np.argsort(order)
    poses, explained, seen = (
        np.array(a[back]) for a in (coarse.poses, coarse.explained, coarse.visibility)
    )
    scored = []
    for i, cloud in enumerate(clouds):
        spans = [overhang(model, pose, cloud).max() for pose in poses[i]]
        first = next((k for k, span in enumerate(spans) if span <= gates.max_overhang), 0)
        order = [first, *(k for k in range(len(spans)) if k != first)]
        poses[i], explained[i], seen[i] = poses[i, order], explained[i, order], seen[i, order]
        confirmed, contradicted, _ = _support(seen[i, 0])
        score = float(explained[i, 0]) * confirmed
        bounds = frame_bounds(model, plane, poses[i, 0], cloud)
        scored.append((score, float(explained[i, 0]), contradicted, bounds, i))
    # larger objects (or an unmeasurable span) last
    scored.sort(
        key=lambda item: (
            not item[3][0] <= gates.max_overhang,
            -_lower_bound(item[0], patch_count(clouds[item[4]])),
        )
    )
    return _Coarse(poses, explained, seen), scored


def _lower_bound(score: float, patches: int) -> float:
    """A coarse ``score`` (a share) less ``EQUAL_WITHIN`` standard errors of a share over
    ``patches`` independent patches (at least that of a share of 0.1, as
    :func:`~jaxreg.pipeline._judge.evidence_gap` weighs them): a few dozen points of a
    fragment fit any model as well as a whole view does, and say far less."""
    return score - EQUAL_WITHIN * np.sqrt(max(score * (1.0 - score), 0.09) / max(patches, 1))


def frame_bounds(model, plane, object_T_base: np.ndarray, points: np.ndarray) -> np.ndarray:
    """How far the pose ``object_T_base`` ``(7,)`` goes beyond what the frame allows (metres,
    ``(3,)``): the segment ``points``' largest span beyond the model
    (:func:`~jaxreg.pipeline._evidence.overhang`; NaN where it cannot be measured), the model's
    depth in the table (:func:`~jaxreg.pipeline._judge.sunk`) and the segment's reach below
    the model (:func:`~jaxreg.pipeline._judge.underneath`)."""
    return np.array([
        overhang(model, object_T_base, points).max(),
        sunk(model, plane, object_T_base),
        underneath(model, plane, object_T_base, points),
    ])  # fmt: skip


def keeps_within(bounds: np.ndarray, gates) -> bool:
    """Whether :func:`frame_bounds` ``(3,)`` stay within the ``gates``: the span within
    ``max_overhang``, the two heights within ``max_below`` (NaN never)."""
    return bool(bounds[0] <= gates.max_overhang and np.all(bounds[1:] <= gates.max_below))


def candidate_record(clusters, score, explained, contradicted, bounds) -> Candidate:
    return Candidate(
        clusters=clusters,
        score=round(score, 3),
        explained=round(explained, 3),
        contradicted=round(contradicted, 3),
        overhang_mm=round(float(bounds[0]) * 1e3, 1),
        sunk_mm=round(float(bounds[1]) * 1e3, 1),
        underneath_mm=round(float(bounds[2]) * 1e3, 1),
    )
