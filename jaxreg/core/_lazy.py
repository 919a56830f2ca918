"""Modules of a package resolved as its attributes on first use."""

from __future__ import annotations

import importlib
import importlib.util
from collections.abc import Callable
from types import ModuleType

__all__ = ["submodules"]


def submodules(package: str) -> Callable[[str], ModuleType]:
    """A module-level ``__getattr__`` for ``package`` that imports ``package.<name>`` on first
    use: since ``import jaxreg`` loads each module when it is first needed,
    ``jaxreg.geometry.kernels`` must resolve without an import statement having loaded it.

    Use as ``__getattr__ = submodules(__name__)`` in the package's ``__init__``. The returned
    function raises ``AttributeError`` when ``package`` has no module ``name`` (dunder names are
    never modules).
    """

    def module(name: str) -> ModuleType:
        if not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}") is not None:
            return importlib.import_module(f"{package}.{name}")
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return module
