"""Compiled programs kept on disk, so that a second process neither traces nor lowers them.

JAX's persistent compilation cache saves XLA's compile step, but every new process still
traces each jitted function in Python and lowers it to StableHLO before it can look the
executable up; for the pipeline's large programs that is most of a warm process's start-up.
:func:`persistent_jit` is ``equinox.filter_jit`` (arrays traced, everything else static) plus a
folder of :mod:`jax.export` programs: the first call with a new signature exports the traced
program and writes it; a later process deserializes it and calls it, and XLA's own cache
(which the command line enables alongside) supplies the executable.

The folder is off until :func:`set_folder` is called: the command line does it, a library
import never does. A program's file name is a digest of everything that can change it: the
function's qualified name, the source of every jaxreg module, the jax and jaxlib versions,
the backend, ``jax_enable_x64``, the input tree with its static leaves (their repr; for an
object holding arrays, such as a prepared model closed into the program as constants, also a
digest of the arrays' bytes, since a repr shortens them), and each array's shape and dtype.
Deleting the folder is always safe.

Falls back to the plain compiled call, with nothing written, when the call is traced (inside
``jit``, ``vmap`` or ``grad``: exported programs are not differentiated here), when the
output holds something that cannot be pickled, or when the export fails.
"""

from __future__ import annotations

import contextlib
import copyreg
import dataclasses
import functools
import hashlib
import io
import os
import pickle
import tempfile
import weakref
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

__all__ = ["persistent_jit", "set_folder"]

_FOLDER: Path | None = None
_LOADED: dict[str, tuple[Callable, object] | None] = {}
_DIGESTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # static leaf -> key text


def set_folder(folder: str | os.PathLike | None) -> None:
    """Where exported programs are kept (created if missing); None turns the store off."""
    global _FOLDER
    _FOLDER = None if folder is None else Path(folder)
    _LOADED.clear()
    if _FOLDER is not None:
        _FOLDER.mkdir(parents=True, exist_ok=True)


@functools.cache
def _source_digest() -> str:
    digest = hashlib.sha256()
    for path in sorted(Path(__file__).parent.glob("*.py")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    digest.update(f"{jax.__version__} {jax.lib.__version__}".encode())
    return digest.hexdigest()


def _missing():
    """Equinox marks unset module fields with a private singleton; pickled output trees must
    come back holding that same object."""
    from equinox._module._flatten import MISSING

    return MISSING


def _dumps(value) -> bytes:
    table = copyreg.dispatch_table.copy()
    try:
        from equinox._module._flatten import _Missing

        table[_Missing] = lambda _: (_missing, ())
    except ImportError:
        pass
    buffer = io.BytesIO()
    pickler = pickle.Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL)
    pickler.dispatch_table = table
    pickler.dump(value)
    return buffer.getvalue()


def _held_arrays(value, depth: int = 0) -> list:
    """The numpy and JAX arrays inside a static leaf: itself, its pytree leaves, and those of
    a dataclass's fields or a container's items (a few levels down)."""
    if isinstance(value, np.ndarray | jax.Array):
        return [value]
    if depth > 4 or isinstance(value, str | bytes | int | float | complex | type(None)):
        return []
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        items = [getattr(value, field.name, None) for field in dataclasses.fields(value)]
    elif isinstance(value, dict):
        items = list(value.values())
    elif isinstance(value, list | tuple):
        items = list(value)
    else:
        return []
    return [
        a for item in items for leaf in jax.tree.leaves(item) for a in _held_arrays(leaf, depth + 1)
    ]


def _static_text(leaf) -> str:
    """A static leaf as key text: its repr, and for an object holding arrays (numpy shortens
    their repr with '...', an equinox module shows only shapes) a digest of their bytes too,
    computed once per object while it lives."""
    try:
        return _DIGESTS[leaf]
    except (KeyError, TypeError):  # TypeError: not hashable or not weakly referenceable
        pass
    text = repr(leaf)
    held = _held_arrays(leaf)
    if held:
        digest = hashlib.sha256(text.encode())
        for array in held:
            host = np.ascontiguousarray(array)
            digest.update(f"{host.shape} {host.dtype}".encode())
            digest.update(host.tobytes())
        text = f"{type(leaf).__qualname__} holding arrays {digest.hexdigest()}"
        with contextlib.suppress(TypeError):
            _DIGESTS[leaf] = text
    return text


def _key(fn: Callable, arrays: list, static, in_tree) -> str:
    avals = [(a.shape, str(a.dtype), bool(getattr(a, "weak_type", False))) for a in arrays]
    text = repr(
        (
            f"{fn.__module__}.{fn.__qualname__}",
            _source_digest(),
            jax.default_backend(),
            bool(jax.config.jax_enable_x64),
            str(in_tree),
            str(jax.tree.structure(static)),
            [_static_text(leaf) for leaf in jax.tree.leaves(static)],
            avals,
        )
    )
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _export(fn: Callable, arrays: list, static, in_tree, path: Path):
    """Traces ``fn`` once through :func:`jax.export.export` and writes the program and its
    output tree to ``path``; returns (program, output tree)."""
    box = []

    def flat(*values):
        out = fn(*eqx.combine(jax.tree.unflatten(in_tree, values), static))
        out_leaves, out_tree = jax.tree.flatten(out)
        box.append(out_tree)
        return out_leaves

    specs = [jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=a.weak_type) for a in arrays]
    exported = jax.export.export(jax.jit(flat))(*specs)
    payload = _dumps((bytes(exported.serialize()), box[0]))
    with tempfile.NamedTemporaryFile(dir=path.parent, delete=False) as handle:
        handle.write(payload)
    os.replace(handle.name, path)
    return exported, box[0]


def _program(fn: Callable, arrays: list, static, in_tree, key: str):
    if key in _LOADED:
        return _LOADED[key]
    path = _FOLDER / f"{fn.__name__}-{key}.jaxprog"
    program = None
    try:
        if path.is_file():
            blob, out_tree = pickle.loads(path.read_bytes())
            exported = jax.export.deserialize(bytearray(blob))
        else:
            exported, out_tree = _export(fn, arrays, static, in_tree, path)
        program = (jax.jit(exported.call), out_tree)
    except Exception:  # a program that cannot be stored is compiled the ordinary way
        program = None
    _LOADED[key] = program
    return program


def persistent_jit(fn: Callable) -> Callable:
    """``equinox.filter_jit(fn)``, with the traced program stored on disk between processes
    once :func:`set_folder` has named a folder. ``fn`` must depend only on its arguments (no
    closed-over arrays or mutable globals)."""
    jitted = eqx.filter_jit(fn)

    @functools.wraps(fn)
    def call(*args):
        if _FOLDER is None:
            return jitted(*args)
        dynamic, static = eqx.partition(args, eqx.is_array)
        arrays, in_tree = jax.tree.flatten(dynamic)
        if any(isinstance(a, jax.core.Tracer) for a in arrays):
            return jitted(*args)
        arrays = [a if isinstance(a, jax.Array) else jax.device_put(a) for a in arrays]
        key = _key(fn, arrays, static, in_tree)
        program = _program(fn, arrays, static, in_tree, key)
        if program is None:
            return jitted(*args)
        run, out_tree = program
        return jax.tree.unflatten(out_tree, run(*arrays))

    return call
