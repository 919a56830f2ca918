"""Names and modules of a package resolved as its attributes on first use."""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil
import sys
from collections.abc import Callable, Mapping
from types import ModuleType
from typing import Any

__all__ = ["exports", "submodules"]


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


def exports(
    package: str, table: Mapping[str, tuple[str, ...]]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """A module-level ``__getattr__`` and ``__dir__`` for ``package`` that re-export the names
    of ``table`` (a module's full name -> the public names it defines), each module imported
    when one of its names is first used, and resolve ``package.<module>`` as
    :func:`submodules` does.

    ``dir(package)`` lists the names of ``table``, the package's public modules and what its
    ``__init__`` imported from the library: no private helper, no module from outside.

    Use as ``__getattr__, __dir__ = exports(__name__, {...})``.
    """
    module_of = {name: module for module, names in table.items() for name in names}
    module = submodules(package)

    def getattr_(name: str) -> Any:
        if name not in module_of:
            return module(name)
        value = getattr(importlib.import_module(module_of[name]), name)
        setattr(sys.modules[package], name, value)  # later lookups find it without this call
        return value

    def dir_() -> list[str]:
        namespace = vars(sys.modules[package])
        own = {
            name
            for name, value in namespace.items()
            if not name.startswith("_") and _from_the_library(value)
        }
        modules = {
            info.name
            for info in pkgutil.iter_modules(namespace.get("__path__", ()))
            if not info.name.startswith("_")
        }
        return sorted({*module_of, *modules, *own})

    return getattr_, dir_


def _from_the_library(value: Any) -> bool:
    """Whether ``value`` (a module, function or type) is the library's own, not a helper of this
    module's or a name from elsewhere (``annotations``, ``TYPE_CHECKING``)."""
    if value is submodules or value is exports:
        return False
    home = getattr(value, "__module__", None) if not isinstance(value, ModuleType) else None
    return (home or getattr(value, "__name__", "") or "").startswith("jaxreg")
