"""The opt-in compilation cache (jaxreg.enable_compilation_cache) and the lazy ``import jaxreg``:
a second process loads ICP's programs instead of compiling them, and importing the library
changes nothing in JAX's configuration."""

import ast
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax

import jaxreg

ROOT = Path(jaxreg.__file__).parents[1]

# jax options a library could be tempted to set; each must read the same before and after.
CONFIG = textwrap.dedent(
    """
    import json, sys
    import jax
    NAMES = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
             "jax_persistent_cache_min_entry_size_bytes", "jax_enable_x64", "jax_platforms",
             "jax_default_matmul_precision", "jax_debug_nans")
    def config():
        return {name: repr(getattr(jax.config, name)) for name in NAMES}
    before = config()
    import jaxreg as jr
    after_import = config()
    heavy = sorted(m for m in ("scipy", "numba", "jaxreg.pipeline", "jaxreg.camera")
                   if m in sys.modules)
    for name in jr.__all__:
        getattr(jr, name)
    print(json.dumps({"before": before, "after_import": after_import,
                      "after_every_name": config(), "heavy_after_import": heavy}))
    """
)

# One ICP in a fresh process with the cache enabled: whether anything was traced (the first
# process traces the solver; a second one loads every program ICP runs), whether a stored
# program was loaded, and the pose.
ICP = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    import jax
    seen = set()
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **_: seen.add(event.rsplit("/", 1)[-1]))
    import jaxreg as jr
    folder = jr.enable_compilation_cache(sys.argv[1])
    points = np.random.default_rng(0).uniform(-0.05, 0.05, (300, 3)).astype(np.float32)
    moved = points + np.float32(0.004)
    result = jr.icp(points, moved, max_correspondence_distance=0.02, max_iterations=10)
    print(json.dumps({"folder": folder, "pose": np.asarray(result.pose.wxyz_xyz).tolist(),
                      "loaded": "executable_load_duration" in seen,
                      "traced": "jaxpr_trace_duration" in seen,
                      "programs": sorted(p.name.split("-")[0]
                                         for p in (jr.core._program_cache._FOLDER).iterdir()),
                      "status": result.status_message()}))
    """
)


def _run(script: str, *args: str, **env) -> dict:
    environ = dict(os.environ, **{"PYTHONPATH": str(ROOT), **env})
    environ.pop("JAX_COMPILATION_CACHE_DIR", None)
    out = subprocess.run(
        [sys.executable, "-c", script, *args], env=environ, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_import_leaves_jax_config_alone_and_loads_lazily():
    found = _run(CONFIG)
    assert found["after_import"] == found["before"]
    assert found["after_every_name"] == found["before"]
    assert found["heavy_after_import"] == []


SUBMODULES = textwrap.dedent(
    """
    import json
    import jaxreg as jr
    found = [jr.geometry.kernels.Huber.__name__, jr.search.neighbors.query_nearest.__name__,
             jr.registration.ransac.__name__, jr.core._program_cache.__name__]
    try:
        jr.geometry.no_such_module
        found.append("no error")
    except AttributeError as err:
        found.append(str(err))
    print(json.dumps(found))
    """
)


def test_modules_resolve_as_attributes_without_an_import():
    found = _run(SUBMODULES)
    assert found[:4] == [
        "Huber", "query_nearest", "jaxreg.registration.ransac", "jaxreg.core._program_cache"
    ]  # fmt: skip
    assert "has no attribute 'no_such_module'" in found[4]


def test_a_second_process_loads_icp_from_the_cache(tmp_path):
    first = _run(ICP, str(tmp_path))
    second = _run(ICP, str(tmp_path))
    assert first["folder"] == second["folder"] == str(tmp_path)
    assert "run" in first["programs"], first["programs"]  # the ICP loop was stored
    assert first["traced"] and not first["loaded"]
    assert second["loaded"] and not second["traced"]
    assert second["pose"] == first["pose"]
    assert second["status"] == first["status"]


# A user's robust kernel in its own file, used by ICP in a fresh process with the cache on.
USER_KERNEL = textwrap.dedent(
    """
    import jax.numpy as jnp
    import jaxreg as jr

    class Flat(jr.geometry.kernels.AbstractRobustKernel):
        def rho(self, s):
            return s

        def weight(self, s):
            return jnp.full_like(s, WEIGHT)
    """
)
WITH_USER_KERNEL = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    import jaxreg as jr
    jr.enable_compilation_cache(sys.argv[1])
    import userkernel
    points = np.random.default_rng(0).uniform(-0.05, 0.05, (300, 3)).astype(np.float32)
    result = jr.icp(points, points + np.float32(0.004), max_correspondence_distance=0.02,
                    max_iterations=10, kernel=userkernel.Flat())
    print(json.dumps({"status": result.status_message()}))
    """
)


def test_editing_a_user_kernel_changes_the_stored_program(tmp_path):
    (tmp_path / "userkernel.py").write_text(USER_KERNEL.replace("WEIGHT", "1.0"))
    path = f"{ROOT}{os.pathsep}{tmp_path}"
    weighted = _run(WITH_USER_KERNEL, str(tmp_path / "cache"), PYTHONPATH=path)
    (tmp_path / "userkernel.py").write_text(USER_KERNEL.replace("WEIGHT", "0.0"))
    unweighted = _run(WITH_USER_KERNEL, str(tmp_path / "cache"), PYTHONPATH=path)
    assert weighted["status"].startswith("converged")
    assert unweighted["status"].startswith("fewer than 3 correspondences have a positive weight")


def test_empty_cache_variable_turns_caching_off(monkeypatch):
    monkeypatch.setenv("JAXREG_CACHE_DIR", "")
    before = jax.config.jax_compilation_cache_dir
    assert jaxreg.enable_compilation_cache() is None
    assert jax.config.jax_compilation_cache_dir == before
    assert jaxreg.core._program_cache._FOLDER is None


def test_type_checking_imports_match_the_lazy_table():
    tree = ast.parse((ROOT / "jaxreg" / "__init__.py").read_text())
    block = next(n for n in tree.body if isinstance(n, ast.If))
    seen = {}
    for node in block.body:
        names = tuple(alias.name for alias in node.names)
        if node.module == "jaxreg":
            assert sorted(names) == sorted(jaxreg._SUBPACKAGES)
        else:
            seen[node.module] = names
    assert seen == jaxreg._EXPORTS
    assert sorted(jaxreg.__all__) == sorted(n for names in seen.values() for n in names)
