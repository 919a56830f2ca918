"""The register stage's error budget: every source of a pose's error, propagated to the
covariance of the right perturbation of ``base_T_object`` (:mod:`jaxreg.uncertainty.budget`).

The registration fits the segment (base frame) into the model: ``object_T_base``, point-to-plane
residuals ``r_i = n_i . (object_T_base @ p_i - q_i)`` with the model point ``q_i`` nearest
the moved segment point ``p_i`` and its normal ``n_i``. With the pairs held fixed, a right
perturbation ``delta`` (base axes) of ``object_T_base`` changes ``r_i`` by ``J_i . delta``,
``J_i = (R^T n_i, p_i x R^T n_i)``; the normal equations ``H = sum_i J_i J_i^T`` and the implicit
function theorem turn any perturbation of the points into one of the pose. The terms:

* **fit**: the cluster-robust ("sandwich") covariance ``H^-1 (sum_b g_b g_b^T) H^-1`` of the
  residuals' gradients ``g_b = sum_{i in b} J_i r_i`` summed over spatial blocks ``b``: it sees
  the residuals as they are (model mismatch included) and noise that is correlated between
  neighbouring points (a stereo camera's matching window); the part beyond the depth term.
* **segmentation**: the segment re-registered with its membership changed (the mask's border
  eroded or grown by a few pixels, a contiguous piece of the visible part dropped), all
  perturbations in one vmapped ICP call; the second moment of the poses about the estimate.
* **calibration**: the user's hand-eye covariance, moved to the object in closed form (every
  lifted point moves rigidly with the camera, so the fitted pose does too), the intrinsics'
  uncertainty through the lifting's derivative and the normal equations, and the depth
  scale's by re-registering the segment lifted at one sigma either way (a scaled segment is
  also a larger or smaller object, whose fit slides sideways as its pairs change: more than
  the pairs held fixed predict).
* **ambiguity**: the second moment of the equally good starts about the answer.
"""

from __future__ import annotations

import jax
import numpy as np
from jaxlie import SE3
from scipy import ndimage
from scipy.spatial import cKDTree

from jaxreg.core._program_cache import persistent_jit
from jaxreg.core._threads import lane_pieces, split_lanes
from jaxreg.pipeline._answer import CONTACT_WEIGHT
from jaxreg.pipeline._judge import PATCH
from jaxreg.pipeline._lift_stage import lift_pixels, project_points
from jaxreg.pipeline._surface import depth_step
from jaxreg.registration.icp import ICPStatus, icp
from jaxreg.search.neighbors import cell_codes
from jaxreg.uncertainty.budget import combine

__all__ = ["Calibration", "pose_budget"]

def mismatch_sigma(model) -> float:
    """The standard deviation (metres) of the offset along the surface normal that the model
    and the sensed surface disagree on, shared by the points of a patch: what neither the depth
    noise nor the residuals show (the model's planes between its points, its edges and
    curvature). It is how far the model's tangent planes miss its own neighbouring points
    (:func:`~jaxreg.pipeline._model._plane_offset`): the offset a point-to-plane fit to this
    model leaves where the surface sensed is the model's own."""
    return float(model.plane_offset)


class Calibration:
    """The user's stated calibration uncertainty (host values).

    Attributes:
        hand_eye: ``(6, 6)`` covariance of the right perturbation of ``base_T_camera``
            (camera axes, ``(v, w)``, metres and radians), or ``None``.
        intrinsics_sigma: ``(4,)`` standard deviations of ``(fx, fy, cx, cy)`` in pixels.
        depth_scale_sigma: relative standard deviation of the depth scale (0.01 = 1%).
    """

    def __init__(self, hand_eye=None, intrinsics_sigma=None, depth_scale_sigma=0.0):
        if hand_eye is not None:
            hand_eye = np.asarray(hand_eye, np.float64)
            if hand_eye.shape != (6, 6) or not np.all(np.isfinite(hand_eye)):
                raise ValueError(
                    f"hand_eye_covariance must be a finite (6, 6) matrix, got {hand_eye.shape}"
                )
            if np.linalg.eigvalsh(0.5 * (hand_eye + hand_eye.T)).min() < -1e-12:
                raise ValueError("hand_eye_covariance must be positive semi-definite")
        sigma = np.zeros(4) if intrinsics_sigma is None else np.asarray(intrinsics_sigma, float)
        if sigma.shape != (4,) or np.any(~np.isfinite(sigma)) or np.any(sigma < 0):
            raise ValueError(
                "intrinsics_sigma must be 4 non-negative standard deviations (fx, fy, cx, cy) "
                f"in pixels, got {sigma}"
            )
        scale = float(depth_scale_sigma)
        if not np.isfinite(scale) or scale < 0:
            raise ValueError(f"depth_scale_sigma must be >= 0 (relative), got {scale}")
        self.hand_eye, self.intrinsics_sigma, self.depth_scale_sigma = hand_eye, sigma, scale


def _adjoint(wxyz_xyz: np.ndarray) -> np.ndarray:
    return np.asarray(SE3(np.asarray(wxyz_xyz, np.float64)).adjoint())


def _nearest_rows(moved, model_points, rows, distance):
    """Distance ``(K,)`` from each of ``moved`` ``(K, 3)`` to the nearest of the model points
    ``rows`` (``inf`` beyond ``distance`` or without rows) and that point's row."""
    if len(rows) == 0 or len(moved) == 0:
        return np.full(len(moved), np.inf), np.zeros(len(moved), np.int64)
    gap, index = cKDTree(model_points[rows]).query(moved, distance_upper_bound=distance)
    return gap, rows[np.minimum(index, len(rows) - 1)]


def _pairs(points, object_T_base, model_points, model_normals, distance, trim, eye, sensed):
    """The registration's pairs at the answer: segment points ``(K, 3)`` (base), their model
    normals ``(K, 3)`` (object frame), residuals ``(K,)`` and the rows of ``points`` kept
    ``(K,)``: those within ``distance`` of a model point with a usable normal (for the
    first ``sensed`` rows, with ``eye`` the camera's centre (base frame): one facing it, as
    ICP's viewpoint pairs them), the ``trim`` fraction with the smallest distances."""
    matrix = np.asarray(SE3(np.asarray(object_T_base, np.float64)).as_matrix(), np.float64)
    moved = points @ matrix[:3, :3].T + matrix[:3, 3]  # host numpy: no program per count
    usable = np.linalg.norm(model_normals, axis=1) > 0.5
    if eye is None:
        gap, index = _nearest_rows(moved, model_points, np.flatnonzero(usable), distance)
    else:
        camera = matrix[:3, :3] @ np.asarray(eye, np.float64) + matrix[:3, 3]
        facing = usable & (np.einsum("ij,ij->i", model_normals, camera - model_points) > 0)
        seen = _nearest_rows(moved[:sensed], model_points, np.flatnonzero(facing), distance)
        rest = _nearest_rows(moved[sensed:], model_points, np.flatnonzero(usable), distance)
        gap, index = (np.concatenate(pair) for pair in zip(seen, rest, strict=True))
    keep = np.flatnonzero(np.isfinite(gap))
    if trim < 1 and len(keep) > 3:
        keep = keep[np.argsort(gap[keep], kind="stable")[: max(3, int(trim * len(keep)))]]
    normals = model_normals[index[keep]]
    residual = np.einsum("ij,ij->i", normals, moved[keep] - model_points[index[keep]])
    return points[keep], normals, residual, keep


def _jacobian(points, normals, object_T_base) -> np.ndarray:
    """``(K, 6)`` rows ``J_i = (R^T n_i, p_i x R^T n_i)``."""
    rotation = np.asarray(SE3(np.asarray(object_T_base, np.float64)).rotation().as_matrix())
    n_base = normals @ rotation  # R^T n_i as rows
    return np.concatenate([n_base, np.cross(points, n_base)], axis=1)


def _blocks(points: np.ndarray, size: float) -> np.ndarray:
    """``(K,)`` int labels of the cubic cells of edge ``size`` holding ``points``."""
    return np.unique(cell_codes(np.floor(points / size)), return_inverse=True)[1].reshape(-1)


def _fit_term(jac, residual, blocks, inverse, depth_base) -> np.ndarray:
    """The cluster-robust covariance (base axes) beyond ``depth_base`` (its PSD excess)."""
    count = int(blocks.max()) + 1
    gradients = np.zeros((count, 6))
    np.add.at(gradients, blocks, jac * residual[:, None])
    correction = count / max(count - 6, 1)  # few blocks underestimate their spread
    sandwich = correction * inverse @ (gradients.T @ gradients) @ inverse
    excess = sandwich - depth_base
    values, vectors = np.linalg.eigh(0.5 * (excess + excess.T))
    return (vectors * np.clip(values, 0.0, None)) @ vectors.T


def _mismatch_term(jac, blocks, sensed, inverse, sigma: float) -> np.ndarray:
    """The covariance (base axes) of an offset ``~N(0, sigma^2)`` along the normal shared by
    the measured points of each block: ``sigma^2 H^-1 (sum_b s_b s_b^T) H^-1`` with
    ``s_b = sum_{i in b} J_i`` and ``inverse`` the normal equations' ``H^-1``."""
    count = int(blocks.max()) + 1
    sums = np.zeros((count, 6))
    np.add.at(sums, blocks[sensed], jac[sensed])
    return sigma**2 * inverse @ (sums.T @ sums) @ inverse


@persistent_jit
def _point_covariance(noise, points):
    """``noise.covariance(points)`` ``(N, 3, 3)`` as one stored program per padded size."""
    return noise.covariance(points)


def _depth_base(jac, points, noise, inverse, sensed) -> np.ndarray:
    """The depth noise's covariance (base axes) by the same normal equations, over the
    ``sensed`` ``(K,)`` rows (weight 1; the others carry no depth noise)."""
    n_base = jac[:, :3]  # R^T n_i on the sensed rows
    # one program for every count: the rows padded to a fixed size (a power of two)
    size = max(1024, 1 << (len(points) - 1).bit_length())
    padded = np.zeros((size, 3), np.float32)
    padded[: len(points)] = points
    cov = np.asarray(_point_covariance(noise, padded), np.float64)[: len(points)]
    variance = np.where(sensed, np.einsum("ki,kij,kj->k", n_base, cov, n_base), 0.0)
    return inverse @ (jac.T * variance) @ jac @ inverse


def _intrinsics_term(calibration, jac, points, frame, inverse):
    """The intrinsics' uncertainty (base axes), through the lifting's derivative: a camera
    point ``z ((u - cx) / fx, (v - cy) / fy, 1)`` moves by ``-x / fx`` per unit of ``fx`` and
    ``-z / fx`` per unit of ``cx`` (likewise in y)."""
    camera = frame.base_T_camera
    to_base = np.asarray(camera.rotation().as_matrix(), np.float64)
    cam = (points - np.asarray(camera.translation(), np.float64)) @ to_base
    fx, fy = float(frame.intrinsics.fx), float(frame.intrinsics.fy)
    zero = np.zeros(len(cam))
    x, y, z = cam.T
    moves = [  # camera-frame motion of each point per unit of each parameter
        (np.stack([-x / fx, zero, zero], 1), calibration.intrinsics_sigma[0]),
        (np.stack([zero, -y / fy, zero], 1), calibration.intrinsics_sigma[1]),
        (np.stack([-z / fx, zero, zero], 1), calibration.intrinsics_sigma[2]),
        (np.stack([zero, -z / fy, zero], 1), calibration.intrinsics_sigma[3]),
    ]
    n_base = jac[:, :3]  # R^T n_i, weighted like the rows of jac
    total = np.zeros((6, 6))
    for motion, sigma in moves:
        if sigma == 0:
            continue
        # residual change per unit, weighted like the rows of jac
        dr = np.einsum("ij,ij->i", n_base, motion @ to_base.T)
        step = -inverse @ (jac.T @ dr)  # the pose's change per unit (base axes)
        total += sigma**2 * np.outer(step, step)
    return total


def _pixels(frame, points: np.ndarray) -> np.ndarray:
    """``(K, 2)`` int (row, col) of base-frame ``points`` in ``frame`` (clipped to it),
    through the intrinsics' distortion (:func:`~jaxreg.pipeline._lift_stage.project_points`)."""
    camera = frame.base_T_camera
    cam = (points - np.asarray(camera.translation())) @ np.asarray(camera.rotation().as_matrix())
    u, v = project_points(frame, cam.astype(np.float32)).T
    h, w = frame.depth.shape
    return np.stack(
        [np.clip(np.rint(v), 0, h - 1).astype(int), np.clip(np.rint(u), 0, w - 1).astype(int)], 1
    )


RING = 3  # the widest border (pixels) eroded from or added to the mask


def _distances(mask: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W)`` Euclidean distances (pixels) of each pixel of ``mask`` to the nearest pixel
    outside it (0 outside), and of each pixel outside to the nearest one in it (0 inside;
    ``inf`` beyond ``margin``), computed on the mask's bounding box grown by ``margin``: the
    same distances as on the whole image (the box's border is outside the mask, nearer than
    anything beyond it), at a fraction of the cost."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    box = (
        slice(max(rows[0] - margin, 0), rows[-1] + margin + 1),
        slice(max(cols[0] - margin, 0), cols[-1] + margin + 1),
    )
    inside = np.zeros(mask.shape)
    outside = np.full(mask.shape, np.inf)
    inside[box] = ndimage.distance_transform_edt(mask[box])
    outside[box] = ndimage.distance_transform_edt(~mask[box])
    return inside, outside


# ICP iterations of a perturbed segment's fit (the last of the refinement's distances): it
# starts at the answer, and a changed membership moves the optimum by a fraction of a
# millimetre, within the last distances' reach.
PERTURBED_ITERATIONS = 8


def perturbed_segments(frame, mask, points, plane, min_height, size, rng, count=16, noise=None):
    """``(count, size, 3)`` float32 segments with their membership changed (NaN padding):
    a quarter with the mask's border eroded by 1-3 pixels, a quarter with the ring of 1-3
    pixels around it added (points above the table; with the camera's ``noise``, only the
    ring's pixels on one surface with the mask's, :func:`_continuing`), half with a contiguous
    ~15% piece of the visible part dropped. Each is subsampled to ``size`` points like the
    registered cloud."""
    inside, outside = _distances(mask, RING + 1)
    rows, cols = _pixels(frame, points).T
    border = inside[rows, cols]
    ring_r, ring_c = np.nonzero((outside > 0) & (outside <= RING))
    ring = np.asarray(lift_pixels(frame, ring_r, ring_c), np.float64)
    ring_ok = np.all(np.isfinite(ring), 1)
    if noise is not None:
        ring_ok &= _continuing(frame, mask, ring_r, ring_c, noise)
    if plane is not None:  # above the table band, as the lift keeps
        height = ring[ring_ok] @ np.asarray(plane.normal) + float(plane.offset)
        ring_ok[ring_ok] = height > min_height
    ring_depth, ring = outside[ring_r, ring_c][ring_ok], ring[ring_ok]
    out = np.full((count, size, 3), np.nan, np.float32)
    tree = cKDTree(points)
    for k in range(count):
        width = 1 + k % 3
        if k < count // 4:
            cloud = points[border > width]
        elif k < count // 2:
            cloud = np.concatenate([points, ring[ring_depth <= width]])
        else:
            centre = points[rng.integers(len(points))]
            _, drop = tree.query(centre, k=max(1, int(0.15 * len(points))))
            cloud = np.delete(points, np.atleast_1d(drop), axis=0)
        cloud = _subsample(cloud, size, rng)
        out[k, : len(cloud)] = cloud
    return out


def _subsample(cloud: np.ndarray, size: int, rng) -> np.ndarray:
    """``cloud`` ``(K, 3)`` cut to at most ``size`` rows drawn at random, in their order: how
    the registered cloud and every perturbed one are thinned."""
    if len(cloud) > size:
        cloud = cloud[np.sort(rng.choice(len(cloud), size, replace=False))]
    return cloud


def _continuing(frame, mask, rows, cols, noise) -> np.ndarray:
    """``(R,)`` bool: which pixels ``(rows, cols)`` outside ``mask`` ``(H, W)`` continue its
    surface: their depth within :func:`~jaxreg.pipeline._surface.depth_step` per pixel of
    distance of the nearest mask pixel's (the background behind an object, or an occluder in
    front, is a step away)."""
    depth = np.asarray(frame.depth, np.float64)
    if len(rows) == 0:
        return np.zeros(0, bool)
    top, left = max(rows.min() - RING - 1, 0), max(cols.min() - RING - 1, 0)
    box = (slice(top, rows.max() + RING + 2), slice(left, cols.max() + RING + 2))
    gap, (near_r, near_c) = ndimage.distance_transform_edt(~mask[box], return_indices=True)
    r, c = rows - top, cols - left
    z, z_near = depth[rows, cols], depth[near_r[r, c] + top, near_c[r, c] + left]
    sigma = np.polynomial.polynomial.polyval(z_near, np.asarray(noise.coefficients, np.float64))
    step = depth_step(z_near, sigma, float(frame.intrinsics.fx))
    return np.abs(z - z_near) <= step * gap[r, c]


@persistent_jit
def _perturbed_fits(sources, weights, points, normals, grid, init, distances, trim, eye, seen):
    """Point-to-plane ICP of every perturbed segment ``(P, N, 3)`` (rows weighted by
    ``weights`` ``(N,)``, NaN rows ignored) from ``init`` (7,), one iteration per
    correspondence distance of ``distances``, with ``eye`` the viewpoint
    of the ``seen`` rows ``(N,)`` (``None``: no viewpoint): the poses ``(P, 7)``, their
    ICP statuses and whether their residuals are finite ``(P,)``."""

    def one(source):
        usable = jax.numpy.all(jax.numpy.isfinite(source), axis=1)
        result = icp(
            source, points, SE3(init), method="point_to_plane", target_normals=normals,
            max_correspondence_distance=distances, max_iterations=distances.shape[0],
            trim_fraction=trim, source_weights=jax.numpy.where(usable, weights, 0.0),
            neighbors=grid, tolerance=1e-5, viewpoint=eye,
            viewpoint_rows=None if eye is None else seen,
        )  # fmt: skip
        return result.pose.wxyz_xyz, result.status, jax.numpy.isfinite(result.inlier_rmse)

    return jax.vmap(one)(sources)


def _fits_in_pieces(
    sources, weights, model, object_T_base, distances, trim, eye, source_size, iterations
):  # fmt: skip
    """:func:`_perturbed_fits` of ``sources`` ``(P, N, 3)`` from ``object_T_base`` (7,) over
    the last ``iterations`` of the refinement's ``distances``, the rows before
    ``source_size`` seen from ``eye``; run as one concurrent call per core on a piece of the
    sources (:func:`jaxreg.core._threads.split_lanes`): numpy poses ``(P, 7)``, statuses and
    finite flags ``(P,)``."""
    steps = np.asarray(distances, np.float32)[-iterations:]
    seen = np.arange(len(weights)) < source_size
    return split_lanes(
        lambda part: _perturbed_fits(
            part, weights, model.points, model.normals, model.fine_grid,
            np.asarray(object_T_base, np.float32), steps, np.float32(trim), eye, seen,
        ),
        np.asarray(sources, np.float32), lane_pieces(len(sources)),
    )  # fmt: skip


def _scaled(segment: np.ndarray, frame, sigma: float) -> np.ndarray:
    """``(2, N, 3)`` the ``segment`` ``(N, 3)`` (base frame) lifted with the depth scale off
    by ``-sigma`` and ``+sigma`` (relative): every point moved along its ray from the camera."""
    centre = np.asarray(frame.base_T_camera.translation(), np.float32)
    return np.stack([centre + (1 + s) * (segment - centre) for s in (-sigma, sigma)])


def _with_contact(segments: np.ndarray, contact: np.ndarray | None) -> np.ndarray:
    """``segments`` ``(P, N, 3)`` each followed by the table's ``contact`` rows ``(C, 3)``
    (``None``: none), as every fit of the budget registers them."""
    if contact is None:
        return segments
    return np.concatenate(
        [segments, np.broadcast_to(contact, (len(segments),) + contact.shape)], 1
    )


def _usable_fits(status, finite, usable) -> np.ndarray:
    """``(P,)`` bool: the fits whose residuals are ``finite`` and whose ICP ``status`` is one of
    the ``usable`` codes."""
    return np.asarray(finite) & np.any([np.asarray(status == code) for code in usable], axis=0)


def _tangents(base: np.ndarray, others: np.ndarray) -> np.ndarray:
    """``(P, 6)`` right-perturbation tangents (base axes) taking ``base`` (7,) to each of
    ``others`` ``(P, 7)`` (object_T_base)."""
    relative = SE3(np.asarray(base, np.float64)).inverse() @ SE3(np.asarray(others, np.float64))
    return np.asarray(relative.log())


def _free(symmetry, hessian_object: np.ndarray) -> tuple[np.ndarray, str | None]:
    """``(6,)`` bool free tangent axes (object axes) and why: the rotation about a continuous
    symmetry axis, and any direction the normal equations leave (nearly) unconstrained,
    each freeing the tangent axes it mostly spans."""
    free = np.zeros(6, bool)
    reasons = []
    if symmetry is not None and symmetry.axis is not None:
        axis = np.asarray(symmetry.axis, np.float64)
        free[3:] |= np.abs(axis) > 1e-6
        reasons.append(f"rotation about the symmetry axis {np.round(axis, 3).tolist()}")
    values, vectors = np.linalg.eigh(0.5 * (hessian_object + hessian_object.T))
    weak = values < 1e-6 * max(values.max(), 1e-300)
    for vector in vectors[:, weak].T:
        spans = np.abs(vector) > 0.5
        if not np.any(free & spans):
            free |= spans
            reasons.append("a motion the visible surface does not constrain")
    return free, ("; ".join(reasons) or None)


def pose_budget(
    *, points, source_size, model, object_T_base, pose, contact, frame, mask, plane,
    min_height, distances, trim, eye, noise, calibration, ambiguous, symmetry, view_free, rng,
    segmentation=None,
):  # fmt: skip
    """The error budget (:class:`~jaxreg.uncertainty.budget.PoseBudget`) of a refined pose,
    and its segmentation term ``(6, 6)`` as measured (object axes, before the free axes are
    set).

    Args:
        points: ``(K, 3)`` the lifted segment (base frame, metres).
        source_size: points per registered cloud (the refinement's ``max_points``).
        model: the prepared model (``points``, ``normals``, ``fine_grid``).
        object_T_base: ``(7,)`` wxyz_xyz of the refined answer.
        pose: ``(7,)`` the reported ``base_T_object`` (the answer on its symmetry branch).
        contact: ``(C, 3)`` the table's contact points the answer was settled with (base
            frame, NaN padding), or ``None``: part of every fit here, without depth noise.
        frame, mask, plane, min_height: the frame, the segment's pixels, the table plane and
            the lift's height floor (for the grown border).
        distances: the refinement's correspondence distances (metres), last the finest.
        trim: the refinement's trim fraction.
        eye: the refinement's ICP viewpoint (:func:`~jaxreg.pipeline._model.viewpoint`).
        noise: the camera's :class:`~jaxreg.uncertainty.DepthNoise` in the base frame.
        calibration: :class:`Calibration`.
        ambiguous: ``((A, 6), (A,))`` the answers about as good as this one (other refined
            starts, the answer turned and refined again) as right perturbations of ``pose``
            (object axes, on its symmetry branch), and each one's weight against the
            answer's 1 (how likely the evidence finds it): their weighted second moment,
            the answer included, is the ambiguity term.
        symmetry: the model's ``Symmetry`` or ``None``.
        view_free: ``((6,) bool, reason)``: tangent axes the view leaves free (a mug whose
            handle is hidden turns about its body's axis and fits as well), or no axis.
        rng: numpy Generator of the perturbations' draws.
        segmentation: ``((6, 6), why or None)`` a segmentation term measured before (object
            axes; the reason it could not be, or ``None``), used instead of re-registering
            perturbed segments; ``None``: measure it.
    """
    found = SE3(np.asarray(object_T_base, np.float64))
    branch = found @ SE3(np.asarray(pose, np.float64))  # the symmetry re-anchoring S
    # right perturbation of object_T_base (base axes) -> of pose (object axes)
    to_object = -_adjoint(np.asarray(branch.inverse().wxyz_xyz)) @ _adjoint(object_T_base)
    support = np.zeros((0, 3)) if contact is None else contact[np.all(np.isfinite(contact), 1)]
    measured = len(points)
    pairs_points, normals, residual, kept = _pairs(
        np.concatenate([points, support]).astype(np.float64), object_T_base,
        model.points.astype(np.float64), model.normals.astype(np.float64),
        float(distances[-1]), float(trim), eye, len(points),
    )  # fmt: skip
    sensed = kept < measured  # the contact points carry no depth noise
    weight = np.where(sensed, 1.0, np.sqrt(CONTACT_WEIGHT))[:, None]
    jac = _jacobian(pairs_points, normals, object_T_base) * weight
    residual = residual * weight[:, 0]
    hessian = jac.T @ jac
    inverse = np.linalg.pinv(hessian, rcond=1e-9, hermitian=True)
    depth_base = _depth_base(jac, pairs_points, noise, inverse, sensed)
    blocks = _blocks(pairs_points, PATCH)
    fit_base = _fit_term(jac, residual, blocks, inverse, depth_base)
    mismatch_base = _mismatch_term(jac, blocks, sensed, inverse, mismatch_sigma(model))

    weights = np.ones(source_size, np.float32)
    if contact is not None:
        weights = np.concatenate([weights, np.full(len(contact), CONTACT_WEIGHT, np.float32)])
    lift = np.linalg.inv(to_object)
    free, reason = _free(symmetry, lift.T @ hessian @ lift)
    usable = (ICPStatus.success, ICPStatus.max_iterations)
    if free.any():  # a fit degenerate along the free axes still pins the others
        usable += (ICPStatus.degenerate,)
    unknown = {}
    if segmentation is None:
        segmentation = _segmentation_term(
            points, source_size, model, object_T_base, contact, weights, frame, mask, plane,
            min_height, distances, trim, eye, noise, usable, to_object, rng,
        )  # fmt: skip
    if segmentation[1] is not None:
        unknown["segmentation"] = segmentation[1]

    calibration_base = _intrinsics_term(calibration, jac, pairs_points, frame, inverse)
    scale = np.zeros((6, 6))
    if calibration.depth_scale_sigma > 0:
        # the segment re-registered with the depth scale off by one sigma either way: its
        # response (along each ray, and sideways where the pairs change) as the fit makes it
        registered = np.full((1, source_size, 3), np.nan, np.float32)
        kept = _subsample(points, source_size, rng)
        registered[0, : len(kept)] = kept
        registered = _with_contact(registered, contact)[0]
        scaled_poses, scaled_status, scaled_finite = _fits_in_pieces(
            _scaled(registered, frame, calibration.depth_scale_sigma), weights, model,
            object_T_base, distances, trim, eye, source_size, 15,
        )  # fmt: skip
        if _usable_fits(scaled_status, scaled_finite, usable).all():
            steps = _tangents(object_T_base, np.asarray(scaled_poses)) @ to_object.T
            scale = steps.T @ steps / len(steps)
        else:
            unknown["calibration"] = (
                "the segment re-registered at the depth scale's +-1 sigma failed"
            )
    hand_eye = np.zeros((6, 6))
    if calibration.hand_eye is not None:
        # every lifted point moves with the camera: base_T_object' = base_T_camera exp(e)
        # camera_T_object = base_T_object exp(Ad_{object_T_camera} e), then re-anchored
        object_T_camera = found @ frame.base_T_camera
        ad = _adjoint(np.asarray(branch.inverse().wxyz_xyz)) @ _adjoint(
            np.asarray(object_T_camera.wxyz_xyz)
        )
        hand_eye = ad @ calibration.hand_eye @ ad.T

    others = np.asarray(ambiguous[0], np.float64).reshape(-1, 6)
    likelihood = np.asarray(ambiguous[1], np.float64)
    if np.any(view_free[0] & ~free):
        free = free | view_free[0]
        reason = "; ".join(r for r in (reason, view_free[1]) if r)
    terms = {
        "depth": to_object @ depth_base @ to_object.T,
        "fit": to_object @ fit_base @ to_object.T,
        "mismatch": to_object @ mismatch_base @ to_object.T,
        "segmentation": segmentation[0],
        "calibration": hand_eye + to_object @ calibration_base @ to_object.T + scale,
        "ambiguity": (others.T * likelihood) @ others / (1.0 + likelihood.sum()),
    }
    return combine(terms, free, reason, unknown=unknown), segmentation


def _segmentation_term(
    points, source_size, model, object_T_base, contact, weights, frame, mask, plane, min_height,
    distances, trim, eye, noise, usable, to_object, rng,
):  # fmt: skip
    """The budget's segmentation term (:func:`pose_budget`'s arguments; ``usable`` the ICP
    statuses a perturbed fit may end with, ``to_object`` the map of right perturbations of
    ``object_T_base`` to those of the reported pose): ``((6, 6)`` object axes, why it could
    not be measured or ``None``)."""
    segments = perturbed_segments(
        frame, mask, points, plane, min_height, source_size, rng, noise=noise
    )
    segments = _with_contact(segments, contact)
    poses, status, finite = _fits_in_pieces(
        segments, weights, model, object_T_base, distances, trim, eye, source_size,
        PERTURBED_ITERATIONS,
    )  # fmt: skip
    ok = _usable_fits(status, finite, usable)
    moved = (_tangents(object_T_base, np.asarray(poses)) @ to_object.T)[ok]
    why = None
    if len(moved) < len(segments) // 2:
        why = (
            f"{len(segments) - len(moved)} of the {len(segments)} re-registrations of the "
            "perturbed segment failed"
        )
    return moved.T @ moved / max(len(moved), 1), why
