"""Shared fixtures: the real-data folder, float64 switching, and JAX test settings."""

import os
from pathlib import Path

import jax
import pytest

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

REPO = Path(__file__).resolve().parents[1]


def data_root() -> Path | None:
    """The shared real-data folder: `$JAXREG_DATA`, else `../shared/data` beside the repo."""
    env = os.environ.get("JAXREG_DATA")
    root = Path(env) if env else REPO.parent / "shared" / "data"
    return root if root.is_dir() else None


@pytest.fixture(scope="session")
def pcl_dir() -> Path:
    """`<data>/pcl`, or skip with the reason when the shared data is not present."""
    root = data_root()
    if root is None or not (root / "pcl").is_dir():
        pytest.skip(
            "real point clouds not found: set JAXREG_DATA or place ../shared/data beside the repo"
        )
    return root / "pcl"


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
