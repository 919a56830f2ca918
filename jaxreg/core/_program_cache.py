"""Compiled programs kept on disk, so that a second process neither traces, lowers nor compiles
them.

JAX's persistent compilation cache saves XLA's compile step, but every new process still
traces each jitted function in Python and lowers it to StableHLO before it can look the
executable up. :func:`persistent_jit` is ``equinox.filter_jit`` (arrays traced, everything else
static) plus a folder of compiled programs: the first call with a new signature traces,
compiles and writes the XLA executable (:mod:`jax.experimental.serialize_executable`); a later
process loads it and calls it, with no tracing or lowering at all. Loading is still XLA's
work, proportional to the program's optimized HLO (tens of microseconds per
instruction on a CPU); it is reported as the ``jax.monitoring`` duration event
``/jaxreg/program_cache/executable_load_duration``, since JAX's own compile events do not
see it.

An executable that XLA itself loaded from its persistent cache cannot be serialized again (its
kernels' code is not kept: it loads, then fails when run), nor can one whose custom calls need a
host library that only lowering sets up (other than LAPACK's, prepared here): such a program is
stored as a :mod:`jax.export` program instead (traced once; lowered and looked up in XLA's cache
in each process). The folder is off until :func:`set_folder` is called
(:func:`jaxreg.enable_compilation_cache` does it; the command line calls that), a library import
never does. A program's file name is a digest of everything that can change
it: the function's qualified name, the source of every jaxreg module, the jax, jaxlib, equinox
and jaxlie versions, the backend and its platform version, the host CPU (model and feature
flags: an executable is machine code), ``jax_enable_x64``, the input tree with its static leaves
(their repr; for an object holding arrays, such as a prepared model closed into the program as
constants, also a digest of the arrays' bytes, since a repr shortens them), the source of any
other module defining a type in the inputs (a user's robust kernel class: editing it changes
the key; a type with no source file, as in a notebook, is compiled the ordinary way instead),
and each array's shape and dtype. Deleting the folder is always safe.

In memory, with or without a folder, the process keeps the ``_MAX_PROGRAMS`` executables it
used most recently and drops the others (compiled or loaded again when next called): each
executable holds XLA's code pages (on a CPU, hundreds of memory maps, of the kernel's 65,530),
so a long-running process that meets new shapes keeps a bounded footprint.

Falls back to the plain compiled call (``equinox.filter_jit``, whose cache is not bounded),
with nothing written, when the call is traced (inside ``jit``, ``vmap`` or ``grad``: stored
programs are not differentiated here), when an input is sharded over several devices (a
stored program runs on one), when the output holds something that cannot be
pickled, or when compiling or storing fails.
"""

from __future__ import annotations

import contextlib
import copyreg
import dataclasses
import functools
import hashlib
import importlib.metadata
import io
import os
import pickle
import re
import sys
import tempfile
import threading
import time
import weakref
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
from jax.experimental import serialize_executable

__all__ = ["persistent_jit", "set_folder"]

_FOLDER: Path | None = None
_MAX_PROGRAMS = 32  # executables kept in memory, least recently used dropped first
_LOADED: OrderedDict[str, tuple[Callable, object] | None] = OrderedDict()
_DIGESTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # static leaf -> key text
_LOCK = threading.Lock()  # guards _LOADED, _MAKING and each persistent_jit's keys
_MAKING: dict[str, threading.Lock] = {}  # key -> held by the thread making its program
_HITS = threading.local()  # .count: XLA persistent-cache hits seen by this thread
# Code a key covers without reading it: jaxreg's sources are digested and these libraries'
# versions recorded (jax's, jaxlib's, equinox's, jaxlie's) or fixed with the interpreter.
_KEYED_CODE = frozenset(
    {"jaxreg", "jax", "jaxlib", "jaxlie", "equinox", "numpy", "builtins", "collections", "typing"}
)


def set_folder(folder: str | os.PathLike | None) -> None:
    """Where compiled programs are kept (created if missing); None turns the store off."""
    global _FOLDER
    _FOLDER = None if folder is None else Path(folder)
    _LOADED.clear()
    if _FOLDER is not None:
        _FOLDER.mkdir(parents=True, exist_ok=True)


@functools.cache
def _source_digest() -> str:
    digest = hashlib.sha256()
    package = Path(__file__).parents[1]  # every source file of jaxreg, in every subpackage
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode())
        digest.update(path.read_bytes())
    digest.update(f"{jax.__version__} {jax.lib.__version__} {eqx.__version__}".encode())
    digest.update(importlib.metadata.version("jaxlie").encode())
    return digest.hexdigest()


def _node_types(treedef):
    """The type of every node of a pytree structure (leaves excluded)."""
    data = treedef.node_data()
    if data is not None:
        yield data[0]
    for child in treedef.children():
        yield from _node_types(child)


@functools.cache
def _module_source(name: str) -> str | None:
    """Digest of a loaded module's source file; None when it has none (a notebook cell)."""
    path = getattr(sys.modules.get(name), "__file__", None)
    if path is not None:
        with contextlib.suppress(OSError):
            return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return None


def _foreign_sources(in_tree, static) -> list[tuple[str, str | None]]:
    """``(module, source digest)`` of every module outside ``_KEYED_CODE`` that defines a
    type in the call's trees or a static leaf (a user's robust kernel class, say): its code
    is traced into the program, so editing it must change the key."""
    types = {*_node_types(in_tree), *_node_types(jax.tree.structure(static))}
    types |= {type(leaf) for leaf in jax.tree.leaves(static)}
    modules = {t.__module__ for t in types}
    foreign = sorted(m for m in modules if m.split(".")[0] not in _KEYED_CODE)
    return [(m, _module_source(m)) for m in foreign]


@functools.cache
def _machine() -> str:
    """The backend's platform version and the host CPU's model and feature flags (Linux's
    ``/proc/cpuinfo``; empty elsewhere): a stored executable is machine code."""
    cpu = ""
    with contextlib.suppress(OSError):
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        cpu = " ".join(
            next((line for line in lines if line.startswith(field)), "")
            for field in ("model name", "flags")
        )
    return f"{jax.local_devices()[0].client.platform_version} {cpu}"


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


def _signature(arrays: list, static, in_tree) -> tuple | None:
    """What :func:`_key` reads from a call, as a hashable tuple (the static leaves with their
    types, so that ``1``, ``1.0`` and ``True`` differ), or None when a static leaf is not
    hashable: a call with the same signature has the same key, found without hashing text."""
    leaves, static_tree = jax.tree.flatten(static)
    avals = tuple((a.shape, a.dtype, bool(getattr(a, "weak_type", False))) for a in arrays)
    signature = (
        in_tree,
        static_tree,
        tuple((type(leaf), leaf) for leaf in leaves),
        avals,
        bool(jax.config.jax_enable_x64),
        jax.default_backend(),
    )
    try:
        hash(signature)
    except TypeError:
        return None
    return signature


def _key(fn: Callable, arrays: list, static, in_tree) -> str | None:
    """The program's name, or None when some of its code cannot be keyed (a type defined
    where there is no source file to digest)."""
    foreign = _foreign_sources(in_tree, static)
    if any(digest is None for _, digest in foreign):
        return None
    avals = [(a.shape, str(a.dtype), bool(getattr(a, "weak_type", False))) for a in arrays]
    text = repr(
        (
            f"{fn.__module__}.{fn.__qualname__}",
            _source_digest(),
            jax.default_backend(),
            _machine(),
            bool(jax.config.jax_enable_x64),
            str(in_tree),
            str(jax.tree.structure(static)),
            [_static_text(leaf) for leaf in jax.tree.leaves(static)],
            avals,
            foreign,
        )
    )
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _write(path: Path, payload: tuple) -> None:
    with tempfile.NamedTemporaryFile(dir=path.parent, delete=False) as handle:
        handle.write(_dumps(payload))
    os.replace(handle.name, path)


def _custom_calls(compiled) -> list[str]:
    """The custom-call targets of a compiled program, checked to be ones :func:`_load` can
    prepare: LAPACK's, whose functions jaxlib fetches from scipy only when a program using
    them is lowered (a stored executable skips lowering; unprepared, it crashes)."""
    targets = sorted(set(re.findall(r'custom_call_target="([^"]+)"', compiled.as_text())))
    if any(not t.startswith("lapack_") for t in targets):
        raise ValueError(f"custom calls {targets}: store the exported program instead")
    return targets


@functools.cache
def _count_cache_hits() -> None:
    """Counts XLA's persistent-cache hits per thread from here on (a ``jax.monitoring``
    listener, registered once, when the first program is stored)."""

    def listen(event: str, **_) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            _HITS.count = getattr(_HITS, "count", 0) + 1

    jax.monitoring.register_event_listener(listen)


def _load(blob: bytes, in_tree, out_tree, custom_calls: list[str]) -> Callable:
    """A serialized executable back as a callable, its load time reported as
    ``/jaxreg/program_cache/executable_load_duration``."""
    start = time.perf_counter()
    if custom_calls:
        from jax._src.lax.linalg import initialize_lapack

        initialize_lapack()
    compiled = serialize_executable.deserialize_and_load(
        blob, in_tree, out_tree, execution_devices=jax.local_devices()[:1]
    )
    jax.monitoring.record_event_duration_secs(
        "/jaxreg/program_cache/executable_load_duration", time.perf_counter() - start
    )
    return compiled


def _flat(fn: Callable, arrays: list, static, in_tree):
    """``fn`` as a function of the flat arrays, its output trees appended to a list, and the
    arrays' specs: (flat function, output trees, specs)."""
    box = []

    def flat(*values):
        out = fn(*eqx.combine(jax.tree.unflatten(in_tree, values), static))
        out_leaves, out_tree = jax.tree.flatten(out)
        box.append(out_tree)
        return out_leaves

    specs = [
        jax.ShapeDtypeStruct(a.shape, a.dtype, weak_type=getattr(a, "weak_type", False))
        for a in arrays
    ]
    return flat, box, specs


def _compile(fn: Callable, arrays: list, static, in_tree):
    """Traces and compiles ``fn`` (nothing written); returns (callable of the flat arrays,
    output tree)."""
    flat, box, specs = _flat(fn, arrays, static, in_tree)
    return jax.jit(flat).lower(*specs).compile(), box[0]


def _store(fn: Callable, arrays: list, static, in_tree, path: Path):
    """Traces and compiles ``fn`` once and writes its executable, or where that does not
    load back, its :mod:`jax.export` program, with the output tree to ``path``; returns
    (callable of the flat arrays, output tree)."""
    flat, box, specs = _flat(fn, arrays, static, in_tree)
    _count_cache_hits()
    hits = getattr(_HITS, "count", 0)
    compiled = jax.jit(flat).lower(*specs).compile()
    try:
        if getattr(_HITS, "count", 0) != hits:  # its kernels' code is gone: it would not run
            raise ValueError("an executable XLA loaded from its cache cannot be saved again")
        calls = _custom_calls(compiled)
        blob, flat_in, flat_out = serialize_executable.serialize(compiled)
        _write(path, ("executable", blob, flat_in, flat_out, calls, box[0]))
    except Exception:
        exported = jax.export.export(jax.jit(flat))(*specs)
        _write(path, ("export", bytes(exported.serialize()), box[-1]))
    return compiled, box[0]


def _read(path: Path):
    """The stored program at ``path`` as (callable of the flat arrays, output tree)."""
    kind, *stored = pickle.loads(path.read_bytes())
    if kind == "executable":
        blob, flat_in, flat_out, calls, out_tree = stored
        return _load(blob, flat_in, flat_out, calls), out_tree
    blob, out_tree = stored
    return jax.jit(jax.export.deserialize(bytearray(blob)).call), out_tree


def _program(fn: Callable, arrays: list, static, in_tree, key: str):
    """The program of ``key``: kept in memory, read from the folder, or compiled (and
    stored when there is a folder); ``None`` where none could be made. Threads asking for
    the same key at once wait for the first one's program instead of compiling it again."""
    with _LOCK:
        if key in _LOADED:
            _LOADED.move_to_end(key)
            return _LOADED[key]
        making = _MAKING.setdefault(key, threading.Lock())
    with making:
        with _LOCK:
            if key in _LOADED:  # made by another thread while this one waited
                return _LOADED[key]
        program = None
        if _FOLDER is None:
            with contextlib.suppress(Exception):  # compiled the ordinary way instead
                program = _compile(fn, arrays, static, in_tree)
        else:
            path = _FOLDER / f"{fn.__name__}-{key}.jaxprog"
            with contextlib.suppress(Exception):  # unreadable (another jaxlib build?): anew
                program = _read(path) if path.is_file() else None
            if program is None:
                with contextlib.suppress(Exception):  # one that cannot be stored is compiled
                    program = _store(fn, arrays, static, in_tree, path)  # the ordinary way
        with _LOCK:
            _LOADED[key] = program
            _MAKING.pop(key, None)
            while len(_LOADED) > _MAX_PROGRAMS:
                _LOADED.popitem(last=False)
    return program


def persistent_jit(fn: Callable) -> Callable:
    """``equinox.filter_jit(fn)`` (arrays traced, everything else static), its executables
    kept among the process's ``_MAX_PROGRAMS`` most recently used and stored on disk between
    processes once :func:`set_folder` has named a folder. ``fn`` must depend only on its
    arguments (no closed-over arrays or mutable globals)."""
    jitted = eqx.filter_jit(fn)
    keys: OrderedDict[tuple, str | None] = OrderedDict()  # the call's signature -> _key

    @functools.wraps(fn)
    def call(*args):
        dynamic, static = eqx.partition(args, eqx.is_array)
        arrays, in_tree = jax.tree.flatten(dynamic)
        if any(isinstance(a, jax.core.Tracer) for a in arrays):
            return jitted(*args)
        if any(len(a.sharding.device_set) > 1 for a in arrays if isinstance(a, jax.Array)):
            return jitted(*args)  # stored programs run on one device
        # host arrays go to the program as they are: its call moves them in one step (a
        # device_put each costs more than the transfer), in JAX's dtypes (float64 as float32
        # unless x64 is on)
        arrays = [
            a if isinstance(a, jax.Array)
            else np.asarray(a, jax.dtypes.canonicalize_dtype(np.result_type(a)))
            for a in arrays
        ]  # fmt: skip
        signature = _signature(arrays, static, in_tree)
        with _LOCK:
            known = signature is not None and signature in keys
            if known:
                keys.move_to_end(signature)
                key = keys[signature]
        if not known:
            key = _key(fn, arrays, static, in_tree)
            if signature is not None:
                with _LOCK:
                    keys[signature] = key
                    while len(keys) > _MAX_PROGRAMS:
                        keys.popitem(last=False)
        program = None if key is None else _program(fn, arrays, static, in_tree, key)
        if program is None:
            return jitted(*args)
        run, out_tree = program
        return jax.tree.unflatten(out_tree, run(*arrays))

    return call
