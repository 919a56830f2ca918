"""Every dependency `pyproject.toml` declares is one the library imports, and none is listed
twice."""

import ast
import importlib.util
import re
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Distribution name -> the module jaxreg imports for it, where the two differ.
IMPORT_NAME = {"pillow": "PIL", "opencv-python-headless": "cv2"}
# Distributions jaxreg needs without importing them: the module jaxreg uses that needs them,
# and the file of that module that imports them.
NEEDED_BY = {"flatbuffers": ("jax.export", "jax._src.export.serialization")}


def _name(requirement: str) -> str:
    """`"scipy>=1.14; python_version < '3.13'"` -> `"scipy"`."""
    return re.match(r"[A-Za-z0-9_.\-]+", requirement).group(0).lower().replace("_", "-")


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _imported_modules() -> set[str]:
    """Every module named by an import statement or an attribute chain (`jax.export.x`) in
    jaxreg/, with its parents."""
    found: set[str] = set()
    for path in (ROOT / "jaxreg").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            elif isinstance(node, ast.Attribute):
                parts = []
                while isinstance(node, ast.Attribute):
                    parts.append(node.attr)
                    node = node.value
                if isinstance(node, ast.Name):
                    names = [".".join([node.id, *reversed(parts)])]
            for name in names:
                pieces = name.split(".")
                found.update(".".join(pieces[: i + 1]) for i in range(len(pieces)))
    return found


def test_every_dependency_is_imported_by_the_library():
    imported = _imported_modules()
    unused = []
    for requirement in _pyproject()["project"]["dependencies"]:
        name = _name(requirement)
        module = NEEDED_BY[name][0] if name in NEEDED_BY else IMPORT_NAME.get(name, name)
        module = module.replace("-", "_")
        if module not in imported:
            unused.append(f"{name} (as {module})")
    assert not unused, f"declared in pyproject.toml but not imported by jaxreg/: {unused}"


@pytest.mark.parametrize("name", sorted(NEEDED_BY))
def test_indirect_dependencies_are_still_needed(name):
    """flatbuffers: jax.export's serialization imports it; check that it still does."""
    user, file_module = NEEDED_BY[name]
    spec = importlib.util.find_spec(file_module)
    assert spec is not None and spec.origin is not None, f"{file_module} is gone"
    assert re.search(rf"^\s*import {name}\b", Path(spec.origin).read_text(), re.M), (
        f"{user} no longer imports {name}: drop it from pyproject.toml"
    )


def test_no_distribution_is_listed_twice():
    project = _pyproject()["project"]
    lists = {"dependencies": project["dependencies"], **project["optional-dependencies"]}
    seen: dict[str, str] = {}
    twice = []
    for where, requirements in lists.items():
        for requirement in requirements:
            name = _name(requirement)
            if name in seen:
                twice.append(f"{name} in {seen[name]} and {where}")
            seen[name] = where
    assert not twice, f"listed more than once in pyproject.toml: {twice}"
