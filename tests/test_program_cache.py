"""Programs stored on disk between processes (jaxreg.core._program_cache)."""

import dataclasses
import json
import pickle
import subprocess
import sys
import textwrap
from collections import OrderedDict

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxreg as jr
from jaxreg.core import _program_cache

pytest.importorskip("flatbuffers", reason="jax.export serialization needs flatbuffers")

# A module-level function of arrays plus one static option, as the pipeline's stages are.
# It counts its traces, so a test can tell a stored program from a freshly traced one.
MODULE = textwrap.dedent(
    """
    import jax.numpy as jnp
    import jaxreg as jr

    TRACES = []

    def fit(source, target, scale):
        TRACES.append(1)
        return jr.align(source * scale, target)
    """
)

FRESH_PROCESS = textwrap.dedent(
    """
    import json
    import sys
    import numpy as np
    from jaxreg.core import _program_cache
    import fitmod

    _program_cache.set_folder(sys.argv[1])
    source = np.load(sys.argv[2])
    result = _program_cache.persistent_jit(fitmod.fit)(source, source + 0.5, 2.0)
    print(json.dumps({"traces": len(fitmod.TRACES), "message": str(result.status_message()),
                      "pose": np.asarray(result.pose.wxyz_xyz).tolist()}))
    """
)


@pytest.fixture
def fitmod(tmp_path, monkeypatch):
    (tmp_path / "fitmod.py").write_text(MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    import fitmod

    fitmod.TRACES.clear()
    yield fitmod
    sys.modules.pop("fitmod", None)


@pytest.fixture
def store(tmp_path):
    folder = tmp_path / "programs"
    _program_cache.set_folder(folder)
    yield folder
    _program_cache.set_folder(None)


def _source(n=20, seed=0):
    return np.random.default_rng(seed).normal(size=(n, 3)).astype(np.float32)


def test_off_by_default_and_the_same_as_filter_jit(fitmod):
    assert _program_cache._FOLDER is None
    fit = _program_cache.persistent_jit(fitmod.fit)
    source = _source()
    direct = jr.align(source * 2.0, source + 0.5)
    stored = fit(source, source + 0.5, 2.0)
    np.testing.assert_array_equal(stored.pose.wxyz_xyz, direct.pose.wxyz_xyz)


def test_a_second_process_runs_the_stored_program_without_tracing(fitmod, store, tmp_path):
    fit = _program_cache.persistent_jit(fitmod.fit)
    source = _source()
    first = fit(source, source + 0.5, 2.0)
    assert len(fitmod.TRACES) == 1 and len(list(store.glob("*.jaxprog"))) == 1
    fit(source, source + 0.5, 2.0)  # same signature: no new trace, no new file
    assert len(fitmod.TRACES) == 1 and len(list(store.glob("*.jaxprog"))) == 1

    fresh = _fresh(store, tmp_path, source)
    assert fresh["traces"] == 0  # the function body never ran: the program came from the file
    np.testing.assert_allclose(fresh["pose"], np.asarray(first.pose.wxyz_xyz), atol=1e-6)
    assert fresh["message"] == str(first.status_message())  # the status survives the trip


def _fresh(store, tmp_path, source, **env) -> dict:
    np.save(tmp_path / "source.npy", source)
    env = {"PYTHONPATH": f"{tmp_path}:{':'.join(sys.path)}", "JAX_PLATFORMS": "cpu", **env}
    out = subprocess.run(
        [sys.executable, "-c", FRESH_PROCESS, str(store), str(tmp_path / "source.npy")],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _kinds(store) -> list[str]:
    return [pickle.loads(path.read_bytes())[0] for path in store.glob("*.jaxprog")]


def test_a_program_whose_executable_cannot_be_saved_is_stored_exported(
    fitmod, store, tmp_path, monkeypatch
):
    def refuse(compiled):
        raise ValueError("not serializable")

    monkeypatch.setattr(_program_cache.serialize_executable, "serialize", refuse)
    source = _source()
    first = _program_cache.persistent_jit(fitmod.fit)(source, source + 0.5, 2.0)
    assert _kinds(store) == ["export"]
    fresh = _fresh(store, tmp_path, source)
    assert fresh["traces"] == 0
    np.testing.assert_allclose(fresh["pose"], np.asarray(first.pose.wxyz_xyz), atol=1e-6)


def test_with_xlas_cache_filled_a_new_store_still_serves_a_fresh_process(fitmod, tmp_path):
    """An executable XLA loaded from its persistent cache may not serialize again (its
    kernels' code is not kept): the store checks that it loads back, else keeps the exported
    program; either way a later process runs it without tracing."""
    store, source = tmp_path / "programs", _source()
    xla = {
        "JAX_COMPILATION_CACHE_DIR": str(tmp_path / "xla"),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
        "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0",
    }
    first = _fresh(store, tmp_path, source, **xla)  # compiles: stores the executable
    assert first["traces"] == 1 and _kinds(store) == ["executable"]
    for path in store.glob("*.jaxprog"):
        path.unlink()
    again = _fresh(store, tmp_path, source, **xla)  # XLA's cache answers the compile
    assert again["traces"] == 1 and len(_kinds(store)) == 1
    last = _fresh(store, tmp_path, source, **xla)
    assert last["traces"] == 0
    np.testing.assert_array_equal(last["pose"], first["pose"])


def test_new_shapes_or_static_options_are_new_programs(fitmod, store):
    fit = _program_cache.persistent_jit(fitmod.fit)
    fit(_source(20), _source(20) + 0.5, 2.0)
    fit(_source(30), _source(30) + 0.5, 2.0)
    fit(_source(20), _source(20) + 0.5, 3.0)
    assert len(fitmod.TRACES) == 3 and len(list(store.glob("*.jaxprog"))) == 3
    scaled = fit(_source(20), _source(20) + 0.5, 3.0)
    direct = jr.align(_source(20) * 3.0, _source(20) + 0.5)
    np.testing.assert_allclose(scaled.pose.wxyz_xyz, direct.pose.wxyz_xyz, atol=1e-6)


def test_traced_calls_fall_back_and_store_nothing(fitmod, store):
    fit = _program_cache.persistent_jit(fitmod.fit)
    sources = jnp.stack([_source(seed=s) for s in range(3)])
    batched = jax.vmap(lambda s: fit(s, s + 0.5, 2.0).pose.wxyz_xyz)(sources)
    grad = jax.grad(lambda s: fit(s, s + 0.5, 2.0).pose.wxyz_xyz[4])(sources[0])
    assert batched.shape == (3, 7) and np.all(np.isfinite(grad))
    assert not list(store.glob("*.jaxprog"))


@dataclasses.dataclass(frozen=True, eq=False)
class _Held:
    """A static leaf (not a pytree) holding an array, as the pipeline's prepared model does:
    its array is closed into the program as a constant."""

    values: np.ndarray


def _offset(x, held):
    return x + jnp.asarray(held.values).sum()


def test_static_objects_holding_arrays_are_keyed_by_their_bytes(store):
    base = np.zeros(2000, np.float32)
    edited = base.copy()
    edited[1000] = 1.0
    assert repr(_Held(base)) == repr(_Held(edited))  # numpy shortens both to the same text
    run = _program_cache.persistent_jit(_offset)
    x = jnp.zeros(3)
    np.testing.assert_array_equal(run(x, _Held(base)), np.zeros(3))
    np.testing.assert_array_equal(run(x, _Held(edited)), np.ones(3))
    np.testing.assert_array_equal(run(x, _Held(base.copy())), np.zeros(3))  # same bytes
    assert len(list(store.glob("*.jaxprog"))) == 2


def test_the_process_keeps_only_the_most_recently_used_programs(fitmod, monkeypatch):
    """In memory (no folder here) at most ``_MAX_PROGRAMS`` executables: the least recently
    used is dropped (its code pages with it) and traced and compiled again when called."""
    monkeypatch.setattr(_program_cache, "_MAX_PROGRAMS", 2)
    monkeypatch.setattr(_program_cache, "_LOADED", OrderedDict())
    fit = _program_cache.persistent_jit(fitmod.fit)

    def call(n):
        return fit(_source(n), _source(n) + 0.5, 2.0)

    first = call(20)
    call(30)
    call(20)  # used again: the most recent
    assert len(fitmod.TRACES) == 2
    call(40)  # drops the 30-point program
    assert len(_program_cache._LOADED) == 2 and len(fitmod.TRACES) == 3
    call(20)
    assert len(fitmod.TRACES) == 3
    call(30)
    assert len(fitmod.TRACES) == 4
    np.testing.assert_array_equal(call(20).pose.wxyz_xyz, first.pose.wxyz_xyz)
