"""Host-side set-up of an ICP problem, shared by every entry point that runs ICP
(:func:`jaxreg.icp`, :func:`jaxreg.multistart_icp`, :func:`jaxreg.icp_covariance`,
:func:`jaxreg.registration.init_spread`, :func:`jaxreg.studies.basin_sweep`, the pipeline): ICP's
options (:class:`ICPOptions`, the one place they and their defaults are written) and the keyword
form of them (:func:`resolve_options`), argument checks that raise ``ValueError``, masking and
padding of the clouds, the neighbour grid (built, or a given one validated), and the batched run
over starts. Public through :mod:`jaxreg.registration.solver`.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import weakref
from collections.abc import Mapping
from typing import Any, Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxlie import SE3
from jaxtyping import ArrayLike, Bool, Float

from jaxreg.core._leaves import as_array
from jaxreg.core._program_cache import persistent_jit
from jaxreg.core._sizes import bucket
from jaxreg.core._threads import lane_pieces, split_lanes
from jaxreg.geometry.kernels import L2, AbstractRobustKernel
from jaxreg.geometry.lie import se3_from_matrix
from jaxreg.registration._icp_core import LoopSettings, Problem, RegistrationResult, run_many
from jaxreg.registration.projective import ProjectiveAssociation
from jaxreg.search.neighbors import NeighborGrid, build_grid, validate_grid

Method = Literal["point_to_point", "point_to_plane"]

# A target normal is usable when finite and of unit length within this (|n| - 1).
NORMAL_TOLERANCE = 1e-3

# Given grids already checked: id(grid) -> (weak reference, digests of the checked inputs).
_CHECKED: dict[int, tuple[weakref.ref, set[bytes]]] = {}
_MAX_CHECKED = 64


class ICPOptions(eqx.Module):
    """ICP's options, taken by every entry point that runs ICP: :func:`jaxreg.icp`,
    :func:`jaxreg.multistart_icp`, :func:`jaxreg.icp_covariance`,
    :func:`jaxreg.registration.init_spread` and :func:`jaxreg.studies.basin_sweep` (as ``options=``,
    or field by field as keywords:
    ``jr.icp(s, t, method="point_to_plane", target_normals=n)`` is
    ``jr.icp(s, t, options=jr.ICPOptions(method="point_to_plane", target_normals=n))``; given
    both, the keywords replace those fields of ``options``). Frozen: derive a variant with
    ``dataclasses.replace(options, max_iterations=80)``. Checked against the clouds when a
    registration starts (``ValueError``), not when built.

    Attributes:
        method: ``"point_to_point"`` (default: minimise the 3D distance of each pair, a
            weighted Kabsch step) or ``"point_to_plane"`` (the distance along the target's
            normal, a Gauss-Newton step; needs ``target_normals``).
        target_normals: ``(M, 3)`` unit normals of the target, in target coordinates; only
            point-to-plane uses them. A point whose normal is not a finite unit vector (zero
            where :func:`jaxreg.estimate_normals` found none, or unnormalised) is excluded
            from matches and counts. Default ``None``.
        max_correspondence_distance: metres; pairs farther apart are rejected. A scalar
            (default ``0.02``), or a schedule ``(max_iterations,)`` giving the distance at each
            iteration (start wide, tighten).
        max_iterations: bound on the increments taken (default ``40``); static: it sizes
            ``rmse_history``, and a new value compiles a new loop.
        tolerance: convergence threshold (default ``1e-6``): the increment's translation
            (metres) and rotation angle (radians) both below it, or the inlier RMSE changing
            by less than this fraction of itself with the inlier count unchanged.
        kernel: robust kernel from :mod:`jaxreg.geometry.kernels` weighting each pair by its
            IRLS weight of the squared residual (its scale in metres); ``None`` (default) is
            least squares (:class:`~jaxreg.geometry.kernels.L2`).
        trim_fraction: keep only this best fraction (in ``(0, 1]``) of the accepted pairs at
            each iteration (trimmed ICP); match it to the expected overlap. ``None`` (default)
            keeps every accepted pair.
        source_weights: ``(N,)`` non-negative per-point weights of the source; 0 marks
            padding. ``None`` (default) weighs every point 1.
        neighbors: a prebuilt :class:`~jaxreg.search.neighbors.NeighborGrid` of the target
            (``build_grid(target, max_distance)``, ideally with ``mask=`` dropping points
            without a usable normal) whose ``max_distance`` covers the largest correspondence
            distance, to reuse across calls. ``None`` (default) builds one per call on a
            concrete target and searches by blocked brute force on a traced one.
        viewpoint: ``(3,)`` the sensor's position in source coordinates (point-to-plane
            only; the target normals must point out of the object, as a mesh's face normals
            do). Each iteration matches a source point only to target points whose normal
            faces the sensor at the current pose (``n . (pose @ viewpoint - q) > 0``): the
            back faces of a thin wall (a cup's inner face behind the outer one the sensor
            saw, 4 mm away) take no pairs; matched, they pull the answer toward the sensor
            by up to the wall's thickness, as the noise carries points nearer the back face.
            With a grid, a source point whose leaf lists only back faces (it lies nearer
            them than any front face) finds no match. ``None`` (default): every target
            point may be matched.
        viewpoint_rows: ``(N,)`` bool, the source rows the sensor at ``viewpoint`` saw
            (default every row); the others (points known another way, such as where an
            object touches a table) may match any face.
        association: a :class:`~jaxreg.registration.projective.ProjectiveAssociation` when
            the target is an organized cloud (``(H, W, 3)``, or its ``(H * W, 3)`` rows, and
            normals of the same shape): each source point's match is the nearest target
            point in a small window around its projection into the camera's image, at
            constant cost per point. ``None`` (default): the nearest target point
            (``neighbors``' grid or brute force).
    """

    method: Method = "point_to_point"
    target_normals: Float[ArrayLike, "M 3"] | None = None
    max_correspondence_distance: Float[ArrayLike, ""] | Float[ArrayLike, " I"] = 0.02
    max_iterations: int = 40
    tolerance: float = 1e-6
    kernel: AbstractRobustKernel | None = None
    trim_fraction: float | None = None
    source_weights: Float[ArrayLike, " N"] | None = None
    neighbors: NeighborGrid | None = None
    viewpoint: Float[ArrayLike, " 3"] | None = None
    viewpoint_rows: Bool[ArrayLike, " N"] | None = None
    association: ProjectiveAssociation | None = None


_DEFAULTS = ICPOptions()
_NAMES = tuple(field.name for field in dataclasses.fields(ICPOptions))


def resolve_options(
    options: ICPOptions | None, overrides: Mapping[str, Any], caller: str
) -> ICPOptions:
    """The options an ICP entry point runs with: ``options`` (the defaults when ``None``)
    with each keyword of ``overrides`` (an :class:`ICPOptions` field name) replacing that
    field. ``caller`` names the entry point in error messages.

    Raises:
        TypeError: ``options`` is not an :class:`ICPOptions`, or a keyword is not one of its
            fields (the message names it and the nearest field).
    """
    if options is None:
        options = _DEFAULTS
    elif not isinstance(options, ICPOptions):
        raise TypeError(
            f"{caller}(options=...) takes a jaxreg.ICPOptions, got {type(options).__name__}"
        )
    unknown = [name for name in overrides if name not in _NAMES]
    if unknown:
        hints = []
        for name in unknown:
            close = difflib.get_close_matches(name, _NAMES, n=1)
            hints.append(f"{name!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
        noun = "argument" if len(unknown) == 1 else "arguments"
        raise TypeError(
            f"{caller}() got unknown keyword {noun} {', '.join(hints)}; ICP's options are "
            f"{', '.join(_NAMES)} (see jaxreg.ICPOptions)"
        )
    return dataclasses.replace(options, **overrides) if overrides else options


def as_pose(init, dtype) -> SE3:
    """``init`` (``None`` for the identity, an ``SE3``, or ``(..., 4, 4)``) as an ``SE3``."""
    if init is None:
        return SE3(np.array([1, 0, 0, 0, 0, 0, 0], dtype))
    if isinstance(init, SE3):
        return SE3(jnp.asarray(init.wxyz_xyz, dtype))
    m = jnp.asarray(init, dtype)
    if m.shape[-2:] != (4, 4):
        raise ValueError(f"init must be a jaxlie.SE3 or a (..., 4, 4) matrix, got shape {m.shape}")
    return se3_from_matrix(m)


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def prepare(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    options: ICPOptions,
    *,
    grid_capacity: int | None = None,
) -> tuple[Problem, LoopSettings, tuple[int, int]]:
    """Checks ``options`` against the clouds and builds the solver's inputs.

    Returns the problem (clouds masked and padded to bucketed sizes), the loop's settings, and
    the caller's ``(N, M)`` for :func:`unpad`. Without ``options.neighbors`` a grid is built on
    a concrete target (``grid_capacity`` asks for shorter candidate lists: cheaper queries,
    slower build, falling back to the default when a leaf cannot fit them); a given grid is
    checked by :func:`jaxreg.search.neighbors.validate_grid` against the caller's target and the
    largest correspondence distance.

    Raises:
        ValueError: an unknown method; clouds not ``(N, 3)`` or empty; fewer than 3 source
            points; point-to-plane without ``(M, 3)`` normals; mis-shaped weights or
            distance schedule; a grid built on another target, for a smaller distance, or
            overflowed.
    """
    s = options
    if s.method not in ("point_to_point", "point_to_plane"):
        raise ValueError(f"method must be 'point_to_point' or 'point_to_plane', got {s.method!r}")
    user_target = target
    source = as_array(source)
    dtype = jnp.result_type(source.dtype, float)
    source = as_array(source, dtype)
    target = as_array(target, dtype)
    target_normals = None if s.target_normals is None else as_array(s.target_normals, dtype)
    if s.association is not None:
        target, target_normals = _organized(s, target, target_normals)
    for name, cloud in (("source", source), ("target", target)):
        if cloud.ndim != 2 or cloud.shape[-1] != 3:
            raise ValueError(f"{name} must have shape (N, 3), got {cloud.shape}")
        if cloud.shape[0] == 0:
            raise ValueError(f"{name} is empty: ICP needs points in both clouds")
    n = source.shape[0]
    if n < 3:
        raise ValueError(f"ICP needs at least 3 source points, got {n}")
    if s.method != "point_to_plane":
        target_normals = None
    else:
        if target_normals is None:
            raise ValueError(
                "point_to_plane needs target_normals (M, 3): see jaxreg.estimate_normals"
            )
        if target_normals.shape != target.shape:
            raise ValueError(
                f"target_normals must match target {target.shape}, got {target_normals.shape}"
            )
    viewpoint = rows = None
    if s.viewpoint is not None:
        if s.method != "point_to_plane":
            raise ValueError(
                "viewpoint needs method='point_to_plane' and target_normals (outward): it "
                "tells the faces of the target by their normals"
            )
        viewpoint = as_array(s.viewpoint, dtype)
        if viewpoint.shape != (3,):
            raise ValueError(f"viewpoint must have shape (3,), got {viewpoint.shape}")
        rows = np.ones(n, bool) if s.viewpoint_rows is None else s.viewpoint_rows
        rows = as_array(rows, bool)
        if rows.shape != (n,):
            raise ValueError(f"viewpoint_rows must have shape ({n},), got {rows.shape}")
        pad = np.pad if isinstance(rows, np.ndarray) else jnp.pad
        rows = pad(rows, (0, bucket(n) - n))  # padding rows weigh nothing: any face
    elif s.viewpoint_rows is not None:
        raise ValueError("viewpoint_rows needs a viewpoint")
    weights = np.ones(n, dtype) if s.source_weights is None else s.source_weights
    weights = as_array(weights, dtype)
    if weights.shape != (n,):
        raise ValueError(f"source_weights must have shape ({n},), got {weights.shape}")
    distances = as_array(s.max_correspondence_distance, dtype)
    if distances.ndim == 0:
        full = np.full if isinstance(distances, np.ndarray) else jnp.full
        distances = full((s.max_iterations,), distances, dtype)
    elif distances.shape != (s.max_iterations,):
        raise ValueError(
            "max_correspondence_distance is a scalar or a schedule with one distance per "
            f"iteration: shape ({s.max_iterations},), got {distances.shape}"
        )
    m = target.shape[0]
    source, weights, target, target_ok, target_normals = _clean(
        source, weights, target, target_normals, bucket(n) - n, bucket(m) - m
    )
    grid = s.neighbors
    if grid is not None:
        _check_given_grid(grid, user_target, distances, target_ok, m, s)
    elif s.association is None and _is_concrete(target) and _is_concrete(distances):
        points, ok = np.asarray(target), np.asarray(target_ok)
        if ok.any():  # else nothing to index: every query is invalid
            radius = float(np.max(np.asarray(distances)))
            grid = build_grid(points, radius, mask=ok, capacity=grid_capacity)
            if grid_capacity is not None and bool(grid.overflow):
                grid = build_grid(points, radius, mask=ok)
    problem = Problem(
        source, weights, target, target_ok, target_normals, grid, viewpoint, rows, s.association
    )
    opts = LoopSettings(
        method=s.method,
        max_iterations=int(s.max_iterations),
        distances=distances,
        tolerance=as_array(s.tolerance, dtype),
        kernel=L2() if s.kernel is None else s.kernel,
        trim_fraction=None if s.trim_fraction is None else as_array(s.trim_fraction, dtype),
    )
    return problem, opts, (n, m)


def _organized(options: ICPOptions, target, normals):
    """The organized ``target`` (and ``normals``) as ``(H * W, 3)`` rows for ``options``'
    projective association, checked against its image size."""
    association = options.association
    if not isinstance(association, ProjectiveAssociation):
        raise TypeError(
            "association must be a jaxreg.ProjectiveAssociation, got "
            f"{type(association).__name__}"
        )
    if options.neighbors is not None:
        raise ValueError(
            "neighbors= and association= are two ways to find matches: give one (a "
            "projective association needs no grid)"
        )
    width, height = association.intrinsics.width, association.intrinsics.height
    shaped = []
    for name, cloud in (("target", target), ("target_normals", normals)):
        if cloud is not None and cloud.ndim == 3:
            cloud = cloud.reshape(-1, cloud.shape[-1])
        if cloud is not None and cloud.shape != (association.pixels, 3):
            raise ValueError(
                f"with a projective association the {name} is organized: one row per pixel "
                f"of the {width} x {height} image, ({height}, {width}, 3) or "
                f"({association.pixels}, 3), got {cloud.shape}"
            )
        shaped.append(cloud)
    return shaped


def _check_given_grid(grid, user_target, distances, target_ok, m, s) -> None:
    """:func:`jaxreg.search.neighbors.validate_grid` and :func:`_check_grid_rows` on a grid
    the caller passed, once per (grid, target, normals, method, largest distance): a grid is
    built to be reused, and its checks cost more than the query (~2 ms on 4k points). A
    digest of the concrete inputs names what was checked; traced inputs are always checked
    (the checks skip what they cannot read)."""
    inputs = (user_target, distances, s.target_normals, grid.candidate_points)
    if not all(_is_concrete(x) for x in jax.tree.leaves(inputs)):
        validate_grid(grid, user_target, distances)
        _check_grid_rows(grid, target_ok, m, s.method)
        return
    digest = hashlib.blake2b(s.method.encode(), digest_size=16)
    for x in (user_target, np.max(np.asarray(distances)), s.target_normals):
        if x is not None:
            host = np.ascontiguousarray(x)
            digest.update(f"{host.shape} {host.dtype}".encode())
            digest.update(host.tobytes())
    entry = _CHECKED.get(id(grid))
    if entry is not None and entry[0]() is grid and digest.digest() in entry[1]:
        return
    validate_grid(grid, user_target, distances)
    _check_grid_rows(grid, target_ok, m, s.method)
    if entry is None or entry[0]() is not grid:
        entry = _CHECKED[id(grid)] = (weakref.ref(grid), set())
        while len(_CHECKED) > _MAX_CHECKED:
            del _CHECKED[next(iter(_CHECKED))]
    entry[1].add(digest.digest())


def _check_grid_rows(grid: NeighborGrid, target_ok, m: int, method: str) -> None:
    """Raises when a given grid indexes target rows that can never be a match (non-finite,
    or without a usable normal for point-to-plane): a query whose nearest point is such a
    row finds no match, although a valid target point may lie within the distance.
    ``target_ok`` is the padded target's validity, of which the first ``m`` rows are the
    caller's."""
    if not (_is_concrete(grid.candidate_index) and _is_concrete(target_ok)):
        return
    ok = np.asarray(target_ok)[:m]
    index = np.asarray(grid.candidate_index)
    rows = index[index < len(ok)]
    bad = np.unique(rows[~ok[rows]])
    if len(bad):
        what = "non-finite or without a finite unit normal" if method == "point_to_plane" else (
            "non-finite"
        )
        raise ValueError(
            f"the neighbors grid indexes {len(bad)} target points that are {what}: their "
            "answers would hide valid neighbours; build it with build_grid(target, distance, "
            "mask=...) excluding them"
        )


@persistent_jit
def _clean(source, source_weights, target, target_normals, n_pad: int, m_pad: int):
    """Masks unusable rows and pads both clouds to bucketed sizes, in one compiled call.

    NaN rows (depth holes) take no part and the arithmetic never sees them: a source row
    gets weight 0 and coordinates 0; a target row that is not finite, or whose normal is
    not a finite unit vector (``estimate_normals`` returns zeros where a normal is
    undefined), is moved far away and marked invalid, so it is never a match. Padding rows
    are zero-weight source rows and far, invalid target rows, so clouds of similar size
    share one compiled loop. Returns the source, its weights, the target, its validity mask
    and its normals (``None`` stays ``None``).
    """
    dtype = source.dtype
    source_ok = jnp.all(jnp.isfinite(source), -1)
    source_weights = jnp.where(source_ok, source_weights, 0.0)
    source = jnp.where(source_ok[:, None], source, 0.0)
    target_ok = jnp.all(jnp.isfinite(target), -1)
    if target_normals is not None:
        finite = jnp.all(jnp.isfinite(target_normals), -1)
        safe = jnp.where(finite[:, None], target_normals, 0.0)
        length = jnp.sqrt(jnp.sum(safe * safe, -1))
        target_ok &= finite & (jnp.abs(length - 1) <= NORMAL_TOLERANCE)
        target_normals = jnp.where(target_ok[:, None], target_normals, 0.0)
        target_normals = jnp.pad(target_normals, ((0, m_pad), (0, 0)))
    far = jnp.asarray(jnp.finfo(dtype).max / 4, dtype)  # never within any distance
    target = jnp.where(target_ok[:, None], target, far)
    return (
        jnp.pad(source, ((0, n_pad), (0, 0))),
        jnp.pad(source_weights, (0, n_pad)),
        jnp.pad(target, ((0, m_pad), (0, 0)), constant_values=far),
        jnp.pad(target_ok, (0, m_pad)),
        target_normals,
    )


@persistent_jit
def unpad(result: RegistrationResult, n: int, m: int) -> RegistrationResult:
    """Drops the padding rows of :func:`prepare` from a (possibly batched) result; the
    no-match sentinel becomes ``m``, the caller's target size. One compiled program (``n``
    and ``m`` static), kept with the solver's when the compilation cache is on."""
    index = result.correspondences[..., :n]
    return eqx.tree_at(
        lambda r: (r.correspondences, r.weights),
        result,
        (jnp.where(index >= m, m, index), result.weights[..., :n]),
    )


def run_starts(
    problem: Problem, opts: LoopSettings, sizes: tuple[int, int], inits
) -> RegistrationResult:
    """ICP from every start of ``inits`` (an ``SE3`` batch ``(S,)`` or ``(S, 4, 4)``) in one
    compiled program, sharded over ``jax.local_devices()`` when there are several, and on a
    single CPU device run as one concurrent call per core on a piece of the starts
    (:func:`jaxreg.core._threads.split_lanes`); every leaf of the (unpadded) result has the
    leading axis ``S``."""
    starts = as_pose(inits, problem.source.dtype)
    if len(starts.get_batch_axes()) != 1:
        raise ValueError(
            f"inits must have exactly one batch axis (S,), got {starts.get_batch_axes()}"
        )
    count = starts.wxyz_xyz.shape[0]
    pieces = lane_pieces(count) if _is_concrete(starts.wxyz_xyz) else 1
    if pieces > 1:  # one CPU device: a piece of the starts per core, run concurrently
        params = np.asarray(starts.wxyz_xyz)
        results = split_lanes(lambda part: run_many(problem, opts, SE3(part)), params, pieces)
        return unpad(results, *sizes)
    results = run_many(problem, opts, _shard_starts(starts))
    if results.pose.wxyz_xyz.shape[0] != count:
        results = results[:count]
    return unpad(results, *sizes)


def _shard_starts(starts: SE3) -> SE3:
    """Splits the start axis over this process's devices when it has more than one, padding
    it (with copies of the last start) to a multiple of the device count. Only the local
    devices: in a ``jax.distributed`` run each process registers its own problem (a device of
    another process would need that process to make the same call with the same data)."""
    devices = jax.local_devices()
    if len(devices) < 2:
        return starts
    params = starts.wxyz_xyz
    pad = -params.shape[0] % len(devices)
    params = jnp.concatenate([params, jnp.repeat(params[-1:], pad, axis=0)])
    mesh = jax.sharding.Mesh(np.array(devices), ("starts",))
    spec = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("starts"))
    return SE3(jax.device_put(params, spec))
