"""The register stage of :func:`jaxreg.estimate_pose` after the coarse search
(:mod:`jaxreg.pipeline._segment_stage` scores the candidates with it): the best distinct
coarse poses refined on the lifted points, ranked by inlier fraction times the share of the
model the image confirms, the answer settled on the table and probed, the checks that refuse
a model that is not there, and the pose's error budget (:mod:`jaxreg.pipeline._budget`).
"""

from __future__ import annotations

import dataclasses
import time

import jax
import numpy as np
from jaxlie import SE3

from jaxreg.pipeline._answer import PROBE_ANGLES_DEG, _probe, _rest, _unfixed_turns
from jaxreg.pipeline._budget import pose_budget
from jaxreg.pipeline._model import _bucketed_symmetry
from jaxreg.pipeline._records import RegisterRecord
from jaxreg.pipeline._register_stage import (
    _confirmed_share,
    _distinct,
    _finish,
    _judge,
    _register_starts,
    _support,
    overhang,
)
from jaxreg.pipeline._settings import _TOLERANCE, _Failed, _ms, _padded, _Settings
from jaxreg.registration.icp import ICPStatus

__all__ = ["refine_stage"]

# Final ICP statuses that leave a pose to judge (the iteration bound leaves the last step's
# pose); degenerate geometry passes too when a symmetry is given (its free directions).
_USABLE = (ICPStatus.success, ICPStatus.max_iterations)


def refine_stage(
    frame, plane, model, settings: _Settings, coarse_poses, coarse_fraction, mask, points, noise,
    symmetry, calibration, rng, stages,
):  # fmt: skip
    """The best distinct ``coarse_poses`` ``(C, 7)`` refined on the lifted ``points`` ``(K, 3)``
    and judged, its record in ``stages["register"]``. Returns ``base_T_object`` (``SE3``), the
    inlier RMSE and fraction, the :class:`~jaxreg.uncertainty.budget.PoseBudget` and a
    one-line summary; raises ``_Failed`` when the evidence says the model is not there."""
    s = settings
    fine_distances = s.fine_distances
    start = time.perf_counter()
    source = _padded(points, s.max_points, rng)
    picks = _distinct(coarse_poses, s.refined_starts, 0.01)
    inits = SE3(jax.device_put(coarse_poses[picks]))
    trim = np.float32(np.clip(coarse_fraction, 0.6, 0.95))  # an argument: one program for all
    results = _register_starts(
        source, model.points, model.normals, model.fine_grid, inits, fine_distances, trim, 30
    )
    fractions = np.asarray(results.inlier_fraction)
    rmses = np.nan_to_num(np.asarray(results.inlier_rmse), nan=np.inf)
    seen = np.asarray(
        _judge(frame, plane, results.pose.wxyz_xyz, model.points, _TOLERANCE, noise.coefficients)
    )
    scores = fractions * _confirmed_share(seen)
    ranked = np.lexsort((rmses, -np.round(scores, 2)))
    best = results[int(ranked[0])]
    fraction, rmse = float(fractions[ranked[0]]), float(rmses[ranked[0]])
    confirmed, contradicted = _support(seen[ranked[0]])
    reach = overhang(model, np.asarray(results.pose.wxyz_xyz[ranked[0]]), points)
    equal = (scores >= scores[ranked[0]] - 0.02) & (rmses <= rmse * 1.1 + 1e-4)
    answers, contact, lowest = _rest(source, model, results, ranked[0], plane, trim, s)
    padded_symmetry = _bucketed_symmetry(symmetry)
    wxyz_xyz, spread, tangents = _finish(answers, np.int32(ranked[0]), equal, padded_symmetry)
    probed = _probe(
        frame, plane, model, source, answers[ranked[0]], scores[ranked[0]], rmse, trim, noise, s
    )
    _, _, probe_tangents = _finish(
        np.concatenate([answers[ranked[0]][None], probed[0]]), np.int32(0),
        np.concatenate([[False], probed[1]]), padded_symmetry,
    )  # fmt: skip
    # a probe that stayed turned (not pulled back to the answer) and fits as well
    turns = np.radians(np.abs(np.tile(PROBE_ANGLES_DEG, 3)))
    stayed = np.linalg.norm(np.asarray(probe_tangents)[1:, 3:], axis=1) >= 0.5 * turns
    view_free, view_reason, turned = _unfixed_turns(model, probed[1] & stayed)
    kept = probed[1] & ~turned
    others = equal & (np.arange(len(equal)) != ranked[0])
    ambiguous = (
        np.concatenate([np.asarray(tangents)[others], np.asarray(probe_tangents)[1:][kept]]),
        np.concatenate([rmses[others], probed[2][kept]]),
        rmse,
    )
    spread_mm, spread_deg = (float(x) for x in np.asarray(spread))
    matched = fraction > 0 and rmse < 1.0  # no match leaves ICP's empty-sum residual
    stages["register"] = RegisterRecord(
        ms=_ms(start),
        starts=s.num_starts + 4 + 6 * s.resting_yaws,
        coarse_kept_starts=int(coarse_poses.shape[0]),
        refined_starts=len(picks),
        trim_fraction=round(float(trim), 3),
        iterations=int(best.iterations),
        icp_status=str(best.status_message()),
        inlier_rmse_mm=round(rmse * 1e3, 3) if matched else None,
        inlier_fraction=round(fraction, 3),
        equally_good_starts=int(equal.sum()),
        equally_good_probes=int(probed[1].sum()),
        start_agreement_mm=round(spread_mm * 1e3, 3),
        start_agreement_deg=round(spread_deg, 3),
        model_confirmed=round(confirmed, 3),
        model_contradicted=round(contradicted, 3),
        overhang_mm=[round(float(r) * 1e3, 1) for r in reach],
        resting_on_table=contact is not None,
        contact_shift_mm=None if lowest is None else round(-lowest * 1e3, 2),
    )
    usable = _USABLE + ((ICPStatus.degenerate,) if symmetry is not None else ())
    if not any(bool(best.status == status) for status in usable):
        raise _Failed(
            "register", f"the final registration failed: {best.status_message()}", mask=mask,
            points=points,
        )  # fmt: skip
    problems = []
    if fraction < s.min_inlier_fraction:
        problems.append(
            f"the model explains only {fraction:.0%} of the segment (need "
            f"{s.min_inlier_fraction:.0%})"
        )
    if not matched:
        problems.append(
            f"no segment point lies within {fine_distances[-1] * 1e3:.0f} mm of the model"
        )
    elif not rmse <= s.max_inlier_rmse:
        problems.append(
            f"the residual is {rmse * 1e3:.1f} mm (at most {s.max_inlier_rmse * 1e3:g})"
        )
    if contradicted > s.max_contradicted:
        problems.append(
            f"the camera sees through {contradicted:.0%} of the model's surface facing it (at "
            f"most {s.max_contradicted:.0%})"
        )
    if np.isnan(reach).any():
        problems.append(
            "the segment's span beyond the model could not be measured (NaN: a non-finite "
            "pose or segment point)"
        )
    elif reach.max() > s.max_overhang:
        problems.append(
            f"the segment spans {reach.max() * 1e3:.0f} mm beyond the model along its "
            f"{('longest', 'middle', 'shortest')[int(reach.argmax())]} axis (at most "
            f"{s.max_overhang * 1e3:g}): a larger object of a similar shape, or the object "
            "merged with a neighbour"
        )
    if problems:
        raise _Failed(
            "register", "the model is not there: " + "; ".join(problems), mask=mask, points=points
        )
    reason = (
        f"found: {fraction:.0%} of {len(points)} segment points within "
        f"{fine_distances[-1] * 1e3:.0f} mm of the model, residual {rmse * 1e3:.2f} mm"
    )
    budget = pose_budget(
        points=points, source_size=s.max_points, model=model,
        object_T_base=answers[ranked[0]], pose=np.asarray(wxyz_xyz), contact=contact,
        frame=frame, mask=mask, plane=plane, min_height=s.lift_min_height,
        distances=fine_distances, trim=trim, noise=noise, calibration=calibration,
        ambiguous=ambiguous, symmetry=symmetry, view_free=(view_free, view_reason),
        rng=np.random.default_rng(1),
    )  # fmt: skip
    stages["register"] = dataclasses.replace(stages["register"], ms=_ms(start))
    return SE3(wxyz_xyz), rmse, fraction, budget, reason
