"""The register stage's tests of a refined pose against the frame's physical evidence, each
weighed against the sensor's noise at the pose's own uncertainty, with a stated false-refusal
rate (``RegisterSettings.false_refusal``, one-sided, per test) instead of fixed millimetres:

- :func:`beyond_model`: the refusals :func:`continuing` gives evidence for (the share the
  model explains, the segment's span beyond the model, its surface running on).
- :func:`continuing`: the segment's points that carry the model's surface on past its edge
  (a larger object of a similar shape). Points the model does not explain and that do not
  continue its surface (a neighbour's face meeting it at a crease, the background behind a
  mask's border, an occluder, the object it rests on) are explained away, not counted, as
  are those on a neighbour's edge a mask's border holds (:func:`carried_past`).
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
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from scipy.stats import norm

from jaxreg.pipeline._error_sources import _pixels, mismatch_sigma
from jaxreg.pipeline._judge import LATERAL_PIXELS, PATCH, patch_count
from jaxreg.pipeline._model import _Model
from jaxreg.pipeline._surface import depth_step
from jaxreg.search.normals import estimate_normals

__all__ = [
    "axis_noise",
    "beyond_model",
    "camera_depths",
    "carried_past",
    "continuing",
    "height_tests",
    "overhang",
]

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
# Independent patches (PATCH cubes) that segment points carrying the model's surface on past
# its edge must cover, and a patch's worth of voxels they must hold, before they say the object
# is larger than the model: one patch can be a mask's border on a neighbour flush with the
# object, or the model's own few millimetres; a few scattered points are flying pixels.
RUNS_ON_PATCHES = 2
# The 2% quantile of the segment's heights (underneath) lies this many depth-noise standard
# deviations below its points' true lowest height (a Gaussian's 2% quantile).
LOW_QUANTILE, LOW_QUANTILE_SIGMAS = 0.02, 2.054


def z_score(false_refusal: float) -> float:
    """The one-sided standard-normal quantile whose upper tail is ``false_refusal``."""
    return float(norm.isf(false_refusal))


def camera_depths(frame, points: np.ndarray) -> np.ndarray:
    """``(N,)`` the camera depth (metres, along its optical axis) of each base-frame point of
    ``points`` ``(N, 3)``."""
    camera = frame.base_T_camera
    axis = np.asarray(camera.rotation().as_matrix(), np.float64)[:, 2]
    return (np.asarray(points, np.float64) - np.asarray(camera.translation(), np.float64)) @ axis


def overhang(model: _Model, object_T_base: np.ndarray, points: np.ndarray) -> np.ndarray:
    """How far a segment spans beyond the model, along each of the model's principal axes
    (metres, ``(3,)``): the span of ``points`` ``(N, 3)`` (base frame) moved by
    ``object_T_base`` ``(7,)`` (wxyz_xyz), between their 2% and 98% quantiles, less the model's
    full span. An object's own points stay within its extent up to the depth noise, whatever
    part of it is visible (a partial view spans less: negative), so a positive overhang of
    several millimetres says the segment is a larger object of a similar shape, or the object
    merged with a neighbour. NaN without points."""
    if not len(points):
        return np.full(3, np.nan)
    rotation = Rotation.from_quat(np.asarray(object_T_base[:4], np.float64), scalar_first=True)
    moved = rotation.apply(np.asarray(points, np.float64)) + object_T_base[4:]
    along = (moved - model.centroid) @ model.axes
    low, high = np.quantile(along, [0.02, 0.98], axis=0)
    return (high - low) - (model.bounds[1] - model.bounds[0])


@dataclasses.dataclass(frozen=True)
class BeyondModel:
    """:func:`beyond_model`'s counts of the segment's points, its span beyond the model
    ``overhang`` ``(3,)`` (metres, along the model's principal axes, longest first) and the
    problems found (each a sentence for the refusal's reason; none when the model is there)."""

    explained_away: int
    runs_on: int
    overhang: np.ndarray
    problems: tuple[str, ...]


def beyond_model(
    frame, model: _Model, plane, object_T_base: np.ndarray, refined: np.ndarray,
    points: np.ndarray, gate: float, noise, z: float, min_share: float, voxel: float,
    lowest: float | None, region: np.ndarray | None = None, border: int = 0,
) -> BeyondModel:  # fmt: skip
    """The segment's ``points`` ``(N, 3)`` (base frame) that the model at the answer
    ``object_T_base`` ``(7,)`` does not explain (:func:`continuing`, with ``gate`` the fit's
    final correspondence distance), judged at ``z`` sigma of the noise (``noise`` the
    camera's ``DepthNoise``):

    - the share the model explains of the points it could (all but those explained away) is
      at least ``min_share``;
    - the points not explained away span beyond the model, at ICP's ``refined`` pose
      ``(7,)``, by at most ``z`` sigma of the sensor's noise along each of the model's axes
      (:func:`axis_noise`) and of the model's mismatch;
    - fewer than a ``PATCH``'s worth of ``voxel`` cells, or fewer than ``RUNS_ON_PATCHES``
      patches, carry the model's surface on past its edge.

    The table's own points (up to ``2 z sigma`` above the table ``plane``, past the lift's
    band) run on no face, nor do those within ``2 z sigma`` of ``lowest``, the model's lowest
    height above the table at the answer (metres; ``None`` without a table): the top of a box
    the object lies on, in the plane of its hidden bottom. Nor do those within ``border``
    pixels of a caller's mask's ``region`` ``(H, W)`` whose surface carries on outside it
    (:func:`carried_past`): a neighbour's edge the mask's border holds."""
    depths = camera_depths(frame, points)
    sigmas = np.asarray(noise.axial_sigma(depths), np.float64)
    explained, runs_on = continuing(
        model, object_T_base, points, gate, z * np.hypot(sigmas, mismatch_sigma(model))
    )
    if plane is not None:  # the table's own points, and the top of what the model rests on
        height = np.asarray(plane.height(points), np.float64)
        runs_on &= (height > 2 * z * sigmas) & (np.abs(height - lowest) > 2 * z * sigmas)
    if region is not None and border and runs_on.any():  # a neighbour the mask's border holds
        runs_on[runs_on] = ~carried_past(frame, region, points[runs_on], noise, border)
    away = int((~explained & ~runs_on).sum())
    problems = []
    share = explained.sum() / max(int((explained | runs_on).sum()), 1)
    if share < min_share:
        problems.append(
            f"the model explains only {share:.0%} of the segment points it could (need "
            f"{min_share:.0%}; {away} more lie off its surface: a neighbour, the background or "
            "an occluder)"
        )
    kept = points[explained | runs_on]
    reach = overhang(model, refined, kept)
    reach_allowed = z * np.hypot(axis_noise(frame, model, refined, kept, noise),
                                 mismatch_sigma(model))  # fmt: skip
    if not np.isfinite(reach).all():
        problems.append(
            "the segment's span beyond the model could not be measured (NaN: a non-finite "
            "pose or segment point)"
        )
    elif np.any(reach > reach_allowed):
        axis = int(np.argmax(reach - reach_allowed))
        problems.append(
            f"the segment's points on the model's surface span {reach[axis] * 1e3:.0f} mm "
            f"beyond the model along its {('longest', 'middle', 'shortest')[axis]} axis (at "
            f"most {reach_allowed[axis] * 1e3:.1f}: {z:.1f} sigma of the sensor's noise along "
            "that axis and of the model's mismatch): a larger object of a similar shape"
        )
    if runs_on.sum() >= (PATCH / voxel) ** 2 and patch_count(points[runs_on]) >= RUNS_ON_PATCHES:
        problems.append(
            f"{int(runs_on.sum())} segment points carry the model's surface on past its edge "
            f"(farther than {gate * 1e3:.1f} mm from it, in its faces' planes within {z:.1f} "
            "sigma of the depth noise): a larger object of a similar shape, or a neighbour "
            "flush with it; give a mask= that leaves the neighbour out"
        )
    return BeyondModel(away, int(runs_on.sum()), reach, tuple(problems))


def axis_noise(frame, model: _Model, object_T_base: np.ndarray, points: np.ndarray,
               noise) -> np.ndarray:  # fmt: skip
    """``(3,)`` the sensor's noise (metres, RMS over ``points`` ``(N, 3)``, base frame) along
    each of the model's principal axes at the pose ``object_T_base`` ``(7,)``: a point's depth
    noise (``noise.axial_sigma``) lies along the camera's ray through it and its lateral noise
    (``LATERAL_PIXELS`` at its depth) across it, so an axis the camera looks along spreads by
    the depth noise and one across its view by a pixel's width. NaN without points."""
    if not len(points):
        return np.full(3, np.nan)
    points = np.asarray(points, np.float64)
    rays = points - np.asarray(frame.base_T_camera.translation(), np.float64)
    rays /= np.maximum(np.linalg.norm(rays, axis=1, keepdims=True), 1e-12)
    rotation = Rotation.from_quat(np.asarray(object_T_base[:4], np.float64), scalar_first=True)
    along = (rotation.apply(rays) @ model.axes) ** 2  # (N, 3) squared cosines
    depths = camera_depths(frame, points)
    axial = np.asarray(noise.axial_sigma(depths), np.float64)[:, None]
    lateral = (depths * LATERAL_PIXELS / float(frame.intrinsics.fx))[:, None]
    return np.sqrt(np.mean(axial**2 * along + lateral**2 * (1.0 - along), axis=0))


def carried_past(frame, region: np.ndarray, points: np.ndarray, noise, border: int) -> np.ndarray:
    """``(N,)`` bool: which of ``points`` ``(N, 3)`` (base frame, seen in ``region`` ``(H, W)``)
    lie on a surface that carries on outside the region: the nearest pixel outside it with
    depth is at most ``border`` pixels from the point's, and its depth differs from the
    point's by at most :func:`~jaxreg.pipeline._surface.depth_step` (the steps of a surface
    seen by a noisy camera, ``noise``) for each pixel between them. Across the object's own
    silhouette the depth steps to the background or the table behind it; a neighbour that a
    mask's border holds carries on."""
    depth = np.asarray(frame.depth, np.float64)
    outside = ~np.asarray(region, bool) & np.isfinite(depth)
    if not outside.any():
        return np.zeros(len(points), bool)
    distance, (rows, cols) = ndimage.distance_transform_edt(~outside, return_indices=True)
    row, col = _pixels(frame, np.asarray(points, np.float64)).T
    z = camera_depths(frame, points)
    step = depth_step(z, np.asarray(noise.axial_sigma(z), np.float64), float(frame.intrinsics.fx))
    apart = distance[row, col]
    beyond = depth[rows[row, col], cols[row, col]]
    return (apart <= border) & (np.abs(beyond - z) <= apart * step)


def continuing(
    model: _Model, object_T_base: np.ndarray, points: np.ndarray, gate: float,
    allowed: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Which of the segment's ``points`` ``(N, 3)`` (base frame) the model explains at the
    pose ``object_T_base`` ``(7,)`` (within ``gate`` metres, the fit's final correspondence
    distance), and which carry the model's surface on past its edge (``(N,)`` bool each):
    farther than ``gate`` from every model point, outside the model's convex hull
    (:func:`_outside_hull`) and past the model's edge (:func:`_past_edge`), with half or more
    of the segment's explained or running-on points within ``GROW_RADIUS`` gates of it
    (``IN_PLANE`` at least) in its tangent plane (its normal from its ``NORMAL_NEIGHBOURS``
    segment neighbours; ``allowed`` ``(N,)`` metres off it), grown from the explained points
    outward for up to ``GROW_STEPS`` steps: the measured surface runs on flat across the
    model's edge. A real object's own surface stays within the gate of its model; a larger
    object's face runs on past it; a touching neighbour's face meets the model's at a crease,
    the background or an occluder lies off it, and depth across a concavity (smeared over the
    narrow gap between a clamp's jaws, or something lying in a bowl) lies within the hull."""
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
    outside = _outside_hull(model.hull, moved[far]) > 0
    past_edge = _past_edge(tree, model.points[rows], moved[far], normals[far])
    past = np.flatnonzero(far)[past_edge & outside]
    runs_on = np.zeros(len(points), bool)
    if not len(past):
        return ~far, runs_on
    nearby = cKDTree(moved).query_ball_point(moved[past], GROW_RADIUS * gate)
    for _ in range(GROW_STEPS):  # from the explained points outward, one radius a step
        grown = False
        for k, i in enumerate(past):
            if runs_on[i]:
                continue
            others = [j for j in nearby[k] if (~far[j] or runs_on[j]) and j != i]
            if len(others) < IN_PLANE:
                continue
            across = np.abs((moved[others] - moved[i]) @ normals[i])
            if np.mean(across <= allowed[i]) >= 0.5:
                runs_on[i] = grown = True
        if not grown:
            break
    return ~far, runs_on


def _outside_hull(hull: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(N,)`` how far each of ``points`` ``(N, 3)`` (object frame) lies outside the model's
    convex ``hull`` ``(F, 4)`` (``_Model.hull``; metres along the farthest facet's normal, 0 or
    less inside). A surface the model lacks inside its hull fills a concavity (depth smeared
    across a clamp's jaws, a mug's handle): it does not make the object larger."""
    return np.max(points @ hull[:, :3].T + hull[:, 3], axis=1)


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
