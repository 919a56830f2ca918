"""The register stage's answer: an answer resting on the table is moved onto it and settled
there with virtual contact points, the answer turned about the model's axes (probes) shows
which other poses the image supports as well, and the answer is reported on one symmetry
branch (:func:`_finish`).

Conventions: poses are ``object_T_base`` (wxyz_xyz) as ICP returns them (the segment, base
frame, registered into the model, object frame); tangents are jaxlie's ``(v, w)``.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
from jaxlie import SE3, SO3
from scipy.spatial.transform import Rotation

from jaxreg.core._program_cache import persistent_jit
from jaxreg.geometry.lie import geodesic_angle
from jaxreg.geometry.metrics import Symmetry, canonicalise
from jaxreg.pipeline._coarse import DISTINCT_ANGLE, DISTINCT_DISTANCE, _starts_in_pieces
from jaxreg.pipeline._judge import (
    EQUAL_WITHIN,
    evidence_gap,
    fit_order,
    judged_fits,
    passes_gates,
)
from jaxreg.pipeline._model import PROBE_ANGLES_DEG, _bucketed_symmetry, _Model
from jaxreg.pipeline.records import Alternatives, EquivalentPose, MeasuredView
from jaxreg.pipeline.settings import PipelineSettings
from jaxreg.registration.icp import icp

# --------------------------------------------------------------------------------------------
# Resting on the table: the plane pins the height and tilt of an object standing on it.

CONTACT_POINTS = 128  # virtual contact points appended to the refined cloud (static)
# Weight of a contact point against a measured one: the plane is fitted to thousands of table
# points, so its height is known far better than one depth pixel's.
CONTACT_WEIGHT = 8.0


def resting_contacts(points: np.ndarray, matrices: np.ndarray, normal, offset, tolerance, voxel):
    """Virtual contact points of a model resting on the table, at each of several poses.

    At a pose (``matrices``: ``(K, 4, 4)`` base_T_object), the model's lowest point (of
    ``points`` ``(M, 3)``, float64, object frame, no padding rows) must lie within
    ``tolerance`` (metres) of the plane ``normal . x + offset = 0``, and the model's points
    within one ``voxel`` of that height must form a face: at least 3 points whose spread
    along both of their principal directions in the plane is a third of the model's width
    or more (not a corner or an edge). The face's points, moved onto the plane along its
    normal, are where the table says the model's bottom is. Returns a list of ``K``: for a
    pose that rests, its ``(CONTACT_POINTS, 3)`` base-frame contact points (subsampled, or
    NaN padded) and the height (metres) its lowest point had above the plane; else
    ``None``. Host numpy, every pose in one batch (coordinates along the middle axis, the
    points along the last, where numpy's loops are long).
    """
    placed = matrices[:, :3, :3] @ points.T + matrices[:, :3, 3:]  # (K, 3, M)
    along = np.einsum("i,kim->km", normal, placed)
    height = along + offset
    lowest = height.min(1)
    flat = placed - normal[:, None] * along[:, None, :]  # along the normal onto n . x = 0
    width = (flat.max(2) - flat.min(2)).max(1)
    face = height <= lowest[:, None] + voxel  # (K, M)
    count = face.sum(1)
    mean = np.where(face[:, None], flat, 0.0).sum(2) / np.maximum(count, 1)[:, None]
    centred = np.where(face[:, None], flat - mean[:, :, None], 0.0)
    scatter = centred @ centred.transpose(0, 2, 1)
    scatter[~np.isfinite(scatter).all((1, 2))] = np.eye(3)  # a non-finite pose: it fails below
    principal = np.linalg.eigh(scatter)[1][:, :, 1:]  # (K, 3, 2)
    spans = principal.transpose(0, 2, 1) @ flat  # (K, 2, M)
    spread = (
        np.where(face[:, None], spans, -np.inf).max(2)
        - np.where(face[:, None], spans, np.inf).min(2)
    ).min(1)
    rests = (np.abs(lowest) <= tolerance) & (count >= 3) & (spread >= width / 3)
    found = [None] * len(matrices)
    for k in np.flatnonzero(rests):
        contact = (flat[k][:, face[k]] - offset * normal[:, None]).T  # onto the plane
        out = np.full((CONTACT_POINTS, 3), np.nan, np.float32)
        step = max(1, int(np.ceil(len(contact) / CONTACT_POINTS)))
        picked = contact[::step][:CONTACT_POINTS]
        out[: len(picked)] = picked
        found[k] = (out, float(lowest[k]))
    return found


@persistent_jit
def _settle(source, contact, points, normals, grid, init, distances, trim, iterations, eye):
    """Point-to-plane ICP of ``source`` ``(N, 3)`` with the ``contact`` points ``(C, 3)``
    appended (weight ``CONTACT_WEIGHT``), from ``init`` (7,): the object settled on the
    table. ``eye``: the ICP viewpoint of the ``source`` rows (the contacts match any face),
    or ``None``."""
    joined = jnp.concatenate([source, contact])
    weights = jnp.concatenate(
        [jnp.ones(source.shape[0], source.dtype), jnp.full(contact.shape[0], CONTACT_WEIGHT)]
    ).astype(source.dtype)
    weights = jnp.where(jnp.all(jnp.isfinite(joined), axis=1), weights, 0.0)
    seen = None if eye is None else jnp.arange(joined.shape[0]) < source.shape[0]
    return icp(
        joined, points, SE3(init), method="point_to_plane", target_normals=normals,
        max_correspondence_distance=distances, max_iterations=iterations, trim_fraction=trim,
        source_weights=weights, neighbors=grid, tolerance=1e-5, viewpoint=eye,
        viewpoint_rows=seen,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Ambiguity: is the answer the only pose the image supports?

def probe_starts(model: _Model, object_T_base: np.ndarray) -> np.ndarray:
    """``(3 * len(PROBE_ANGLES_DEG), 7)`` object_T_base starts: the answer turned about each
    of the model's principal axes through its centroid by each probe angle (a mug whose handle
    is hidden turns about its body's axis and still fits), axis-major."""
    answer = SE3(np.asarray(object_T_base, np.float64))
    centre = SE3.from_translation(np.asarray(model.centroid, np.float64))
    angles = np.radians(PROBE_ANGLES_DEG)
    tangents = np.asarray(model.axes, np.float64).T[:, None, :] * angles[None, :, None]
    turns = SE3.from_rotation(SO3.exp(tangents.reshape(-1, 3)))  # one batch: a few dispatches
    return np.asarray((centre @ turns @ centre.inverse() @ answer).wxyz_xyz, np.float32)


def _probe(frame, plane, model, source, answer, trim, noise, distances, max_rmse, eye, settings):
    """The answer turned about the model's axes (:func:`probe_starts`), refined (``eye`` the
    ICP viewpoint) and judged like the refined starts (as ICP left them): their poses
    ``(P, 7)`` (object_T_base, moved onto the table where they rest on it, as the starts'
    answers are), scores and residuals ``(P,)`` (metres), whether each passes the gates an
    answer must pass (``(P,)`` bool: residual within ``max_rmse``, the explained, confirmed
    and contradicted shares within the register settings') and the image's counts ``(P, 5)``
    (:func:`~jaxreg.pipeline._judge.visibility`). The probes are refined on every second
    point of ``source`` (half the cost)."""
    probed = _starts_in_pieces(
        source[::2], model.points, model.normals, model.fine_grid, probe_starts(model, answer),
        distances, trim, 30, eye,
    )  # fmt: skip
    refined = np.asarray(probed.pose.wxyz_xyz)
    poses, _ = _onto_table(model, refined, plane, settings)
    scores, rmses, seen = judged_fits(frame, plane, refined, model.points, probed, noise)
    passes = passes_gates(probed.inlier_fraction, rmses, seen, max_rmse, settings.register)
    return poses, scores, rmses, passes, seen


def _unfixed_turns(model, equal: np.ndarray):
    """Turns about a model axis that the view does not fix: where the probes as good as the
    answer (``equal`` ``(3 * A,)``, axis-major) span 120 degrees or more about one of the
    model's principal axes, and that axis is (within 25 degrees) one of the object frame's,
    the rotation about it is free. Returns the free tangent axes ``(6,)``, why, and which
    probes turned about a free axis ``(3 * A,)``."""
    angles = np.asarray(PROBE_ANGLES_DEG)
    free = np.zeros(6, bool)
    turned = np.zeros(len(equal), bool)
    reasons = []
    for k, axis in enumerate(np.asarray(model.axes).T):
        rows = slice(k * len(angles), (k + 1) * len(angles))
        span = _good_arc(angles, equal[rows])
        frame_axis = int(np.argmax(np.abs(axis)))
        if span >= 120 and abs(axis[frame_axis]) > np.cos(np.radians(25)):
            free[3 + frame_axis] = True
            turned[rows] = True
            reasons.append(
                f"the view does not fix the rotation about the object's "
                f"{'xyz'[frame_axis]} axis (equally good answers span {span:.0f} deg)"
            )
    return free, "; ".join(reasons) or None, turned


def _alike_turns(model, max_rmse: float) -> np.ndarray:
    """``(3 * len(PROBE_ANGLES_DEG),)`` bool, axis-major like the probes: the turns under which
    the model lies within ``max_rmse`` (the fit's residual gate, metres) of itself
    (``model.self_misfits``): a box's or a can's half turns, a can's spin, a near-symmetric
    shape's turns, which the view's depth cannot tell from the answer."""
    return (np.asarray(model.self_misfits) <= max_rmse).reshape(-1)


def _good_arc(angles: np.ndarray, good: np.ndarray) -> float:
    """Degrees spanned by the run of consecutive good turns around the circle that holds the
    answer (turn 0): a contiguous range of equally good answers about it, unlike isolated
    flips or a second basin elsewhere."""
    turns = np.mod(np.append(angles, 0.0), 360.0)
    flags = np.append(good, True)
    order = np.argsort(turns, kind="stable")
    turns, flags = turns[order], flags[order]
    if flags.all():
        return 360.0
    n, here = len(turns), int(np.flatnonzero(turns == 0.0)[0])
    right = here
    while flags[(right + 1) % n]:
        right += 1
    left = here
    while flags[(left - 1) % n]:
        left -= 1
    return float(turns[right % n] - turns[left % n]) % 360.0


def _onto_table(model, answers, plane, settings: PipelineSettings):
    """``answers`` ``(S, 7)`` (object_T_base wxyz_xyz) with each one that rests on the table
    (:func:`resting_contacts`) moved onto it, and each one's contact (points, lowest height)
    or ``None`` (a list of ``S``). The poses are composed in batches (a few dispatches for
    all ``S``)."""
    answers = np.array(answers, np.float32)
    if plane is None:
        return answers, [None] * len(answers)
    matrices = np.asarray(SE3(np.asarray(answers, np.float64)).inverse().as_matrix())
    points = model.points[np.all(np.isfinite(model.points), axis=1)].astype(np.float64)
    normal, offset = np.asarray(plane.normal, np.float64), float(plane.offset)
    restings = resting_contacts(
        points, matrices, normal, offset, settings.register.rest_tolerance, settings.voxel_size
    )
    rests = np.array([resting is not None for resting in restings])
    if rests.any():
        shifts = np.array([normal * (0.0 if r is None else r[1]) for r in restings])
        shifted = SE3(np.asarray(answers, np.float64)) @ SE3.from_translation(shifts)
        answers = np.where(rests[:, None], np.asarray(shifted.wxyz_xyz, np.float32), answers)
    return answers, restings


def _rest(
    source, model, results, best: int, plane, trim, distances, settings: PipelineSettings, eye
):  # fmt: skip
    """The refined answers ``(S, 7)`` (object_T_base) with each one that rests on the table
    moved onto it, the best one settled there by ICP with the contact points (``eye``: the
    ICP viewpoint of the segment's points, or ``None``); the contact
    points ``(C, 3)`` of the best (``None`` when it does not rest) and its lowest point's
    height above the table before (metres; ``None`` likewise)."""
    answers, restings = _onto_table(model, results.pose.wxyz_xyz, plane, settings)
    contact, lowest = None, None
    resting = restings[best]
    if resting is not None:
        settled = _settle(
            source, resting[0], model.points, model.normals, model.fine_grid, answers[best],
            distances[-15:], trim, 15, eye,
        )  # fmt: skip
        if bool(np.isfinite(np.asarray(settled.inlier_rmse))):
            answers[best] = np.asarray(settled.pose.wxyz_xyz, np.float32)
            contact, lowest = resting
    return answers, contact, lowest


# --------------------------------------------------------------------------------------------
# The answer on one symmetry branch, and the distinct starts it is chosen from.


def _canonical(pose: SE3, reference: SE3, symmetry) -> SE3:
    """:func:`canonicalise` by a bucketed ``symmetry`` ``(rotations (K, 3, 3), axis (3,),
    continuous)``: with the axis when ``continuous``, else the rotations alone."""
    rotations, axis, continuous = symmetry
    fixed = canonicalise(pose, reference, Symmetry(rotations))
    turned = canonicalise(pose, reference, Symmetry(rotations, axis))
    return SE3(jnp.where(continuous, turned.wxyz_xyz, fixed.wxyz_xyz))


@persistent_jit
def _finish(object_T_base, best, equal, symmetry):
    """The answer from the refined starts ``object_T_base (S, 7)``, as one stored program
    for every model: ``base_T_object`` of start ``best`` (wxyz_xyz; the equivalent under the
    bucketed ``symmetry`` (:func:`_bucketed_symmetry`) nearest the base axes), the largest
    offset (metres) and angle (degrees) to the starts flagged ``equal`` ``(S,)`` and their
    tangents ``(S, 6)``, all compared on the answer's symmetry branch (right perturbations
    of the reported ``base_T_object``, object axes)."""
    found = SE3(object_T_base[best])
    pose = found.inverse()
    others = _canonical(SE3(object_T_base).inverse(), pose, symmetry)
    offset = jnp.linalg.norm(others.translation() - pose.translation(), axis=-1)
    angle = jnp.degrees(geodesic_angle(others.rotation(), pose.rotation()))
    spread = jnp.stack([jnp.max(jnp.where(equal, offset, 0)), jnp.max(jnp.where(equal, angle, 0))])
    # report one branch: the equivalent nearest the base axes
    pose = _canonical(pose, SE3.from_translation(pose.translation()), symmetry)
    others = _canonical(others, pose, symmetry)
    tangents = (pose.inverse() @ others).log()
    return pose.wxyz_xyz, spread, tangents


def _distinct(poses: np.ndarray, count: int) -> list[int]:
    """The first ``count`` rows of ``poses`` (``(S, 7)`` wxyz_xyz, best first) that are
    distinct from every earlier pick (``DISTINCT_DISTANCE`` or ``DISTINCT_ANGLE``)."""
    quats, trans = poses[:, :4], poses[:, 4:]
    chosen: list[int] = []
    for i in range(len(poses)):
        if all(
            np.linalg.norm(trans[i] - trans[j]) > DISTINCT_DISTANCE
            or 2 * np.arccos(min(1.0, abs(float(quats[i] @ quats[j])))) > DISTINCT_ANGLE
            for j in chosen
        ):
            chosen.append(i)
        if len(chosen) == count:
            break
    return chosen


# --------------------------------------------------------------------------------------------
# Everything that fits as well as the answer.


def _pivoted(tangents: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``tangents`` ``(A, 6)`` (right perturbations ``(v, w)``, object axes) with their
    translations replaced so that the linear map ``v + w x centre`` gives the exact
    displacement of the model's ``centre`` ``(3,)`` (object frame) under ``exp(v, w)``: a
    large turn's effect on the model is linearised at its centre, not at its frame's origin
    (a mug turned half round its body moves its handle's side of the box, not its body)."""
    tangents = np.asarray(tangents, np.float64).reshape(-1, 6)
    v, w = tangents[:, :3], tangents[:, 3:]
    theta = np.linalg.norm(w, axis=1)
    small = theta < 1e-6
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 0.5, (1 - np.cos(safe)) / safe**2)[:, None, None]
    b = np.where(small, 1 / 6, (safe - np.sin(safe)) / safe**3)[:, None, None]
    skew = np.zeros((len(w), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    skew -= skew.transpose(0, 2, 1)
    rotation = Rotation.from_rotvec(w).as_matrix() if len(w) else np.zeros((0, 3, 3))
    left = np.eye(3) + a * skew + b * skew @ skew  # SO(3)'s left Jacobian
    moved = rotation @ centre + np.einsum("aij,aj->ai", left, v) - centre
    return np.concatenate([moved - np.cross(w, centre), w], axis=1)


def _axis_angle(rotation: np.ndarray) -> tuple[np.ndarray, float]:
    """The unit axis ``(3,)`` and angle (degrees) of a rotation vector ``(3,)``."""
    angle = float(np.linalg.norm(rotation))
    return np.asarray(rotation, np.float64) / max(angle, 1e-12), float(np.degrees(angle))


def _alternatives(
    frame, plane, model, source, answers, best, scores, rmses, patches, trim, noise, distances,
    max_rmse, eye, symmetry, settings,
) -> tuple[Alternatives, np.ndarray]:  # fmt: skip
    """The refined starts (``answers`` ``(S, 7)`` object_T_base, their ``scores`` and
    ``rmses``, ``best`` the answer's row) and the answer's probes (:func:`_probe`) judged
    against the answer over the segment's ``patches``: which fit as well (within two
    standard errors of :func:`~jaxreg.pipeline._judge.evidence_gap`), each one's weight for
    the error budget's ambiguity term, the rotations a contiguous arc of equally good probes
    leaves free (:func:`_unfixed_turns`), and the equivalent poses: the refined starts that
    fit as well turned ``DISTINCT_ANGLE`` or more from the answer, and the probes that fit as
    well and stay turned after refinement (half their turn or more), both on the answer's
    ``symmetry`` branch (a declared symmetry's copies are the answer itself), one per
    distinct pose (1 cm or 0.2 rad apart), best first. A probe's turn under which the model
    matches itself within the fit's residual gate ``max_rmse`` (:func:`_alike_turns`) is as
    good as the answer whatever the fits' differences (they come from where the model's
    surface differs from the object's, not from the pose) when its refined fit passes the
    answer's gates: weight 1, and part of a free arc.

    Also returns the probes ``(L, 7)`` (object_T_base, best first) that pass the answer's
    gates and fit clearly better than the answer (it falls more than ``EQUAL_WITHIN``
    standard errors short of each): the answer is then a turn of the object (a mug's body
    fitted with its handle on the hidden side while the image shows it), and the refinement
    answers again from them."""
    padded = _bucketed_symmetry(symmetry)
    gaps = evidence_gap(scores, rmses, scores[best], rmses[best], patches)
    equal = gaps <= EQUAL_WITHIN
    pose, spread, tangents = _finish(answers, np.int32(best), equal, padded)
    probes, probe_scores, probe_rmses, probe_passes, _ = _probe(
        frame, plane, model, source, answers[best], trim, noise, distances, max_rmse, eye,
        settings,
    )  # fmt: skip
    probe_gaps = evidence_gap(probe_scores, probe_rmses, scores[best], rmses[best], patches)
    equal_probes = probe_gaps <= EQUAL_WITHIN
    behind = np.array([
        evidence_gap(scores[best:best + 1], rmses[best:best + 1], score, rmse, patches)[0]
        for score, rmse in zip(probe_scores, probe_rmses, strict=True)
    ])  # fmt: skip
    leads = np.flatnonzero(probe_passes & (behind > EQUAL_WITHIN))
    leads = leads[fit_order(probe_scores[leads], probe_rmses[leads])]
    _, _, probe_tangents = _finish(
        np.concatenate([answers[best][None], probes]), np.int32(0),
        np.concatenate([[False], equal_probes]), padded,
    )  # fmt: skip
    probe_tangents = np.asarray(probe_tangents)[1:]
    turns = np.radians(np.abs(np.tile(PROBE_ANGLES_DEG, 3)))
    stayed = np.linalg.norm(probe_tangents[:, 3:], axis=1) >= 0.5 * turns
    alike = _alike_turns(model, max_rmse) & probe_passes
    view_free, view_reason, turned = _unfixed_turns(model, (equal_probes | alike) & stayed)
    probe_gaps = np.where(alike, 0.0, probe_gaps)
    kept = (equal_probes | alike) & ~turned
    others = equal & (np.arange(len(equal)) != best)
    start_tangents = np.asarray(tangents)
    tangents = _pivoted(
        np.concatenate([start_tangents[others], probe_tangents[kept]]), model.centre
    )
    weights = np.exp(-0.5 * np.concatenate([gaps[others], probe_gaps[kept]]) ** 2)
    axes = np.asarray(model.axes, np.float64).T
    # turned answers: refined starts that came to rest turned, then probes that stayed turned
    alternatives = [
        (gaps[i], answers[i], *_axis_angle(start_tangents[i, 3:]), scores[i], rmses[i])
        for i in np.flatnonzero(others)
        if np.linalg.norm(start_tangents[i, 3:]) >= DISTINCT_ANGLE
    ] + [
        (probe_gaps[i], probes[i], axes[i // len(PROBE_ANGLES_DEG)],
         PROBE_ANGLES_DEG[i % len(PROBE_ANGLES_DEG)], probe_scores[i], probe_rmses[i])
        for i in np.flatnonzero(kept & stayed)
    ]  # fmt: skip
    alternatives.sort(key=lambda alternative: alternative[0])  # stable: best first
    ordered = np.stack([answers[best], *(alternative[1] for alternative in alternatives)])
    equivalent = tuple(
        EquivalentPose(
            pose=SE3(np.asarray(other, np.float64)).inverse(), axis=np.asarray(axis, np.float64),
            angle_deg=float(angle), score=float(score), inlier_rmse=float(rmse),
            weight=float(np.exp(-0.5 * gap**2)),
        )
        for gap, other, axis, angle, score, rmse in (
            alternatives[k - 1] for k in _distinct(ordered, len(alternatives) + 1)[1:]
        )
    )  # fmt: skip
    return Alternatives(
        np.asarray(pose), np.asarray(spread), equal, equal_probes, tangents, weights, view_free,
        view_reason, equivalent,
    ), probes[leads]  # fmt: skip


def _carried(view: MeasuredView, answers, best, scores, rmses, patches, symmetry) -> Alternatives:
    """:func:`_alternatives` with what the probes found carried from a previous frame's
    ``view`` (:class:`~jaxreg.pipeline.records.MeasuredView`) instead of measured again: the
    refined starts (``answers`` ``(S, 7)``, ``scores``, ``rmses``, ``best`` the answer's row)
    judged against the answer as there, the equivalent poses moved with the answer, the rest
    as it was (the ambiguity's tangents are right perturbations in the object's axes, which
    move with it)."""
    gaps = evidence_gap(scores, rmses, scores[best], rmses[best], patches)
    equal = gaps <= EQUAL_WITHIN
    pose, spread, _ = _finish(answers, np.int32(best), equal, _bucketed_symmetry(symmetry))
    moved = SE3(np.asarray(pose, np.float64)) @ view.pose.inverse()
    then = view.alternatives
    return dataclasses.replace(
        then, pose=np.asarray(pose), spread=np.asarray(spread), equal_starts=equal,
        equivalent=tuple(dataclasses.replace(e, pose=moved @ e.pose) for e in then.equivalent),
    )  # fmt: skip
