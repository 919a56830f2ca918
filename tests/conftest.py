"""Shared fixtures: the real-data folder, float64 switching, and JAX test settings. Under
pytest-xdist: the numba host loops compiled once before the workers start, files that
compile the same programs run on one worker, and the workers share one XLA compilation cache
for the run."""

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import jax
import pytest

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

REPO = Path(__file__).resolve().parents[1]
# The environment variable that hands the workers the run's shared XLA cache folder.
_SHARED_XLA_CACHE = "JAXREG_TESTS_XLA_CACHE"

# Two halves of jaxreg's numba kernels (cache=True), compiled side by side in two processes:
# the kNN pass behind estimate_normals, and the grid build (top level, split, float32 and
# float64 tables; the k=1 witnesses last, by when the first half has usually cached the kNN
# pass it calls). Only public entry points, so the split follows any reorganisation.
_NUMBA_WARMUP = (
    """
import numpy as np
from jaxreg.search.normals import estimate_normals
estimate_normals(np.random.default_rng(0).uniform(-0.02, 0.02, (500, 3)), k=8)
""",
    """
import jax
import numpy as np
from jaxreg.search.neighbors import build_grid
points = np.random.default_rng(0).uniform(-0.02, 0.02, (4000, 3))
build_grid(points.astype(np.float32), 0.01, k=None, max_depth=2)
with jax.enable_x64(True):
    build_grid(points, 0.01, k=None)
build_grid(points.astype(np.float32), 0.01)
""",
)


def pytest_configure(config):
    """With ``-n N`` (the controller, before it starts the workers): fills numba's cache, so
    the workers load the kernels instead of each compiling all of them at once (on an empty
    cache, ~35 s of CPU per process), and makes a folder for XLA's persistent compilation
    cache that the workers share for this run (a program one worker compiled, the other
    loads). A failed warm-up is a warning; the tests still run."""
    if hasattr(config, "workerinput"):
        if os.environ.get(_SHARED_XLA_CACHE):
            jax.config.update("jax_compilation_cache_dir", os.environ[_SHARED_XLA_CACHE])
        return
    if not config.getoption("numprocesses", None):
        return
    os.environ[_SHARED_XLA_CACHE] = tempfile.mkdtemp(prefix="jaxreg-tests-xla-")
    runs = [
        subprocess.Popen(
            [sys.executable, "-c", code],
            cwd=REPO,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for code in _NUMBA_WARMUP
    ]
    for run in runs:
        _, err = run.communicate()
        if run.returncode:
            config.issue_config_time_warning(
                pytest.PytestWarning(f"numba warm-up failed, workers compile: {err[-800:]}"), 2
            )


def pytest_unconfigure(config):
    """The controller removes the workers' shared XLA cache folder."""
    if not hasattr(config, "workerinput") and os.environ.get(_SHARED_XLA_CACHE):
        shutil.rmtree(os.environ.pop(_SHARED_XLA_CACHE), ignore_errors=True)


def data_root() -> Path | None:
    """The shared real-data folder: `$JAXREG_DATA`, else `../shared/data` beside the repo."""
    env = os.environ.get("JAXREG_DATA")
    root = Path(env) if env else REPO.parent / "shared" / "data"
    return root if root.is_dir() else None


# Files whose tests compile the same JAX programs, mapped to the file they run beside (with
# ``--dist loadfile`` each file is a unit of work): the files that run ``estimate_pose`` or
# ``track`` on 848x480 synthetic frames with models of the first size class (the demo command,
# ``jaxreg bop``'s synthetic BOP frames, test_colour's painted twins, test_facing's mug with
# its mesh's normals) share one worker, which compiles the pipeline's programs (~90 s of CPU,
# and more for the twins' refusal and the oriented model's ICP) once.
_SAME_WORKER = {
    f"tests/{name}.py": "tests/test_pipeline.py"
    for name in (
        "test_cli", "test_bop_run", "test_pipeline_batch", "test_equivalent", "test_track",
        "test_mask_surface", "test_colour", "test_facing",
    )
}  # fmt: skip


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile``, with the files of ``_SAME_WORKER`` in one unit."""
    if config.getoption("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class SharedProgramsScheduling(LoadFileScheduling):
        def _split_scope(self, nodeid):
            scope = super()._split_scope(nodeid)
            return _SAME_WORKER.get(scope, scope)

    return SharedProgramsScheduling(config, log)


@pytest.fixture(scope="session", autouse=True)
def no_compilation_cache():
    """The commands turn on JAX's persistent cache and jaxreg's program store; the tests, module
    fixtures included, leave the user's cache folder alone (``JAXREG_CACHE_DIR=""``)."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("JAXREG_CACHE_DIR", "")
        yield


@pytest.fixture(scope="session")
def pcl_dir() -> Path:
    """`<data>/pcl`, or skip with the reason when the shared data is not present."""
    root = data_root()
    if root is None or not (root / "pcl").is_dir():
        pytest.skip(
            "real point clouds not found: set JAXREG_DATA or place ../shared/data beside the repo"
        )
    return root / "pcl"


@pytest.fixture(scope="session")
def ycbv_dir() -> Path:
    """`<data>/ycbv` (YCB-Video frames and models), or skip with the reason when absent."""
    root = data_root()
    if root is None or not (root / "ycbv" / "data").is_dir():
        pytest.skip(
            "YCB-Video frames not found: set JAXREG_DATA or place ../shared/data (with ycbv/) "
            "beside the repo"
        )
    return root / "ycbv"


@pytest.fixture(params=["float32", "float64"])
def dtype(request):
    """Runs a test once in float32 and once with `jax_enable_x64` on, yielding the numpy dtype."""
    import numpy as np

    if request.param == "float64":
        with jax.enable_x64(True):
            yield np.float64
    else:
        yield np.float32


@pytest.fixture
def x64():
    """Enables float64 for one test."""
    with jax.enable_x64(True):
        yield
