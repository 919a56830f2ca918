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
twin too unless the winner's refined fit is clearly better
(:func:`~jaxreg.pipeline._fits.twin_of`).

:func:`refine_stage` (after it): the winner's best distinct coarse poses refined on the lifted
points, ranked by inlier fraction times the confirmed share (those that keep to what the frame
allows first), the answer settled on the table and probed (:mod:`jaxreg.pipeline._answer`), the
checks that refuse a model that is not there, and the pose's error budget
(:mod:`jaxreg.pipeline._error_sources`).

The candidates' fits, their bounds and the contest between them are in
:mod:`jaxreg.pipeline._fits`.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from jaxlie import SE3

from jaxreg.pipeline._answer import (
    _alternatives,
    _carried,
    _onto_table,
    _rest,
)
from jaxreg.pipeline._colour import colour_match, other_colour
from jaxreg.pipeline._error_sources import _pixels, mismatch_sigma, pose_budget
from jaxreg.pipeline._evidence import (
    LOCAL_TERMS,
    camera_depths,
    height_tests,
    z_score,
)
from jaxreg.pipeline._fits import (
    candidate_record,
    coarse_scores,
    frame_bounds,
    joined_pieces,
    judged_beyond,
    keeps_within,
    refit,
    twin_of,
)
from jaxreg.pipeline._judge import (
    NOISE_SIGMAS,
    _support,
    patch_count,
    seen_share,
)
from jaxreg.pipeline._model import viewpoint
from jaxreg.pipeline._stages import _Failed
from jaxreg.pipeline.records import (
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
    coarse, scored = coarse_scores(
        frame, segmented.plane, model, settings, clouds, rng, noise, gates
    )  # fmt: skip
    _, explained, *_, chosen = scored[0]
    poses = np.asarray(coarse.poses[chosen])  # object_T_base per start, best first
    candidates = [
        candidate_record(list(segmented.candidates[i][0]), *rest) for *rest, i in scored
    ]
    r = settings.register
    starts = r.num_starts + 4 + 6 * r.resting_yaws
    joined = joined_pieces(model, segmented, chosen, poses[0])
    twin = twin_of(frame, model, segmented, coarse, scored, joined, gates, settings, noise)
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
        fit = refit(
            frame, model, plane, points, starts, coarse_fraction, gates, settings, noise, rng, eye
        )
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
            and keeps_within(frame_bounds(model, plane, turn, points), gates)
            for turn, resting in zip(turns, restings, strict=True)
        ]

    def beyond_at(answer, refined):
        return judged_beyond(
            frame, model, plane, answer, refined, points, gates, noise, settings,
            settings.voxel_size, (coarse.region, coarse.border),
        )  # fmt: skip

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
    _, low, under = frame_bounds(model, plane, answers[ranked[0]], points)
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
    in_view = float(seen_share(seen[ranked[0]]))
    if judged and in_view < s.min_seen:
        problems.append(
            f"the image confirms only {in_view:.0%} of the model's surface facing it where "
            f"nothing hides it (need {s.min_seen:.0%}; the rest lies outside the image or over "
            "depth holes): too little of the model is in view to tell it from another object"
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
