"""Modules of a package resolved as its attributes on first use."""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

__all__ = ["submodule"]


def submodule(package: str, name: str) -> ModuleType:
    """``package.name`` imported now, for a package's module-level ``__getattr__``: since
    ``import jaxreg`` loads each module on first use, ``jaxreg.geometry.kernels`` must resolve
    without an import statement having loaded it.

    Raises:
        AttributeError: ``package`` has no module ``name`` (dunder names are never modules).
    """
    if not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}") is not None:
        return importlib.import_module(f"{package}.{name}")
    raise AttributeError(f"module {package!r} has no attribute {name!r}")
