"""A griffe extension (mkdocs.yml's mkdocstrings ``extensions``): the docstrings' Sphinx roles
(``:func:`jaxreg.icp```, ``:class:`~jaxreg.pipeline.records.SegmentRecord```) become links to
the documented object, so the API pages read as links, not as markup.

A role's target is resolved the way Python resolves it (absolute, or relative to the
docstring's module and class) and linked where the API pages document it: its module's page,
or its package's for a name defined in a private module. A target in a private module that no
package re-exports is shown as code, not linked (the API pages document the public surface).
A target that does not resolve is logged as a warning, so ``mkdocs build --strict`` (``make
docs``) fails on a broken reference.
"""

from __future__ import annotations

import importlib
import inspect
import logging
import re
import sys
from pathlib import Path

import griffe

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _hooks import _identifier  # noqa: E402

LOG = logging.getLogger("mkdocs.plugins.jaxreg.roles")
ROLE = re.compile(r":(?:py:)?(func|class|mod|meth|attr|data|obj|exc|const):`(~?)([^`]+)`")


def _resolve(target: str, module: str, owner: str | None):
    """The object ``target`` names, looked up as written, then in ``owner`` (a class's path),
    ``module``, its package and the top level; ``None`` when nothing matches."""
    package = ".".join(module.split(".")[:2])
    for base in (None, owner, module, package, "jaxreg"):
        dotted = target if base is None else f"{base}.{target}"
        value = _lookup(dotted)
        if value is not None:
            return dotted, value
    return None, None


def _lookup(dotted: str):
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            value = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        try:
            for part in parts[cut:]:
                value = getattr(value, part)
        except AttributeError:
            return None
        return value
    return None


def _link(kind: str, tilde: str, target: str, module: str, owner: str | None, where: str):
    target = re.sub(r"\s+", "", target)
    text = target.rsplit(".", 1)[-1] if tilde else target
    dotted, value = _resolve(target.rstrip("()"), module, owner)
    if dotted is None:
        # a broken reference in a documented docstring fails the build; a member named
        # without its class (:meth:`as_dict`) reads as code
        member = kind in ("meth", "attr") and "." not in target
        if not member and not any(p.startswith("_") for p in where.split(".")[1:]):
            LOG.warning("%s: %s does not resolve (:%s:`%s`)", where, target, kind, target)
        return f"`{text}`"
    if inspect.ismodule(value):
        name = value.__name__
        if any(part.startswith("_") for part in name.split(".")[1:]):
            return f"`{text}`"
        return f"[`{text}`][{name}]"
    if inspect.isclass(value) or inspect.isfunction(value):
        home = getattr(value, "__module__", "") or ""
        qualname = getattr(value, "__qualname__", value.__name__)
        if "." in qualname or "<" in qualname:  # a method or a nested helper: show as code
            return f"`{text}`"
        if not home.startswith(("jaxreg", "jaxlie")):
            return f"`{text}`"
        identifier = _identifier(value, value.__name__)
        if identifier is None:
            return f"`{text}`"  # private and not re-exported: not documented
        return f"[`{text}`][{identifier}]"
    return f"`{text}`"  # attributes, constants, methods: their owner's page describes them


class SphinxRoles(griffe.Extension):
    """Rewrites each object's docstring's roles as links (see the module docstring)."""

    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is None or ":" not in obj.docstring.value:
            return
        module = obj.module.path
        parent = obj.parent
        owner = obj.path if obj.is_class else (parent.path if parent and parent.is_class else None)
        obj.docstring.value = ROLE.sub(
            lambda m: _link(m[1], m[2], m[3], module, owner, obj.path), obj.docstring.value
        )
