"""Studies: sweeps of thousands of registrations that answer one question each.

* :func:`basin_sweep`: how far from the truth can ICP start and still find it? Starts at
  controlled rotation offsets (and optional translation offsets) from the true pose, all
  registered in one compiled call sharded over every device of every process, scored with
  the symmetry-aware metrics of :mod:`jaxreg.geometry.metrics`.
* :func:`repeatability`: is my error noise or bias, and whose? The three tiers (frozen
  scene re-measured, object re-placed, camera moved) on synthetic scenes, with the
  per-viewpoint bias test and the error budget against a gripper's margin.
* :func:`estimate_hand_eye_correction`: the hand-eye correction that makes the viewpoints
  agree, by differentiating through lifting and registration.
  (In :mod:`jaxreg.studies._repeatability` and :mod:`jaxreg.studies._hand_eye`; the study needs the
  ray caster of :mod:`jaxreg.synth.scenes`.)

Scale-out uses JAX's own runtime, nothing else: the starts are one array sharded over a 1-D
mesh of ``jax.devices()``. On one machine that is every local device (force several CPU
devices with ``XLA_FLAGS=--xla_force_host_platform_device_count=N``; on a single CPU
device each chunk of starts runs as one concurrent call per core,
:func:`jaxreg.core._threads.split_lanes`); in processes started with
``jax.distributed.initialize`` it is every device of every process, each process
registers the starts on its own devices, and every process receives the whole result. Call
the study with the same arguments in every process (the starts are drawn from ``key``, the
same everywhere). On CPU the processes need gloo collectives, which only the caller may
choose: ``jax.config.update("jax_cpu_collectives_implementation", "gloo")`` before
``jax.distributed.initialize``.

Conventions (those of :mod:`jaxreg.registration.icp`): ``truth`` and every pose map source
coordinates into target coordinates; angles in degrees at this interface, distances in the clouds'
units (metres).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jaxlie import SE3, SO3
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxreg.core._program_cache import persistent_jit
from jaxreg.core._threads import lane_pieces, split_lanes
from jaxreg.geometry.metrics import Symmetry, pose_error
from jaxreg.registration.solver import ICPOptions, ICPStatus, prepare, resolve_options, run
from jaxreg.studies._hand_eye import HandEyeCorrection, estimate_hand_eye_correction
from jaxreg.studies._repeatability import Repeatability, repeatability

__all__ = [
    "BasinSweep",
    "HandEyeCorrection",
    "Repeatability",
    "basin_radius",
    "basin_starts",
    "basin_sweep",
    "estimate_hand_eye_correction",
    "lesson_cube",
    "repeatability",
]


class BasinSweep(eqx.Module):
    """Result of :func:`basin_sweep`: ``A`` angles, ``T`` translation offsets, ``S`` starts
    per cell; per-start fields have shape ``(A, T, S)``.

    Attributes:
        angles_deg: ``(A,)`` rotation offset of the starts from the truth (degrees).
        translation_offsets: ``(T,)`` translation offset of the starts' source centroid.
        init: ``SE3`` batch ``(A, T, S)``, the starts.
        pose: ``SE3`` batch ``(A, T, S)``, where ICP ended.
        status: :class:`jaxreg.ICPStatus` per start.
        converged: ICP's own test passed (``status == success``).
        iterations: increments taken.
        inlier_rmse: at the final pose (distance units).
        inlier_fraction: at the final pose.
        rotation_error_deg: geodesic angle to the nearest symmetric equivalent of the truth.
        translation_error: ``|t - t_truth|`` (distance units).
        success: both errors within the sweep's success thresholds.
        confidently_wrong: ``converged & ~success``: ICP reports success at a wrong pose.
        success_rate: ``(A, T)`` fraction of successful starts per cell.
        basin_radius_deg: ``(T,)`` :func:`basin_radius` of each translation offset's column.
    """

    angles_deg: Float[Array, " A"]
    translation_offsets: Float[Array, " T"]
    init: SE3
    pose: SE3
    status: ICPStatus
    converged: Bool[Array, "A T S"]
    iterations: Int[Array, "A T S"]
    inlier_rmse: Float[Array, "A T S"]
    inlier_fraction: Float[Array, "A T S"]
    rotation_error_deg: Float[Array, "A T S"]
    translation_error: Float[Array, "A T S"]
    success: Bool[Array, "A T S"]
    confidently_wrong: Bool[Array, "A T S"]
    success_rate: Float[Array, "A T"]
    basin_radius_deg: Float[Array, " T"]


def lesson_cube(angle_deg: float = 15.0, n: int = 800, seed: int = 0):
    """The lesson's basin experiment: ``n`` points uniform in a 6 cm cube (the model) and the
    scene: the model turned ``angle_deg`` about z, shifted by (10, -20, 5) mm, with 2 mm
    Gaussian noise. Returns ``(model (n, 3), scene (n, 3), truth)``: float32 clouds and the
    model -> scene ``SE3``, ready for :func:`basin_sweep`."""
    rng = np.random.default_rng(seed)
    model = rng.uniform(-0.03, 0.03, (n, 3)).astype(np.float32)
    truth = SE3.from_rotation_and_translation(
        SO3.from_z_radians(np.deg2rad(angle_deg)), jnp.array([0.01, -0.02, 0.005])
    )
    scene = np.asarray(truth @ model) + rng.normal(0.0, 0.002, model.shape)
    return model, scene.astype(np.float32), truth


def basin_starts(
    source: Float[ArrayLike, "N 3"],
    truth: SE3,
    *,
    angles_deg: Float[ArrayLike, " A"],
    samples_per_angle: int,
    key: Array,
    translation_offsets: Float[ArrayLike, " T"] | None = None,
) -> SE3:
    """The starts of :func:`basin_sweep`, an ``SE3`` batch ``(A, T, S)``.

    Start ``(a, t, s)`` turns the source about its centroid ``c`` (finite rows) by
    ``angles_deg[a]`` about a uniform random axis, then moves it by
    ``translation_offsets[t]`` along a uniform random direction (target frame):
    ``init = Trans(d u) @ truth @ Trans(c) @ Rot(axis, angle) @ Trans(-c)``. Its geodesic
    rotation error is exactly the angle and its source centroid lies exactly the offset
    away from where the truth puts it. Axes and directions are drawn independently for
    every start by numpy's generator seeded with ``key``'s data (no compilation).
    """
    angles = np.asarray(angles_deg, np.float64).reshape(-1)
    offsets = np.zeros(1) if translation_offsets is None else np.asarray(translation_offsets)
    offsets = np.asarray(offsets, np.float64).reshape(-1)
    src = np.asarray(source, np.float64)
    c = src[np.all(np.isfinite(src), -1)].mean(0)
    shape = (angles.size, offsets.size, samples_per_angle)
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
    axes = _unit_vectors(rng, shape)
    directions = _unit_vectors(rng, shape)
    # Host arithmetic in float64 (nothing to compile): the turn about c is the rotation q
    # with translation c - q c; composed with the truth, then shifted.
    half = np.deg2rad(angles)[:, None, None, None] / 2
    q = np.concatenate([np.broadcast_to(np.cos(half), (*shape, 1)), np.sin(half) * axes], -1)
    params = np.asarray(truth.wxyz_xyz, np.float64)
    rotation = _quaternion_matrix(params[:4])
    offset = c - np.einsum("...ij,j->...i", _quaternion_matrix(q), c)
    translation = offset @ rotation.T + params[4:] + directions * offsets[None, :, None, None]
    wxyz = _quaternion_product(params[:4], q)
    wxyz *= np.where(wxyz[..., :1] < 0, -1.0, 1.0)
    dtype = jnp.asarray(truth.wxyz_xyz).dtype
    return SE3(jnp.asarray(np.concatenate([wxyz, translation], -1), dtype))


def _quaternion_product(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a b`` of quaternions ``(..., 4)`` (``wxyz``)."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        -1,
    )


def _quaternion_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` (``wxyz``)."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _unit_vectors(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """Uniform random unit vectors ``(*shape, 3)``."""
    v = rng.normal(size=(*shape, 3))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def basin_radius(angles_deg: Float[ArrayLike, " A"], success_rate: ArrayLike, level: float):
    """The start angle at which the success rate first falls below ``level``, linearly
    interpolated between the two sampled angles around the crossing.

    ``angles_deg (A,)`` increasing; ``success_rate (A, ...)``; returns ``(...)``. The
    largest sampled angle when the rate never falls below ``level`` (the basin is at least
    that wide); 0 when it is already below at the smallest angle.
    """
    angles = np.asarray(angles_deg, np.float64)
    rate = np.asarray(success_rate, np.float64)
    below = rate < level
    first = np.argmax(below, axis=0)
    radius = np.where(below.any(axis=0), 0.0, angles[-1])
    for index in np.ndindex(rate.shape[1:]):
        i = first[index]
        if not below[(slice(None), *index)].any() or i == 0:
            continue
        r0, r1 = rate[(i - 1, *index)], rate[(i, *index)]
        radius[index] = angles[i - 1] + (r0 - level) / (r0 - r1) * (angles[i] - angles[i - 1])
    return radius


def _scores(problem, opts, starts, truth, symmetry, thresholds):
    """ICP from every start of ``starts`` ``(S, 7)`` and its scores (one device's share)."""
    result = jax.vmap(run, in_axes=(None, None, 0))(problem, opts, SE3(starts))
    t_err, r_err = pose_error(result.pose, SE3(truth), symmetry=symmetry)
    r_deg = jnp.rad2deg(r_err)
    success = (r_deg <= thresholds[0]) & (t_err <= thresholds[1])
    return dict(
        pose=result.pose.wxyz_xyz,
        status=result.status,
        converged=result.converged,
        iterations=result.iterations,
        inlier_rmse=result.inlier_rmse,
        inlier_fraction=result.inlier_fraction,
        rotation_error_deg=r_deg,
        translation_error=t_err,
        success=success,
    )


# One device: the same scores as a stored program (jaxreg.enable_compilation_cache's folder
# serves a fresh process the executable without tracing), run on pieces of the starts.
_scores_stored = persistent_jit(_scores)


@eqx.filter_jit
def _register_shard(problem, opts, starts, truth, symmetry, thresholds, mesh):
    """:func:`_scores` with the start axis split over ``mesh``: each device runs its own loop
    over its own starts (``shard_map``), so the loop needs no collective per iteration and a
    device stops when its own starts have finished."""
    whole, split = jax.sharding.PartitionSpec(), jax.sharding.PartitionSpec("starts")
    return jax.shard_map(
        _scores,
        mesh=mesh,
        in_specs=(whole, whole, split, whole, whole, whole),
        out_specs=split,
        check_vma=False,
    )(problem, opts, starts, truth, symmetry, thresholds)


def _host(tree):
    """Every JAX array of ``tree`` as a numpy array: replicated constants that a jitted call
    over a mesh of any process's devices accepts."""
    return jax.tree.map(lambda x: np.asarray(x) if isinstance(x, jax.Array) else x, tree)


def basin_sweep(
    source: Float[ArrayLike, "N 3"],
    target: Float[ArrayLike, "M 3"],
    truth: SE3,
    *,
    angles_deg: Float[ArrayLike, " A"],
    samples_per_angle: int,
    key: Array,
    translation_offsets: Float[ArrayLike, " T"] | None = None,
    symmetry: Symmetry | None = None,
    success_rotation_deg: float = 5.0,
    success_translation: float = 0.01,
    basin_level: float = 0.9,
    chunk_size: int | None = None,
    progress: Callable[[int, int], None] | None = None,
    options: ICPOptions | None = None,
    **overrides: Any,
) -> BasinSweep:
    """ICP's basin of attraction around ``truth``: success rate against start offset.

    Draws :func:`basin_starts` (``samples_per_angle`` uniform random axes for every angle
    and translation offset), runs ICP from all of them in one compiled function whose start
    axis is sharded over ``jax.devices()`` (padded to a multiple of the device count), and
    scores each end pose against ``truth``: a start succeeds when its rotation error (the
    smallest over ``symmetry``, :func:`jaxreg.geometry.metrics.pose_error`) is at most
    ``success_rotation_deg`` and its translation error at most ``success_translation``.
    The same arguments give the same answer on any number of devices and processes (see the
    module docstring for several processes).

    Args:
        source: ``(N, 3)`` source (model) points.
        target: ``(M, 3)`` target (scene) points.
        truth: the true source -> target ``SE3``.
        angles_deg: ``(A,)`` rotation offsets, increasing (degrees).
        samples_per_angle: ``S``, starts per angle and translation offset.
        key: ``jax.random`` key for the axes and directions.
        translation_offsets: ``(T,)`` offsets of the source centroid (distance units);
            ``(0,)`` by default.
        symmetry: the source object's :class:`jaxreg.Symmetry` (object origin on its
            axes), so that an equivalent pose counts as success.
        success_rotation_deg, success_translation: success thresholds.
        basin_level: the success rate that bounds the basin (:func:`basin_radius`).
        chunk_size: register at most this many starts per call (rounded up to a multiple
            of the device count; one compilation serves every chunk); all at once by
            default.
        progress: called as ``progress(done, total)`` after each chunk.
        options: ICP's options (:class:`jaxreg.ICPOptions`); its defaults when ``None``.
        **overrides: fields of :class:`jaxreg.ICPOptions` by name (``method=``,
            ``max_correspondence_distance=``, ...), replacing those of ``options``.

    Returns:
        :class:`BasinSweep`, every field on every process.

    Raises:
        ValueError: angles not increasing or negative, ``samples_per_angle < 1``, a
            non-positive threshold, ``basin_level`` outside ``(0, 1]``, or any of
            :func:`jaxreg.icp`'s.
        TypeError: a keyword that is not a field of :class:`jaxreg.ICPOptions`.
    """
    angles = np.asarray(angles_deg, np.float64)
    if angles.ndim != 1 or angles.size == 0 or np.any(np.diff(angles) <= 0) or angles[0] < 0:
        raise ValueError(f"angles_deg must be (A,) non-negative and increasing, got {angles}")
    if samples_per_angle < 1:
        raise ValueError(f"samples_per_angle must be at least 1, got {samples_per_angle}")
    if not (success_rotation_deg > 0 and success_translation > 0):
        raise ValueError("success_rotation_deg and success_translation must be positive")
    if not 0 < basin_level <= 1:
        raise ValueError(f"basin_level must lie in (0, 1], got {basin_level}")
    if not isinstance(truth, SE3) or truth.get_batch_axes() != ():
        raise ValueError("truth must be one (unbatched) jaxlie.SE3")
    options = resolve_options(options, overrides, "basin_sweep")
    problem, opts, _ = prepare(source, target, options, grid_capacity=24)
    dtype = problem.source.dtype
    starts = basin_starts(
        source, truth, angles_deg=angles, samples_per_angle=samples_per_angle, key=key,
        translation_offsets=translation_offsets,
    )  # fmt: skip
    shape = starts.get_batch_axes()
    flat = np.asarray(starts.wxyz_xyz, dtype).reshape(-1, 7)
    total = flat.shape[0]
    devices = jax.devices()
    chunk = total if chunk_size is None else min(int(chunk_size), total)
    chunk = -(-max(chunk, 1) // len(devices)) * len(devices)
    count = -(-total // chunk)
    flat = np.concatenate([flat, np.repeat(flat[-1:], count * chunk - total, axis=0)])
    mesh = jax.sharding.Mesh(np.array(devices), ("starts",))
    sharding = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("starts"))
    constants = _host(
        (problem, opts, np.asarray(truth.wxyz_xyz, dtype), symmetry,
         np.array([success_rotation_deg, success_translation], dtype))
    )  # fmt: skip
    # One device (a CPU): a piece of each chunk per core, run concurrently.
    pieces = lane_pieces(chunk) if len(devices) == 1 else 1

    def scores(part):
        return _scores_stored(constants[0], constants[1], part, *constants[2:])

    parts = []
    for i in range(count):
        block = flat[i * chunk : (i + 1) * chunk]
        if pieces > 1:
            parts.append(split_lanes(scores, block, pieces))
        else:
            sharded = jax.make_array_from_callback(block.shape, sharding, block.__getitem__)
            out = _register_shard(constants[0], constants[1], sharded, *constants[2:], mesh)
            parts.append(multihost_utils.process_allgather(out, tiled=True))
        if progress is not None:
            progress(min((i + 1) * chunk, total), total)
    out = jax.tree.map(
        lambda *xs: np.concatenate(xs)[:total].reshape(*shape, *xs[0].shape[1:]), *parts
    )
    rate = out["success"].mean(-1)
    return BasinSweep(
        angles_deg=jnp.asarray(angles, dtype),
        translation_offsets=jnp.asarray(
            np.zeros(1) if translation_offsets is None else translation_offsets, dtype
        ).reshape(-1),
        init=SE3(jnp.asarray(starts.wxyz_xyz, dtype)),
        pose=SE3(jnp.asarray(out["pose"])),
        status=jax.tree.map(jnp.asarray, out["status"]),
        converged=jnp.asarray(out["converged"]),
        iterations=jnp.asarray(out["iterations"]),
        inlier_rmse=jnp.asarray(out["inlier_rmse"]),
        inlier_fraction=jnp.asarray(out["inlier_fraction"]),
        rotation_error_deg=jnp.asarray(out["rotation_error_deg"]),
        translation_error=jnp.asarray(out["translation_error"]),
        success=jnp.asarray(out["success"]),
        confidently_wrong=jnp.asarray(out["converged"] & ~out["success"]),
        success_rate=jnp.asarray(rate, dtype),
        basin_radius_deg=jnp.asarray(basin_radius(angles, rate, basin_level), dtype),
    )
