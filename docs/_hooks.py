"""mkdocs hooks (mkdocs.yml's ``hooks``): the site's pages are the repository's own files at their
own paths, so every relative link in them works as it does on the repository, and the API
pages are written from the library itself.

* ``README.md`` is the first page (the guide), ``docs/reference.md`` beside it, with the other
  Markdown files and images that the README links to (``benchmarks/README.md``,
  ``paper_figs/README.md``, ``paper_figs/key/*.png``, ``docs/view.png``).
* ``docs/api/index.md`` lists the top level (``jaxreg.__all__``); ``docs/api/<package>.md``
  renders each package's public modules with mkdocstrings, and the public names a package
  re-exports from its private modules. Written at build time from what the packages export,
  so a name added to the library is documented without editing a page.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from pathlib import Path

from mkdocs.structure.files import File, Files

ROOT = Path(__file__).resolve().parents[1]
# Repository files that are pages or images of the site, at their repository paths.
PAGES = ("README.md", "docs/reference.md", "benchmarks/README.md", "paper_figs/README.md")
IMAGES = ("docs/view.png", "paper_figs/key/*.png")
# The packages whose API pages are written, in the order the reference's table lists them.
PACKAGES = (
    "geometry", "search", "registration", "camera", "uncertainty", "pipeline", "io", "synth",
    "studies", "core", "cli",
)  # fmt: skip


def on_files(files: Files, config) -> Files:
    """The repository's pages and images, and the generated API pages, in place of
    ``docs_dir``'s files (the theme's files stay)."""
    docs = Path(config["docs_dir"]).resolve()
    kept = [f for f in files if not Path(f.abs_src_path or "").resolve().is_relative_to(docs)]
    out = Files(kept)
    use_urls = config["use_directory_urls"]
    paths = list(PAGES) + [str(p.relative_to(ROOT)) for g in IMAGES for p in ROOT.glob(g)]
    for path in paths:
        out.append(File(path, str(ROOT), config["site_dir"], use_urls))
    out.append(File.generated(config, "docs/api/index.md", content=_top_level_page()))
    for package in PACKAGES:
        out.append(File.generated(config, f"docs/api/{package}.md", content=_package_page(package)))
    return out


def _first_line(value) -> str:
    doc = inspect.getdoc(value) or ""
    return doc.strip().split("\n\n")[0].replace("\n", " ").replace("|", "\\|")


def _public_modules(package: str) -> list[str]:
    loaded = importlib.import_module(package)
    return [
        f"{package}.{info.name}"
        for info in pkgutil.iter_modules(loaded.__path__)
        if not info.name.startswith("_")
    ]


def _identifier(value, name: str) -> str | None:
    """The path the API pages document ``value`` under: its module's when public; else the
    public module of its package whose ``__all__`` re-exports it, else its package's ("Also in
    this package"); ``None`` when no package exports it (private: not documented)."""
    module = getattr(value, "__module__", "") or ""
    if not module.startswith("jaxreg"):
        return None  # jaxlie's SE3 and SO3: documented by jaxlie
    parts = module.split(".")
    if not any(part.startswith("_") for part in parts[1:]):
        return f"{module}.{name}"
    package = ".".join(parts[:2])
    for public in _public_modules(package):
        loaded = importlib.import_module(public)
        if name in getattr(loaded, "__all__", ()) and getattr(loaded, name, None) is value:
            return f"{public}.{name}"
    if getattr(importlib.import_module(package), name, None) is value:
        return f"{package}.{name}"
    return None


def _top_level_page() -> str:
    import jaxreg

    rows = []
    for name in jaxreg.__all__:
        value = getattr(jaxreg, name)
        identifier = _identifier(value, name)
        link = f"[`{name}`][{identifier}]" if identifier else f"`{name}`"
        rows.append(f"| {link} | {_first_line(value)} |")
    packages = ", ".join(f"[`jaxreg.{p}`]({p}.md)" for p in PACKAGES)
    return "\n".join(
        [
            "# The top level",
            "",
            "`import jaxreg as jr`: what a user calls, each name once. Everything else is "
            f"reached through its package: {packages}.",
            "",
            "| name | what |",
            "|---|---|",
            *rows,
            "",
        ]
    )


def _package_page(package: str) -> str:
    loaded = importlib.import_module(f"jaxreg.{package}")
    modules = [m.rsplit(".", 1)[1] for m in _public_modules(f"jaxreg.{package}")]
    lines = [
        f"# jaxreg.{package}",
        "",
        f"::: jaxreg.{package}",
        "    options:",
        "      members: false",
        "      show_root_heading: false",
        "",
    ]
    for module in modules:
        lines += [f"::: jaxreg.{package}.{module}", ""]
        if not hasattr(importlib.import_module(f"jaxreg.{package}.{module}"), "__all__"):
            lines[-1:] = ["    options:", "      members: false", ""]  # its docstring only
    # public names the package re-exports from its private modules
    private = {}
    for name in dir(loaded):
        value = getattr(loaded, name)
        home = getattr(value, "__module__", "") or ""
        if home.startswith(f"jaxreg.{package}.") and home.split(".")[2].startswith("_"):
            documented = _identifier(value, name) == f"jaxreg.{package}.{name}"
            if documented and (inspect.isclass(value) or inspect.isfunction(value)):
                private.setdefault(home, []).append(name)
    if private:
        lines += ["## Also in this package", ""]
        for home, names in sorted(private.items()):
            for name in sorted(names, key=lambda n: (not n[0].isupper(), n)):
                lines += [
                    f"::: jaxreg.{package}.{name}",
                    "    options:",
                    "      heading_level: 3",
                    "",
                ]
    return "\n".join(lines)
