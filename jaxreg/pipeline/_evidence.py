"""The register stage's tests of a refined pose against the frame's physical evidence, each
weighed against the sensor's noise at the pose's own uncertainty, with a stated false-refusal
rate (``RegisterSettings.false_refusal``, one-sided, per test) instead of fixed millimetres:

- :func:`continuing`: the segment's points that carry the model's surface on past its edge
  (a larger object of a similar shape). Points the model does not explain and that do not
  continue its surface (a neighbour's face meeting it at a crease, the background behind a
  mask's border, an occluder, the object it rests on) are explained away, not counted.
- :func:`height_tests`: how far the pose sinks the model's lowest point into the table, and
  how far the segment reaches below the model, each against the standard deviation of that
  height under the pose's local error budget (depth, fit, mismatch, segmentation), the depth
  noise of the table and of the points, and the model's mismatch.

Conventions of :mod:`jaxreg.pipeline.estimate`: base-frame points, ``object_T_base`` wxyz_xyz
poses as ICP returns them, ``base_T_object`` 4x4 matrices for the reported pose, budgets as
right perturbations ``(v, w)`` in the object's axes.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.stats import norm

from jaxreg.pipeline._model import _Model
from jaxreg.search.normals import estimate_normals

__all__ = ["continuing", "height_tests", "sigmas_at"]

# The pose's error-budget terms that move the model against the table and the segment (the
# calibration moves both together; the ambiguity term is the alternatives', judged apart).
LOCAL_TERMS = ("depth", "fit", "mismatch", "segmentation")
# Neighbours (segment points) of each point whose principal axes give its surface normal.
NORMAL_NEIGHBOURS = 10
# Model points nearest a segment point that must all lie on one side of it, in its tangent
# plane, for it to lie past the model's edge rather than in a gap between the model's samples.
EDGE_NEIGHBOURS = 12
# A point runs the model's surface on when the segment's points within GROW_RADIUS gates of it
# that the model explains (or that run it on) lie in its tangent plane, IN_PLANE of them at
# least; GROW_STEPS such steps reach out from the model's edge.
IN_PLANE, GROW_RADIUS, GROW_STEPS = 4, 2.0, 4
# A segment point is on a face of the model the camera sees when one of its SEEN_NEIGHBOURS
# nearest model points within the gate faces the camera with a normal within PARALLEL_DEG of
# the point's (and the point lies on its tangent plane within the noise), and a face runs on
# through points on that plane whose normals agree that closely: a face's own points agree to
# a few degrees; a support's top meeting the model's hidden bottom edge, a neighbour's face at
# a crease, or a thin object lying on the face, differ by far more.
SEEN_NEIGHBOURS, PARALLEL_DEG = 8, 30.0
# A seen point's plane, which the surface running on from it must keep to: the principal axes
# of its PLANE_NEIGHBOURS nearest seen points (a patch of the face, steadier than the
# NORMAL_NEIGHBOURS that find each point's own normal among whatever lies around it).
PLANE_NEIGHBOURS = 30
# The 2% quantile of the segment's heights (underneath) lies this many depth-noise standard
# deviations below its points' true lowest height (a Gaussian's 2% quantile).
LOW_QUANTILE, LOW_QUANTILE_SIGMAS = 0.02, 2.054


def z_score(false_refusal: float) -> float:
    """The one-sided standard-normal quantile whose upper tail is ``false_refusal``."""
    return float(norm.isf(false_refusal))


def sigmas_at(frame, noise, points: np.ndarray) -> np.ndarray:
    """``(N,)`` the depth noise's axial standard deviation (metres) at the camera depth of each
    base-frame point of ``points`` ``(N, 3)``."""
    camera = frame.base_T_camera
    axis = np.asarray(camera.rotation().as_matrix(), np.float64)[:, 2]
    depth = (np.asarray(points, np.float64) - np.asarray(camera.translation(), np.float64)) @ axis
    return np.asarray(noise.axial_sigma(depth), np.float64)


def continuing(
    model: _Model, object_T_base: np.ndarray, points: np.ndarray, gate: float,
    allowed: np.ndarray, eye: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Which of the segment's ``points`` ``(N, 3)`` (base frame) the model explains at the
    pose ``object_T_base`` ``(7,)`` (within ``gate`` metres, the fit's final correspondence
    distance), and which carry the model's surface on past its edge (``(N,)`` bool each):
    farther than ``gate`` from every model point and past the model's edge
    (:func:`_past_edge`), with half or more of the segment's seen or running-on points
    within ``GROW_RADIUS`` gates of it (``IN_PLANE`` at least) carrying a plane that it lies
    on (within ``allowed`` ``(N,)`` metres, its normal within ``PARALLEL_DEG`` of the
    plane's; normals from ``NORMAL_NEIGHBOURS`` segment neighbours), grown from the seen
    points outward for up to ``GROW_STEPS`` steps: the measured surface runs on flat across
    the model's edge. The seen points are the explained ones on a face of the model that the
    camera at ``eye`` ``(3,)`` (base frame) sees (:func:`_seen_faces`), each carrying the
    plane of the seen surface around it (``PLANE_NEIGHBOURS``), and a running-on point
    carries the plane it continues: a point
    explained only by a face turned away (the bottom the object rests on) is where the
    object meets what it stands on, and the top of a box it lies on runs on from there, not
    from the object. A real object's own surface stays within the gate of its model; a
    larger object's face runs on past it; a touching neighbour's face meets the model's at a
    crease, something lying on the object stands off its face, and the background or an
    occluder lies off it."""
    points = np.asarray(points, np.float64)
    if len(points) < 3:
        return np.zeros(len(points), bool), np.zeros(len(points), bool)
    rotation = Rotation.from_quat(np.asarray(object_T_base[:4], np.float64), scalar_first=True)
    moved = rotation.apply(points) + np.asarray(object_T_base[4:], np.float64)
    rows = np.flatnonzero(np.all(np.isfinite(model.points), axis=1))
    tree = cKDTree(model.points[rows])
    distance, _ = tree.query(moved)
    far = distance > gate
    if not far.any():
        return ~far, far
    normals = np.asarray(estimate_normals(moved, min(NORMAL_NEIGHBOURS, len(moved))), np.float64)
    allowed = np.broadcast_to(np.asarray(allowed, np.float64), far.shape)
    camera = rotation.apply(np.asarray(eye, np.float64)) + np.asarray(object_T_base[4:])
    seen = ~far & _seen_faces(model, rows, tree, moved, normals, gate, allowed, camera)
    anchors, planes = moved.copy(), normals.copy()
    if seen.sum() >= 3:  # each seen point's plane: the seen surface's around it
        planes[seen] = estimate_normals(moved[seen], min(PLANE_NEIGHBOURS, int(seen.sum())))
    past = np.flatnonzero(far)[_past_edge(tree, model.points[rows], moved[far], normals[far])]
    runs_on = np.zeros(len(points), bool)
    if not len(past):
        return ~far, runs_on
    nearby = cKDTree(moved).query_ball_point(moved[past], GROW_RADIUS * gate)
    cos_parallel = np.cos(np.radians(PARALLEL_DEG))
    for _ in range(GROW_STEPS):  # from the seen points outward, one radius a step
        grown = False
        for k, i in enumerate(past):
            if runs_on[i]:
                continue
            others = [j for j in nearby[k] if (seen[j] or runs_on[j]) and j != i]
            if len(others) < IN_PLANE:
                continue
            across = np.abs(np.sum((moved[i] - anchors[others]) * planes[others], axis=1))
            parallel = np.abs(planes[others] @ normals[i]) >= cos_parallel
            coplanar = (across <= allowed[i]) & parallel
            if np.mean(coplanar) >= 0.5:  # on the seen face's plane: it carries it on
                j = others[int(np.argmax(coplanar))]
                anchors[i], planes[i] = anchors[j], planes[j]
                runs_on[i] = grown = True
        if not grown:
            break
    return ~far, runs_on


def _seen_faces(model, rows, tree, points, normals, gate, allowed, eye) -> np.ndarray:
    """``(N,)`` bool: which of ``points`` ``(N, 3)`` (object frame, their unit ``normals``)
    lie on a face of the model that the camera at ``eye`` ``(3,)`` (object frame) sees:
    one of their ``SEEN_NEIGHBOURS`` nearest model points within ``gate`` (of the model's
    ``rows``, in ``tree``) faces the camera with a normal within ``PARALLEL_DEG`` of the
    point's, and the point lies within ``allowed`` ``(N,)`` metres of its tangent plane."""
    outward = model.normals[rows] * (1.0 if model.oriented else -1.0)  # estimated face inward
    facing = np.sum(outward * (eye - model.points[rows]), axis=1) > 0
    _, near = tree.query(points, SEEN_NEIGHBOURS, distance_upper_bound=gate)
    found = near < len(rows)
    near = np.where(found, near, 0)
    parallel = np.abs(np.einsum("nkd,nd->nk", outward[near], normals))
    across = np.abs(np.einsum("nkd,nkd->nk", points[:, None] - model.points[rows][near],
                              outward[near]))  # fmt: skip
    return np.any(
        found & facing[near] & (parallel >= np.cos(np.radians(PARALLEL_DEG)))
        & (across <= allowed[:, None]), axis=1,
    )  # fmt: skip


def _past_edge(tree, model_points, points, normals) -> np.ndarray:
    """``(N,)`` bool: whether each of ``points`` ``(N, 3)`` (object frame) lies past the
    model's edge, not in a gap between its samples: its ``EDGE_NEIGHBOURS`` nearest model
    points, seen in the point's tangent plane (``normals`` ``(N, 3)``), all lie on one side
    of it (each within 90 degrees of their mean direction)."""
    _, near = tree.query(points, EDGE_NEIGHBOURS)
    offsets = model_points[near] - points[:, None]
    offsets -= np.sum(offsets * normals[:, None], axis=2, keepdims=True) * normals[:, None]
    unit = offsets / np.maximum(np.linalg.norm(offsets, axis=2, keepdims=True), 1e-12)
    mean = unit.sum(1)
    mean /= np.maximum(np.linalg.norm(mean, axis=1, keepdims=True), 1e-12)
    return np.all(np.sum(unit * mean[:, None], axis=2) > 0.0, axis=1)


@dataclasses.dataclass(frozen=True)
class HeightTests:
    """:func:`height_tests`' results (metres): the model's depth in the table ``sunk`` and
    the segment's reach below the model ``under`` (each 0 or less when it keeps to the
    table), with their allowances at the false-refusal rate."""

    sunk: float
    sunk_allowed: float
    under: float
    under_allowed: float


def height_tests(
    model: _Model, plane, base_T_object: np.ndarray, covariance: np.ndarray,
    points: np.ndarray, sigma_table: float, sigma_points: float, z: float,
) -> HeightTests:  # fmt: skip
    """The model's lowest point against the table ``plane`` at the pose ``base_T_object``
    ``(4, 4)``, whose local error budget is ``covariance`` ``(6, 6)`` (right perturbation,
    object axes; non-finite entries, free axes, count as 0: a symmetry's turn leaves the
    shape in place).

    The lowest point's height ``h`` moves by ``J delta`` for a perturbation ``delta``
    (``J = [R^T n, c x R^T n]`` at the model point ``c``); its standard deviation is
    ``sqrt(J Sigma J^T + sigma_table^2 + mismatch^2)`` with ``sigma_table`` the depth noise at
    the table where the object stands (metres) and the model's mismatch. The pose sinks the
    model by ``-h``, allowed ``z`` of those; the segment's ``points`` ``(N, 3)`` reach below
    ``h`` by their ``LOW_QUANTILE`` height's shortfall, allowed ``z`` of those with the
    points' own noise ``sigma_points`` added, plus the quantile's noise offset."""
    rotation = np.asarray(base_T_object, np.float64)[:3, :3]
    translation = np.asarray(base_T_object, np.float64)[:3, 3]
    normal, offset = np.asarray(plane.normal, np.float64), float(plane.offset)
    model_points = model.points[np.all(np.isfinite(model.points), axis=1)].astype(np.float64)
    heights = (model_points @ rotation.T + translation) @ normal + offset
    low = int(np.argmin(heights))
    up = rotation.T @ normal
    jacobian = np.concatenate([up, np.cross(model_points[low], up)])
    sigma = np.where(np.isfinite(covariance), covariance, 0.0)
    pose_var = max(float(jacobian @ sigma @ jacobian), 0.0)
    mismatch = float(model.plane_offset)
    sunk_sigma = np.sqrt(pose_var + sigma_table**2 + mismatch**2)
    below = np.quantile(np.asarray(points, np.float64) @ normal + offset, LOW_QUANTILE)
    under_sigma = np.sqrt(pose_var + sigma_points**2 + mismatch**2)
    return HeightTests(
        sunk=float(-heights[low]),
        sunk_allowed=float(z * sunk_sigma),
        under=float(heights[low] - below),
        under_allowed=float(z * under_sigma + LOW_QUANTILE_SIGMAS * sigma_points),
    )
