"""The register stage of :func:`jaxreg.estimate_pose`, in two parts around the lift.

:func:`coarse_search` (before the lift): every candidate segment registered into the model from
many starts in one compiled call (:func:`jaxreg.pipeline._coarse._score_candidates`) and scored
by the fraction of its points the model explains times the share of the model's camera-facing
surface the depth image confirms, at its best coarse pose that keeps its points within the
model's span; the best candidate wins, those with no such pose last. On the table route the
clusters its coarse pose explains (60% of their points within 1 cm) join it first: pieces of one
object are no rivals. A candidate sharing no cluster with it whose coarse score is as good
within the frame's noise is a twin (refused, naming both, since depth cannot tell which one is
meant); one whose coarse score comes close is refined and probed beside the winner, and is a
twin too unless the winner's refined fit is clearly better (:func:`_twin`).

:func:`refine_stage` (after it): the winner's best distinct coarse poses refined on the lifted
points, ranked by inlier fraction times the confirmed share (those that keep to what the frame
allows first), the answer settled on the table and probed (:mod:`jaxreg.pipeline._answer`), the
checks that refuse a model that is not there, and the pose's error budget
(:mod:`jaxreg.pipeline._error_sources`).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from jaxlie import SE3

from jaxreg.core._threads import lane_pieces, split_lanes
from jaxreg.pipeline._answer import (
    _alternatives,
    _carried,
    _distinct,
    _onto_table,
    _probe,
    _rest,
)
from jaxreg.pipeline._coarse import (
    _Coarse,
    _coarse_problem,
    _score_candidates,
    _starts_in_pieces,
)
from jaxreg.pipeline._colour import colour_match, other_colour
from jaxreg.pipeline._error_sources import _pixels, mismatch_sigma, pose_budget
from jaxreg.pipeline._evidence import (
    LOCAL_TERMS,
    beyond_model,
    camera_depths,
    height_tests,
    overhang,
    z_score,
)
from jaxreg.pipeline._judge import (
    CONTESTED_WITHIN,
    EQUAL_WITHIN,
    NOISE_SIGMAS,
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
from jaxreg.pipeline._stages import _Failed, _padded
from jaxreg.pipeline.records import (
    Candidate,
    CoarseSearch,
    LiftedSegment,
    MeasuredView,
    RegisterRecord,
    Registration,
    Segmented,
)
from jaxreg.pipeline.segment import cluster_mask
from jaxreg.pipeline.settings import PipelineSettings
from jaxreg.registration.icp import ICPStatus

__all__ = ["coarse_search", "refine_stage"]

# Final ICP statuses that leave a pose to judge (the iteration bound leaves the last step's
# pose); degenerate geometry passes too when a symmetry is given (its free directions).
_USABLE = (ICPStatus.success, ICPStatus.max_iterations)


# A fit's residual may be this many times the one the depth noise, the model's sampling and
# the model-sensor mismatch explain (their RMS sum).
RESIDUAL_FACTOR = 1.5


@dataclasses.dataclass(frozen=True)
class Tolerances:
    """The register stage's distances and gates for one segment, from the depth noise at the
    segment's depth and the model's sampling (:func:`tolerances`).

    Attributes:
        distances: ``(30,)`` float32 the refinement's correspondence distances (metres, 15 mm
            down to the final one).
        max_rmse: the largest inlier RMSE of a fit (metres).
        max_overhang: how far the segment may span beyond the model (metres).
        sigma_z: the depth noise's standard deviation at the segment's depth (metres).
        max_below: how far the model may reach into the table, or the segment below the
            model (metres): ``max_overhang`` or ``NOISE_SIGMAS`` (4) ``sigma_z``, whichever is
            larger (both measure against a plane fitted to noisy depth, as the image's
            judgement does).
    """

    distances: np.ndarray
    max_rmse: float
    max_overhang: float
    sigma_z: float
    max_below: float


def tolerances(model, noise, depth: float, settings: PipelineSettings) -> Tolerances:
    """The :class:`Tolerances` of a segment ``depth`` metres from the camera (its median).

    With ``sigma_z`` the depth noise there and the model's sampling (``rms``, ``gap``: how
    far a surface point lies from the nearest model point, :func:`~jaxreg.pipeline._model.
    _sampling`): the final correspondence distance reaches a point ``3 sigma_z`` off the
    surface in the model's widest gap (``hypot(gap, 3 sigma_z)``, at least 1.5 voxels, the
    measured points' own spacing, at most 15 mm); a fit's residual may be ``RESIDUAL_FACTOR``
    times ``sqrt(rms^2 + sigma_z^2 + mismatch^2)`` (:func:`~jaxreg.pipeline._error_sources.
    mismatch_sigma`; ``max_inlier_rmse`` when set); the segment may span ``max_overhang``
    beyond the model (its 2% and 98% quantiles hold the noise's tails: a partial view of a 10%
    larger box reaches only a few millimetres beyond)."""
    r = settings.register
    sigma = float(np.polynomial.polynomial.polyval(depth, np.asarray(noise.coefficients)))
    rms, gap = model.sampling
    final = min(max(float(np.hypot(gap, 3 * sigma)), 1.5 * settings.voxel_size), 0.015)
    if final == 1.5 * settings.voxel_size:
        distances = settings.fine_distances
    else:
        distances = np.geomspace(0.015, final, 30).astype(np.float32)
    expected = float(np.sqrt(rms**2 + sigma**2 + mismatch_sigma(model) ** 2))
    max_rmse = RESIDUAL_FACTOR * expected if r.max_inlier_rmse is None else r.max_inlier_rmse
    max_below = max(r.max_overhang, NOISE_SIGMAS * sigma)
    return Tolerances(distances, max_rmse, r.max_overhang, sigma, max_below)


def coarse_search(
    frame, model, segmented: Segmented, settings: PipelineSettings, noise, rng
) -> CoarseSearch:
    """The winner among ``segmented``'s candidates and its coarse poses (see the module
    docstring); ``noise`` is the camera's ``DepthNoise`` (base frame), ``rng`` the numpy
    Generator that subsamples the candidates."""
    start = time.perf_counter()
    clouds = [cloud for _, cloud in segmented.candidates]
    depth = float(np.median(camera_depths(frame, np.concatenate(clouds))))
    gates = tolerances(model, noise, depth, settings)
    coarse, scored = _score(frame, segmented.plane, model, settings, clouds, rng, noise, gates)
    _, explained, *_, chosen = scored[0]
    poses = np.asarray(coarse.poses[chosen])  # object_T_base per start, best first
    candidates = [_candidate(list(segmented.candidates[i][0]), *rest) for *rest, i in scored]
    r = settings.register
    starts = r.num_starts + 4 + 6 * r.resting_yaws
    joined = _joined(model, segmented, chosen, poses[0])
    twin = _twin(frame, model, segmented, coarse, scored, joined, gates, settings, noise)
    if twin is not None:
        groups = (segmented.candidates[chosen], segmented.candidates[twin])
        centres = np.stack([np.mean(cloud, axis=0) for _, cloud in groups])
        places = [
            f"clusters {list(group)} at pixel ({col}, {row})"
            for (group, _), (row, col) in zip(groups, _pixels(frame, centres), strict=True)
        ]
        merged = next(item[3][0] for item in scored if item[4] == twin) > gates.max_overhang
        raise _Failed(
            "register",
            (
                f"the model fits {places[0]}, and part of {places[1]} fits it better, which "
                "spans beyond the model (the object touching a neighbour, or a larger object "
                "of a similar shape)"
                if merged
                else f"two separate segments fit the model equally well ({'; '.join(places)})"
            )
            + ": the depth cannot tell which is the object; give pixel=, box= or mask= to say "
            "which",
            RegisterRecord(
                ms=0.0, starts=starts, candidates=candidates,
                coarse_kept_starts=int(poses.shape[0]),
            ).with_ms(start),  # fmt: skip
        )
    region = segmented.mask
    if joined is not None:
        region = cluster_mask(segmented.clusters, joined, frame.depth.shape)
        if segmented.bounds is not None:
            region = region & segmented.bounds
        if segmented.palette is not None:
            region = _painted(frame, region, segmented.palette, settings.segment.color_tolerance)
    record = RegisterRecord(
        ms=0.0, starts=starts, candidates=candidates,
        coarse_kept_starts=int(poses.shape[0]),
        chosen_clusters=None if joined is None else list(joined),
    )  # fmt: skip
    border = settings.segment.mask_border if segmented.clusters is None else 0
    return CoarseSearch(region, poses, explained, gates, record.with_ms(start), border)


def _painted(frame, region: np.ndarray, palette: np.ndarray, tolerance: float) -> np.ndarray:
    """``region`` ``(H, W)`` without its pixels of another colour than the model's
    (:func:`~jaxreg.pipeline._colour.other_colour`, in the region's bounding box, one-pixel
    rims aside): a touching neighbour of another paint that a cluster or its footprint
    holds."""
    rows, cols = np.nonzero(region)
    if not len(rows):
        return region
    box = np.s_[rows.min() : rows.max() + 1, cols.min() : cols.max() + 1]
    judged, match = colour_match(np.asarray(frame.rgb)[box], palette, tolerance)
    painted = region.copy()
    painted[box] &= ~other_colour(judged, match, region[box], rim=1)
    return painted


def _joined(model, segmented: Segmented, chosen: int, pose: np.ndarray) -> list[int] | None:
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


def _twin(frame, model, segmented: Segmented, coarse, scored, joined, gates, settings, noise):
    """The slot of a candidate the winner (``scored[0]``) cannot be told from, or None.

    Rivals are the candidates that share no cluster with the winner nor with the pieces its pose
    explains (``joined``, :func:`_joined`: parts of one object are no rivals) and whose coarse
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
    """A coarse candidate's ``(score, explained, contradicted, ...)`` (:func:`_score`) as the
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
    (:func:`_refit`), and the best of them probed as an answer is
    (:func:`~jaxreg.pipeline._answer._probe`: a mug whose coarse poses all put the handle where
    the image sees through it may find it); the best one's score, ``shown``, the share of the
    segment it explains times the share of the judged model surface not seen through (occlusion
    aside), and whether that fit keeps to what the frame allows (:func:`_bounds`,
    :func:`_within`, placed on the table where it rests on it). The best is among the fits that
    keep to it where there are any: a mug turned about its axis spans its handle beyond the
    model. ``fits``: whether any of its refined or probed fits passes the gates an answer must
    pass (residual, explained, confirmed and contradicted shares), and the best one the
    evidence an answer must on its ``points`` (:func:`~jaxreg.pipeline._evidence.beyond_model`,
    its runs-on count in the segment grid's cells: the share explained, the span and the
    surface running on past the model): a segment that no fit of the model passes is no rival,
    however its coarse score compares (a mug's fit on a brick explains its top and its sides
    run on)."""
    fit = _refit(frame, model, plane, points, poses, explained, gates, settings, noise, rng,
                 eye)  # fmt: skip
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
        [_within(_bounds(model, plane, pose, points), gates) for pose in poses]
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
        beyond = _beyond(frame, model, plane, poses[top], poses[top], points, gates, noise,
                         settings, cell)  # fmt: skip
        fits = not beyond.problems
    return float(scores[top]), float(shown), bool(within[top]), fits


def _beyond(frame, model, plane, answer, refined, points, gates, noise, settings, cell,
            masked=(None, 0)):  # fmt: skip
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
class _Refit:
    """A segment's coarse poses refined and judged (:func:`_refit`): the padded ``source``
    ``(max_points, 3)``, the ``trim`` fraction, the number of ``starts``, ICP's ``results``
    ``(S,)``, their ``scores``, ``rmses`` and image counts ``seen`` (:func:`judged_fits`),
    and the indices ``ranked`` best first (:func:`fit_order`; see :func:`_refit`)."""

    source: np.ndarray
    trim: np.float32
    starts: int
    results: object
    scores: np.ndarray
    rmses: np.ndarray
    seen: np.ndarray
    ranked: np.ndarray


def _refit(frame, model, plane, points, poses, explained, gates, settings, noise, rng, eye):
    """The best distinct of a segment's coarse ``poses`` ``(K, 7)`` (object_T_base, best
    first) refined on its ``points`` ``(N, 3)`` (base frame; subsampled to the register
    settings' ``max_points``), trimmed to the share its best coarse pose ``explained``
    (0.6-0.95), and judged as the refinement judges its starts (``eye`` the ICP viewpoint);
    the fits that keep to what the frame allows (:func:`_within`, once moved onto the table
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
            [_within(_bounds(model, plane, p, points), gates) for p in placed]
        )
        ranked = np.concatenate([ranked[within[ranked]], ranked[~within[ranked]]])
    return _Refit(source, trim, len(picks), results, scores, rmses, seen, ranked)


def _score(frame, plane, model, settings: PipelineSettings, clouds, rng, noise, gates):
    """Coarse registration of the candidate ``clouds`` (each ``(N, 3)``, base frame) in one
    compiled call, and each one's evidence, best first: tuples ``(score, explained,
    contradicted, bounds, slot)`` (:func:`_bounds`) of its best coarse pose that keeps its
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
        bounds = _bounds(model, plane, poses[i, 0], cloud)
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


def _bounds(model, plane, object_T_base: np.ndarray, points: np.ndarray) -> np.ndarray:
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


def _within(bounds: np.ndarray, gates: Tolerances) -> bool:
    """Whether :func:`_bounds` ``(3,)`` stay within the ``gates``: the span within
    ``max_overhang``, the two heights within ``max_below`` (NaN never)."""
    return bool(bounds[0] <= gates.max_overhang and np.all(bounds[1:] <= gates.max_below))


def _candidate(clusters, score, explained, contradicted, bounds) -> Candidate:
    return Candidate(
        clusters=clusters,
        score=round(score, 3),
        explained=round(explained, 3),
        contradicted=round(contradicted, 3),
        overhang_mm=round(float(bounds[0]) * 1e3, 1),
        sunk_mm=round(float(bounds[1]) * 1e3, 1),
        underneath_mm=round(float(bounds[2]) * 1e3, 1),
    )



def refine_stage(
    frame, model, coarse: CoarseSearch, lifted: LiftedSegment, plane, settings: PipelineSettings,
    noise, symmetry, calibration, rng, carried: MeasuredView | None = None,
) -> Registration:  # fmt: skip
    """The best distinct coarse poses refined on the lifted points and judged (see the
    module docstring). Raises ``_Failed`` when the evidence says the model is not there.
    ``carried``: what a previous frame measured of the view (:func:`jaxreg.track`), used
    instead of probing the answer and re-registering perturbed segments again."""
    coarse_poses, coarse_fraction = coarse.poses, coarse.explained
    mask, points = lifted.mask, lifted.points
    s = settings.register
    gates = coarse.tolerances
    fine_distances = gates.distances
    start = time.perf_counter()
    eye = viewpoint(model, frame)
    patches = patch_count(points)

    def answer_from(starts):
        fit = _refit(frame, model, plane, points, starts, coarse_fraction, gates, settings,
                     noise, rng, eye)  # fmt: skip
        answers, contact, lowest = _rest(
            fit.source, model, fit.results, fit.ranked[0], plane, fit.trim, fine_distances,
            settings, eye,
        )  # fmt: skip
        best = int(fit.ranked[0])
        if carried is not None:
            found = _carried(carried, answers, best, fit.scores, fit.rmses, patches, symmetry)
            return fit, answers, contact, lowest, found, answers[:0]
        found, leads = _alternatives(
            frame, plane, model, fit.source, answers, best, fit.scores, fit.rmses, patches,
            fit.trim, noise, fine_distances, gates.max_rmse, eye, symmetry, settings,
        )  # fmt: skip
        return fit, answers, contact, lowest, found, leads

    def kept(turns, contact):  # a turn must rest as the answer does: one floating fits freely
        _, restings = _onto_table(model, turns, plane, settings)
        return [
            (resting is not None or contact is None)
            and _within(_bounds(model, plane, turn, points), gates)
            for turn, resting in zip(turns, restings, strict=True)
        ]

    def beyond_at(answer, refined):
        return _beyond(frame, model, plane, answer, refined, points, gates, noise, settings,
                       settings.voxel_size, (coarse.region, coarse.border))  # fmt: skip

    fit, answers, contact, lowest, found, leads = answer_from(coarse_poses)
    within = kept(leads, contact)
    if any(within):  # a turn of the answer fits clearly better, as it rests: answer from it
        lead = leads[within.index(True)]
        fit, answers, contact, lowest, found, _ = answer_from(
            np.concatenate([lead[None], coarse_poses])
        )
    answer = answers[fit.ranked[0]]
    beyond = beyond_at(answer, np.asarray(fit.results.pose.wxyz_xyz[fit.ranked[0]]))
    if beyond.problems and found.equivalent:
        # a turn that fits as well leaves no surface beyond the model: the evidence picks it
        turns = np.stack([np.asarray(e.pose.inverse().wxyz_xyz) for e in found.equivalent])
        clean = next((
            turn for turn, ok in zip(turns, kept(turns, contact), strict=True)
            if ok and not beyond_at(turn, turn).problems
        ), None)  # fmt: skip
        if clean is not None:
            fit, answers, contact, lowest, found, _ = answer_from(clean[None])
            answer = answers[fit.ranked[0]]
            beyond = beyond_at(answer, np.asarray(fit.results.pose.wxyz_xyz[fit.ranked[0]]))
    trim, results, rmses, seen, ranked = fit.trim, fit.results, fit.rmses, fit.seen, fit.ranked
    fractions = np.asarray(results.inlier_fraction)
    best = results[int(ranked[0])]
    fraction, rmse = float(fractions[ranked[0]]), float(rmses[ranked[0]])
    confirmed, contradicted, judged = _support(seen[ranked[0]])
    low = sunk(model, plane, answers[ranked[0]])
    under = underneath(model, plane, answers[ranked[0]], points)
    spread_mm, spread_deg = (float(x) for x in found.spread)
    matched = fraction > 0 and rmse < 1.0  # no match leaves ICP's empty-sum residual
    record = dataclasses.replace(
        coarse.record,
        refined_starts=fit.starts,
        trim_fraction=round(float(trim), 3),
        iterations=int(best.iterations),
        icp_status=str(best.status_message()),
        inlier_rmse_mm=round(rmse * 1e3, 3) if matched else None,
        inlier_fraction=round(fraction, 3),
        equally_good_starts=int(found.equal_starts.sum()),
        equally_good_probes=int(found.equal_probes.sum()),
        start_agreement_mm=round(spread_mm * 1e3, 3),
        start_agreement_deg=round(spread_deg, 3),
        model_confirmed=round(confirmed, 3) if judged else None,
        model_contradicted=round(contradicted, 3) if judged else None,
        sunk_mm=round(float(low) * 1e3, 1),
        underneath_mm=round(float(under) * 1e3, 1),
        resting_on_table=contact is not None,
        contact_shift_mm=None if lowest is None else round(-lowest * 1e3, 2),
        hypothesis=np.asarray(SE3(found.pose).as_matrix(), np.float64).tolist(),
    )

    def fail(reason: str):
        raise _Failed("register", reason, _timed(record, start), mask=mask, points=points)

    usable = _USABLE + ((ICPStatus.degenerate,) if symmetry is not None else ())
    if not any(bool(best.status == status) for status in usable):
        fail(f"the final registration failed: {best.status_message()}")
    problems = []
    if not matched:
        problems.append(
            f"no segment point lies within {fine_distances[-1] * 1e3:.0f} mm of the model"
        )
    elif not rmse <= gates.max_rmse:
        problems.append(
            f"the residual is {rmse * 1e3:.1f} mm (at most {gates.max_rmse * 1e3:.1f} at "
            f"sigma_z {gates.sigma_z * 1e3:.1f} mm)"
        )
    if not judged:
        problems.append(
            "the image judges none of the model's surface facing the camera at the fitted pose "
            "(no depth where the model would be seen)"
        )
    elif confirmed < s.min_confirmed:
        problems.append(
            f"the image confirms only {confirmed:.0%} of the model's surface facing it (need "
            f"{s.min_confirmed:.0%})"
        )
    if contradicted > s.max_contradicted:
        problems.append(
            f"the camera sees through {contradicted:.0%} of the model's surface facing it (at "
            f"most {s.max_contradicted:.0%})"
        )
    record = dataclasses.replace(
        record, explained_away=beyond.explained_away, runs_on=beyond.runs_on,
        overhang_mm=[round(float(r) * 1e3, 1) for r in beyond.overhang],
    )  # fmt: skip
    problems += beyond.problems
    if problems:
        fail("the model is not there: " + "; ".join(problems))
    reason = (
        f"found: {fraction:.0%} of {len(points)} segment points within "
        f"{fine_distances[-1] * 1e3:.0f} mm of the model, residual {rmse * 1e3:.2f} mm"
    )
    budget, segmentation = pose_budget(
        points=points, source_size=s.max_points, model=model,
        object_T_base=answers[ranked[0]], pose=found.pose, contact=contact,
        frame=frame, mask=mask, plane=plane, min_height=settings.lift.min_height,
        distances=fine_distances, trim=trim, eye=eye, noise=noise, calibration=calibration,
        ambiguous=(found.tangents, found.weights), symmetry=symmetry,
        view_free=(found.view_free, found.view_reason), rng=np.random.default_rng(1),
        segmentation=None if carried is None else
        (carried.segmentation, carried.segmentation_unknown),
    )  # fmt: skip
    if plane is not None:
        local = sum(budget.terms[name] for name in LOCAL_TERMS)
        z = z_score(s.false_refusal)
        heights = height_tests(
            model, plane, np.asarray(SE3(found.pose).as_matrix()), local, points,
            gates.sigma_z, gates.sigma_z, z,
        )  # fmt: skip
        if heights.sunk > heights.sunk_allowed:
            problems.append(
                f"the fitted model reaches {heights.sunk * 1e3:.0f} mm into the table (at most "
                f"{heights.sunk_allowed * 1e3:.1f}: {z:.1f} sigma of the pose's, the table's "
                "and the model's uncertainty there): a shorter object of a similar shape"
            )
        if heights.under > heights.under_allowed:
            problems.append(
                f"the segment reaches {heights.under * 1e3:.0f} mm below the fitted model (at "
                f"most {heights.under_allowed * 1e3:.1f}: {z:.1f} sigma of the pose's, the "
                "points' and the model's uncertainty there): the model sits on a taller object "
                "of a similar shape"
            )
        if problems:
            fail("the model is not there: " + "; ".join(problems))
    pose = SE3(found.pose)
    view = carried or MeasuredView(
        model.key, pose, frame.base_T_camera.inverse() @ pose, len(points), found, *segmentation
    )
    return Registration(
        pose, rmse, fraction, budget, reason, _timed(record, start), found.equivalent, view
    )


def _timed(record: RegisterRecord, start: float) -> RegisterRecord:
    """``record`` (its ``ms`` the coarse search's) with the refinement's time since ``start``
    added."""
    return dataclasses.replace(record, ms=round(record.ms + (time.perf_counter() - start) * 1e3, 2))
