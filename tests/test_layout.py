"""The package layout: each package imports only the packages below it, no module imports
itself back through others, the root shows the architecture, and the public API that
``../shared/DESIGN.md`` documents resolves from ``jaxreg``."""

import ast
import importlib
import re
from pathlib import Path

import pytest

import jaxreg

ROOT = Path(jaxreg.__file__).parent

# Each package and the packages it may import (its docstring says the same).
ALLOWED = {
    "core": set(),
    "geometry": {"core"},
    "uncertainty": {"core", "geometry"},
    "search": {"core", "geometry"},
    "registration": {"core", "geometry", "uncertainty", "search"},
    "camera": {"core", "geometry"},
    "io": {"core", "geometry", "camera"},
    "pipeline": {"core", "geometry", "uncertainty", "search", "registration", "camera"},
    "synth": {"core", "geometry", "uncertainty", "camera"},
    "studies": {
        "core", "geometry", "uncertainty", "search", "registration", "camera", "io", "pipeline",
        "synth",
    },  # fmt: skip
    "cli": set(),  # filled below: every other package
}
ALLOWED["cli"] = set(ALLOWED) - {"cli"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """jaxreg modules that ``path`` imports anywhere: when it loads, inside its functions and
    under ``TYPE_CHECKING`` (``from a import b`` counts ``a.b`` when that is a module)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("jaxreg"):
            found.add(node.module)
            for alias in node.names:
                candidate = f"{node.module}.{alias.name}"
                if _path_of(candidate) is not None:
                    found.add(candidate)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("jaxreg"))
    return found


def _path_of(module: str) -> Path | None:
    base = ROOT.parent.joinpath(*module.split("."))
    for candidate in (base.with_suffix(".py"), base / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


SOURCES = sorted(ROOT.rglob("*.py"))


def test_root_shows_the_architecture():
    entries = sorted(p.name for p in ROOT.iterdir() if p.name != "__pycache__")
    packages = [name for name in entries if (ROOT / name).is_dir()]
    assert set(packages) == set(ALLOWED), packages
    assert set(entries) - set(packages) == {"__init__.py", "__main__.py"}, entries
    for name in packages:
        doc = ast.get_docstring(ast.parse((ROOT / name / "__init__.py").read_text()))
        assert doc and len(doc) > 80, f"jaxreg.{name} needs a docstring that says its job"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_packages_import_only_those_below_them(path):
    parts = path.relative_to(ROOT).parts
    if len(parts) == 1:  # jaxreg/__init__.py and __main__.py see everything
        return
    package = parts[0]
    for module in _imports(path):
        other = module.split(".")[1] if module.count(".") else None
        if other is None or other == package or other not in ALLOWED:
            continue
        assert other in ALLOWED[package], f"{path.relative_to(ROOT)} imports {module}"


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_no_private_module_of_another_package(path):
    """A package uses another's public modules; ``core``'s private modules serve everyone."""
    package = path.relative_to(ROOT).parts[0]
    for module in _imports(path):
        parts = module.split(".")
        if len(parts) > 2 and parts[1] not in (package, "core"):
            assert not any(p.startswith("_") for p in parts[2:]), (
                f"{path.relative_to(ROOT)} imports {module}"
            )


def test_no_import_cycles():
    """No module imports itself back through others, counting every import: one inside a
    function hides a circle from the loader until that function runs, not from the reader."""
    graph = {_module_name(p): _imports(p) for p in SOURCES}
    graph = {m: {t for t in targets if t in graph and t != m} for m, targets in graph.items()}
    # a package's __init__ importing its own modules is the package loading, not a cycle
    for module, targets in graph.items():
        graph[module] = {t for t in targets if not module.startswith(t + ".")}
    state: dict[str, int] = {}

    def visit(node, trail):
        state[node] = 1
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycle = trail[trail.index(nxt) :] + [nxt] if nxt in trail else [node, nxt]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if nxt not in state:
                visit(nxt, trail + [nxt])
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [module])


def _design_names() -> list[str]:
    for folder in (Path(__file__).resolve().parents[1] / ".." / "shared",):
        design = folder / "DESIGN.md"
        if design.is_file():
            api = design.read_text().split("## Public API", 1)[1].split("Command line:", 1)[0]
            return sorted(set(re.findall(r"\bjr\.([A-Za-z_][\w.]*\w)", api)))
    pytest.skip("../shared/DESIGN.md is absent: the documented names cannot be listed")


def test_design_names_resolve():
    names = _design_names()
    assert len(names) > 25, names
    for dotted in names:
        value = jaxreg
        for part in dotted.split("."):
            value = getattr(value, part)
        assert value is not None, dotted
    for module in ("jaxreg.io", "jaxreg.synth", "jaxreg.studies", "jaxreg.cli"):
        importlib.import_module(module)


# What a user calls, each name once: the top level a user learns the library from. The
# pipeline's stage records, files, scenes, studies and the building blocks are reached through
# their package (``jr.pipeline.SegmentRecord``, ``jr.io.read_pcd``, ``jr.geometry.lie``).
TOP_LEVEL = (
    # geometry: poses, alignment, robust kernels, metrics
    "SE3", "SO3", "se3_exp", "adjoint_transport", "kabsch", "umeyama", "align", "Alignment",
    "AlignmentStatus", "L2", "Huber", "Tukey", "Cauchy", "GemanMcClure", "Welsch", "Symmetry",
    "pose_error", "rotation_error", "add", "add_s", "canonicalise", "mssd", "mspd", "vsd",
    "average_recall", "BopRecall",
    # search
    "estimate_normals", "voxel_downsample", "build_grid", "NeighborGrid", "fpfh",
    "match_features", "FPFH", "FeatureMatches",
    # registration
    "icp", "multistart_icp", "select_best", "ICPOptions", "ICPStatus", "RegistrationResult",
    "rotation_inits", "perturbed_inits", "pca_inits", "icp_covariance", "organized_normals",
    "ProjectiveAssociation", "ransac_registration", "ransac_iterations", "RansacResult",
    "RansacStatus", "robust_kabsch", "RobustAlignment", "RobustStatus",
    # camera
    "Intrinsics", "RGBDFrame", "solve_pnp", "solve_pnp_planar", "PnPResult", "PlanarPnPResult",
    "PnPStatus", "detect_tags", "tag_object_points",
    # uncertainty
    "DepthNoise", "IsotropicNoise", "PointCovariance", "error_budget", "ErrorBudget",
    "pose_statistics", "PoseStatistics", "grasp_margin", "grasp_prediction", "GraspPrediction",
    "grasp_success_probability", "PoseBudget",
    # pipeline
    "estimate_pose", "estimate_poses", "track", "PoseEstimate", "EquivalentPose",
    "PipelineSettings", "SegmentSettings", "LiftSettings", "RegisterSettings",
    # the compiled programs kept between processes
    "enable_compilation_cache",
)  # fmt: skip
PACKAGES = tuple(sorted(ALLOWED))


def test_the_top_level_is_what_a_user_calls():
    """``dir(jaxreg)``: the list above and the packages, nothing private, nothing from outside
    the library (no ``TYPE_CHECKING``, ``annotations``, ``importlib``), each name once."""
    assert len(TOP_LEVEL) == len(set(TOP_LEVEL))
    assert sorted(jaxreg.__all__) == sorted(TOP_LEVEL)
    names = dir(jaxreg)
    public = [n for n in names if not (n.startswith("__") and n.endswith("__"))]
    assert sorted(public) == sorted(TOP_LEVEL + PACKAGES)
    assert len(public) <= 100
    for name in TOP_LEVEL:
        assert getattr(jaxreg, name).__module__.split(".")[0] in ("jaxreg", "jaxlie"), name
    for package in PACKAGES:
        assert getattr(jaxreg, package).__name__ == f"jaxreg.{package}"


def test_stage_records_live_in_the_pipeline():
    for name in ("Segmented", "CoarseSearch", "LiftedSegment", "Candidate", "MeasuredView",
                 "Registration", "SegmentRecord", "LiftRecord", "RegisterRecord"):
        assert not hasattr(jaxreg, name), name
        assert getattr(jaxreg.pipeline, name).__module__ == "jaxreg.pipeline.records"


def test_public_names_spell_color():
    """One spelling, numpy's and Open3D's: no public name of the library writes ``colour``."""
    offenders = []
    for path in SOURCES:
        if any(part.startswith("_") and part != "__init__.py" for part in
               path.relative_to(ROOT).parts):
            continue
        loaded = importlib.import_module(_module_name(path))
        for name in getattr(loaded, "__all__", ()):
            value = getattr(loaded, name)
            fields = getattr(value, "__dataclass_fields__", None) or getattr(
                value, "__annotations__", {}
            )
            offenders += [f"{name}.{f}" for f in fields if "colour" in f]
            offenders += [name] if "colour" in name.lower() else []
    assert not offenders, offenders


# Where docs/reference.md says each public name resolves: through its package
# (``jaxreg.geometry.random_rotations``, ``jaxreg.io.read_pcd``); the top level holds TOP_LEVEL.
LIBRARY = ("core", "geometry", "search", "registration", "camera", "uncertainty", "pipeline")
NAMESPACES = ("io", "synth", "studies")
PUBLIC_MODULES = sorted(
    _module_name(p)
    for p in SOURCES
    if len(p.relative_to(ROOT).parts) > 1
    and p.relative_to(ROOT).parts[0] in LIBRARY + NAMESPACES
    and not any(part.startswith("_") for part in _module_name(p).split("."))
)
# ICP's building blocks (prepare, run, unpad, ...) are reached through their module, as the
# reference says: names as generic as ``jr.registration.run`` would mislead.
THROUGH_THEIR_MODULE = {"jaxreg.registration.solver"}


@pytest.mark.parametrize("module", [m for m in PUBLIC_MODULES if m not in THROUGH_THEIR_MODULE])
def test_public_names_resolve_where_readme_says(module):
    """Every function and type in a public module's ``__all__`` is the same object through its
    package (constants stay in their module), and ``dir`` of the package lists it."""
    loaded = importlib.import_module(module)
    home = importlib.import_module(".".join(module.split(".")[:2]))
    values = {name: getattr(loaded, name) for name in getattr(loaded, "__all__", ())}
    own_name = module.rsplit(".", 1)[1]  # jaxreg.registration.icp: the module; jaxreg.icp: ICP
    missing = [
        name
        for name, value in values.items()
        if callable(value)
        and (getattr(home, name, None) is not value or name not in dir(home))
        and not (name == own_name and getattr(jaxreg, name, None) is value)
    ]
    assert not missing, f"{module}: {missing} do not resolve as {home.__name__}.<name>"
    for name in set(TOP_LEVEL) & set(values):
        assert getattr(jaxreg, name) is values[name], name


def test_type_checkers_see_the_exported_names():
    """``jaxreg/__init__.py``'s ``TYPE_CHECKING`` imports name exactly ``_EXPORTS``."""
    tree = ast.parse((ROOT / "__init__.py").read_text())
    block = next(n for n in tree.body if isinstance(n, ast.If) and "TYPE_CHECKING" in ast.dump(n))
    seen = {
        (node.module, alias.name)
        for node in block.body
        if isinstance(node, ast.ImportFrom) and node.module != "jaxreg"
        for alias in node.names
    }
    assert seen == {(m, n) for m, names in jaxreg._EXPORTS.items() for n in names}
