"""The shape every solver's result shares: ``pose``, ``status``, ``converged``, ``iterations``.

Results are ``equinox.Module`` pytrees, so a batch of results (from ``vmap``, a batched
solve or :func:`jaxreg.multistart_icp`) is one value whose leaves all carry the same leading
batch axes. :class:`AbstractResult` gives every result the same two host-side conveniences:

* ``result[i]`` indexes the leading batch axes of every leaf at once (an int, a slice, an
  integer array or a boolean mask, as numpy indexing of the batch axes would), so one lane of
  a batch is a result of the same type without touching its leaves;
* ``result.status_message()`` turns the status into the text a user reads.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Int

__all__ = ["AbstractResult", "select_status"]


class AbstractResult(eqx.Module):
    """Base of every result type. Subclasses declare at least these fields:

    - ``pose``: the solved pose (``jaxlie.SE3``), batch ``(...)``;
    - ``status``: a member of the solver's ``equinox.Enumeration``, batch ``(...)``; its
      value is the message;
    - ``converged``: ``(...)`` bool, the solver's own stopping test passed;
    - ``iterations``: ``(...)`` int, steps taken (0 for closed forms).
    """

    pose: eqx.AbstractVar[object]
    status: eqx.AbstractVar[object]
    converged: eqx.AbstractVar[Bool[Array, "..."]]
    iterations: eqx.AbstractVar[Int[Array, "..."]]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """The leading batch axes every leaf carries (``()`` for one problem)."""
        return tuple(np.shape(self.status._value))

    def __getitem__(self, index) -> AbstractResult:
        """One lane (or a sub-batch) of a batched result, indexing every leaf's batch axes.

        Concrete leaves are indexed on the host and put back on the device: eager indexing
        would compile (and in a later process load) one small program per leaf shape."""
        if not self.batch_shape:
            raise IndexError(f"{type(self).__name__} holds one problem: there is no batch to index")
        if isinstance(index, jax.core.Tracer) or any(
            isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(self)
        ):
            return jax.tree.map(lambda leaf: leaf[index], self)
        if isinstance(index, jax.Array):
            index = np.asarray(index)
        return jax.device_put(jax.tree.map(lambda leaf: np.asarray(leaf)[index], self))

    def status_message(self) -> str | np.ndarray:
        """The status as text, on the host: a string, or an array of strings for a batch."""
        codes = np.asarray(self.status._value)
        messages = np.asarray(self.status._enumeration._index_to_message, dtype=object)
        return str(messages[codes]) if codes.ndim == 0 else messages[codes]


def select_status(cases, default) -> eqx.Enumeration:
    """Elementwise status over batch axes: the member of the first true condition, else
    ``default``.

    ``cases`` is a sequence of ``(condition, member)`` with boolean ``(...)`` conditions and
    members of one ``equinox.Enumeration``; ``Enumeration.where`` takes only a scalar
    predicate, which suits code written per problem and vmapped, this batched code.
    """
    conditions = [jnp.asarray(c) for c, _ in cases]
    code = jnp.select(conditions, [m._value for _, m in cases], default._value)
    return type(default)(_value=code, _enumeration=default._enumeration)
