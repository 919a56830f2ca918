"""ICP's solver as building blocks, for code that batches registrations its own way (the
pipeline's coarse search, :func:`jaxreg.studies.basin_sweep`); :func:`jaxreg.icp` and
:func:`jaxreg.multistart_icp` are these steps put together.

A registration in three steps::

    problem, settings, sizes = prepare(source, target, ICPOptions(max_iterations=20))
    results = jax.vmap(run, in_axes=(None, None, 0))(problem, settings, starts)  # jittable
    results = unpad(results, *sizes)

* :func:`prepare` (host): checks the :class:`ICPOptions` against the clouds (``ValueError``),
  masks unusable rows, pads both clouds to bucketed sizes (similar clouds share compiled
  programs) and builds the neighbour grid; returns the :class:`Problem`, the
  :class:`LoopSettings` and the caller's ``(N, M)``.
* :func:`run`: the loop for one start, an ``SE3`` or ``(4, 4)`` (:func:`as_pose` converts), on
  the prepared problem; it returns a :class:`RegistrationResult` whose per-point fields keep
  the padding rows. :func:`run_starts` runs a batch of starts ``(S,)`` in one compiled call
  (over every local device, or a piece per core on one CPU device) and unpads.
* :func:`unpad`: drops the padding rows; the no-match sentinel becomes the caller's ``M``.
* :func:`apply_pose`: ``pose @ points`` as the loop computes it (fused into its consumers).
* :func:`resolve_options`: an :class:`ICPOptions` with keyword overrides applied, the keyword
  form every ICP entry point accepts.

Conventions of :mod:`jaxreg.registration.icp`: a pose maps source into target coordinates.
"""

from jaxreg.registration._icp_core import (
    ICPStatus as ICPStatus,
    LoopSettings as LoopSettings,
    Problem as Problem,
    RegistrationResult as RegistrationResult,
    apply_pose as apply_pose,
    run as run,
)
from jaxreg.registration._icp_setup import (
    ICPOptions as ICPOptions,
    Method as Method,
    as_pose as as_pose,
    prepare as prepare,
    resolve_options as resolve_options,
    run_starts as run_starts,
    unpad as unpad,
)

__all__ = [
    "ICPOptions",
    "ICPStatus",
    "LoopSettings",
    "Method",
    "Problem",
    "RegistrationResult",
    "apply_pose",
    "as_pose",
    "prepare",
    "resolve_options",
    "run",
    "run_starts",
    "unpad",
]
