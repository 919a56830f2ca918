"""Turns a `make bench` log into benchmarks/README.md and README.md's summary of the goals.

Usage: python benchmarks/_report.py [LOG]      (LOG defaults to benchmarks/results/make_bench.txt)
       python benchmarks/_report.py --header   (prints the log's header: `make bench` runs it first)

The log is what `make bench` tees: a header (date, machine, CPU, versions of jax and the peers),
then for each `bench_*.py` a line `== bench_x.py (load average 1m 5m 15m, ...)` and the
script's output. The page shows the header, the table of goals (each value read from a table of
the same log), then each script's docstring (what it measures and how) and its output as
printed; README.md's block between the `bench:summary` markers says how many goals were met
and links the table. Nothing here holds a measured number: a goal whose table is missing from
the log reads "not in this log".
"""

from __future__ import annotations

import ast
import importlib.metadata
import os
import platform
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

HERE = Path(__file__).resolve().parent
LOG = HERE / "results" / "make_bench.txt"
PAGE = HERE / "README.md"
MAIN_README = HERE.parent / "README.md"
START, END = "<!-- bench:summary:start -->", "<!-- bench:summary:end -->"

# Distributions whose versions the header records, as (label, distribution).
VERSIONS = [
    ("jax", "jax"),
    ("jaxlib", "jaxlib"),
    ("numpy", "numpy"),
    ("scipy", "scipy"),
    ("open3d", "open3d"),
    ("small_gicp", "small_gicp"),
    ("opencv", "opencv-python-headless"),
]
FIRST_LINE = re.compile(r"make bench, (\d{4}-\d\d-\d\d \d\d:\d\d UTC), (\S+), (\d+) cores")
SECTION = re.compile(r"== (bench_\w+\.py) \(load average ([\d.]+) ([\d.]+) ([\d.]+)")
DASHES = re.compile(r"-+(  -+)*")


def header() -> str:
    """The lines `make bench` writes before the first script: date, machine, CPU, versions."""
    cpu = platform.processor() or "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    versions = []
    for label, dist in VERSIONS:
        try:
            versions.append(f"{label} {importlib.metadata.version(dist)}")
        except importlib.metadata.PackageNotFoundError:
            versions.append(f"{label} absent")
    date = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
    return "\n".join([
        f"make bench, {date}, {platform.machine()}, {os.cpu_count()} cores",
        f"cpu: {cpu}",
        f"versions: {', '.join(versions)}",
    ])  # fmt: skip


@dataclass
class Table:
    """One fixed-column table a script printed (`_timing.print_table`'s layout)."""

    title: str
    columns: list[str]
    rows: list[list[str]]

    def cell(self, column: str, **match: str) -> str | None:
        """The `column` cell of the first row whose cells start with the `match` values
        (keys are column names with spaces as underscores)."""
        index = {name.replace(" ", "_"): i for i, name in enumerate(self.columns)}
        for row in self.rows:
            if all(row[index[k]].startswith(v) for k, v in match.items()):
                return row[self.columns.index(column)]
        return None


@dataclass
class Section:
    """One script's part of the log."""

    script: str
    load: float  # 1-minute load average before the script
    lines: list[str]
    tables: list[Table] = field(default_factory=list)

    def table(self, title_start: str, *needles: str) -> Table | None:
        """The first table whose title starts with `title_start` and holds every needle (the
        workload a goal is about: a run with other sizes does not count)."""
        for table in self.tables:
            if table.title.startswith(title_start) and all(n in table.title for n in needles):
                return table
        return None

    def search(self, pattern: str) -> re.Match | None:
        return re.search(pattern, "\n".join(self.lines))


@dataclass
class Run:
    """A parsed `make bench` log."""

    date: str
    machine: str
    cores: str
    cpu: str | None
    versions: dict[str, str]
    sections: dict[str, Section]


def _tables(lines: list[str]) -> list[Table]:
    tables = []
    for i, line in enumerate(lines):
        if i == 0 or not DASHES.fullmatch(line.rstrip()):
            continue
        spans = [m.span() for m in re.finditer(r"-+", line)]
        columns = [lines[i - 1][a:b].strip() for a, b in spans]
        title = lines[i - 2].strip() if i >= 2 else ""
        rows = []
        for row in lines[i + 1 :]:
            if not row.strip():
                break
            rows.append([row[a:b].strip() for a, b in spans])
        tables.append(Table(title, columns, rows))
    return tables


def parse(text: str) -> Run:
    """Reads a log written by `make bench` (with or without the cpu and versions lines)."""
    lines = [line.rstrip() for line in text.splitlines()]
    first = FIRST_LINE.match(lines[0]) if lines else None
    if first is None:
        raise ValueError(
            "the log's first line is not `make bench, YYYY-MM-DD HH:MM UTC, ARCH, N cores`: "
            "pass a log that `make bench` wrote"
        )
    meta, sections, current = {}, {}, None
    for line in lines[1:]:
        if match := SECTION.match(line):
            current = Section(match[1], float(match[2]), [])
            sections[current.script] = current
        elif current is None:
            key, _, value = line.partition(": ")
            meta[key] = value
        elif "\x1b[" not in line:  # peers' coloured warnings (Open3D's) are not results
            current.lines.append(line)
    for section in sections.values():
        while section.lines and not section.lines[0]:
            section.lines.pop(0)
        while section.lines and not section.lines[-1]:
            section.lines.pop()
        section.tables = _tables(section.lines)
    versions = {}
    if "versions" in meta:
        versions = dict(v.split(" ", 1) for v in meta["versions"].split(", "))
    if not versions:  # an older log: the versions its scripts printed in their titles
        body = "\n".join(line for s in sections.values() for line in s.lines)
        for label, pattern in [("jax", r"\bjax (\d[\w.]*)"), ("open3d", r"(?i)\bopen3d (\d[\w.]*)"),
                               ("opencv", r"\bOpenCV (\d[\w.]*)")]:  # fmt: skip
            if match := re.search(pattern, body):
                versions[label] = f"{match[1]} (from the tables' titles)"
    return Run(first[1], first[2], first[3], meta.get("cpu"), versions, sections)


@dataclass(frozen=True)
class Goal:
    """A speed or accuracy goal and where its value is read from the log."""

    workload: str
    goal: str
    read: Callable[[Run], tuple[str, float] | None]  # (what to print, the compared value)
    at_least: float | None = None
    at_most: float | None = None

    def row(self, run: Run) -> list[str]:
        try:
            found = self.read(run)
        except (KeyError, AttributeError, TypeError, ValueError):
            found = None
        if found is None:
            return [self.workload, self.goal, "not in this log", "-"]
        text, value = found
        if self.at_least is None and self.at_most is None:
            return [self.workload, self.goal, text, "-"]
        met = (self.at_least is None or value >= self.at_least) and (
            self.at_most is None or value <= self.at_most
        )
        return [self.workload, self.goal, text, "yes" if met else "no"]


def _number(text: str) -> float:
    return float(text.rstrip("x%").replace(",", ""))


def _icp(row: str, jaxreg: str, peer: str) -> Callable[[Run], tuple[str, float]]:
    def read(run: Run) -> tuple[str, float]:
        section = run.sections["bench_icp.py"]
        ratio = section.table("Speed-up of jaxreg").cell("ratio", comparison=row)
        times = section.table("ICP point-to-point, milk.pcd @ 4 mm", "40 iterations")
        ours, theirs = (times.cell("median ms", solver=s) for s in (jaxreg, peer))
        return f"{ratio} ({ours} vs {theirs} ms)", _number(ratio)

    return read


def _normals(run: Run) -> tuple[str, float]:
    rows = run.sections["bench_neighbors.py"].lines
    found = [
        re.search(r"normals (\d+) .*open3d ([\d.]+) ms: jaxreg ([\d.]+)x", line) for line in rows
    ]
    n, open3d, ratio = max((m.groups() for m in found if m), key=lambda g: int(g[0]))
    return f"{ratio}x on {n} points (open3d {open3d} ms)", float(ratio)


def _pnp(method: str, peer: str) -> Callable[[Run], tuple[str, float]]:
    def read(run: Run) -> tuple[str, float]:
        table = run.sections["bench_pnp.py"].table("Planar PnP")
        ratio = table.cell("speed vs OpenCV (same stage)", tags="2000", method=method)
        ours, theirs = (table.cell("ms (median)", tags="2000", method=m) for m in (method, peer))
        return f"{ratio}x ({ours} vs {theirs} ms)", _number(ratio)

    return read


def _kabsch(run: Run) -> tuple[str, float]:
    table = run.sections["bench_kabsch.py"].table("Kabsch throughput: 10,000 problems x 1,000")
    ratio = table.cell("time vs jaxreg", solver="numpy SVD loop")
    ours = table.cell("median ms", solver="jaxreg.kabsch")
    theirs = table.cell("median ms", solver="numpy SVD loop")
    return f"{ratio} ({ours} vs {theirs} ms)", _number(ratio)


def _coldstart(run: Run) -> tuple[str, float]:
    table = run.sections["bench_coldstart.py"].table("Cold start")
    stage = "total to first result"
    warm = table.cell("seconds", setting="jaxreg, jr.enable_compilation_cache", stage=stage)
    peer = table.cell("seconds", setting="Open3D", stage=stage)
    if warm is None:  # a log from before the program store served library calls
        cold = table.cell("seconds", setting="jaxreg", stage=stage)
        warm = table.cell("seconds", setting="jaxreg, persistent", stage=stage)
        text = f"{warm} s with JAX's compilation cache ({cold} s with none; Open3D {peer} s)"
        return text, _number(warm)
    cold = table.cell("seconds", setting="jaxreg, no cache", stage=stage)
    return f"{warm} s with a warm cache ({cold} s with none; Open3D {peer} s)", _number(warm)


def _demo(run: Run) -> tuple[str, float]:
    table = run.sections["bench_coldstart.py"].table("A second `jaxreg demo` process")
    seconds = table.cell("seconds", caches="XLA cache + program store", step="in all (JAX)")
    return f"{seconds} s", _number(seconds)


def _pipeline(column: str, unit: str) -> Callable[[Run], tuple[str, float]]:
    def read(run: Run) -> tuple[str, float]:
        if not run.sections["bench_pipeline.py"].search(r"\b50 frames\b"):
            return None
        table = run.sections["bench_pipeline.py"].table("Pose from one frame")
        ours, theirs = (table.cell(column, pipeline=p) for p in ("jaxreg", "Open3D"))
        peer = f" (Open3D's pipeline {theirs}{unit})" if theirs else ""
        return f"{ours}{unit}{peer}", _number(ours)

    return read


def _basin(when: str) -> Callable[[Run], tuple[str, float] | None]:
    """The basin sweep's speed-up over the Open3D loop: ``when`` is "compiled" or "fresh"
    (a fresh process's first call with a warm compilation cache)."""

    def read(run: Run) -> tuple[str, float] | None:
        section = run.sections["bench_basin.py"]
        if section.table("Basin sweep", "5 angles x 256 starts") is None:
            return None
        first = section.search(r"first call \(compile included\) ([\d.]+)x")[1]
        if when == "compiled":
            ratio = section.search(r"/ jaxreg compiled ([\d.]+)x")[1]
            return f"{ratio}x ({first}x with its first compile)", float(ratio)
        ratio = section.search(r"fresh process's first call, warm cache ([\d.]+)x")[1]
        return f"{ratio}x", float(ratio)

    return read


def _import(run: Run) -> tuple[str, float]:
    table = run.sections["bench_coldstart.py"].table("Cold start")
    setting = "jaxreg, jr.enable_compilation_cache"
    seconds = table.cell("seconds", setting=setting, stage="import jaxreg")
    return f"{seconds} s", _number(seconds)


def _batch(run: Run) -> tuple[str, float]:
    section = run.sections["bench_batch.py"]
    table = section.table("Pixels to pose", "frames of a")
    fps = table.cell("frames per second", contender="estimate_poses (one call)")
    loop = table.cell("frames per second", contender="estimate_pose loop")
    ratio = section.search(r"estimate_poses / the loop ([\d.]+)x")[1]
    return f"{fps} frames/s ({ratio}x a loop's {loop})", _number(fps)


def _global(stage: str) -> Callable[[Run], tuple[str, float]]:
    def read(run: Run) -> tuple[str, float]:
        table = run.sections["bench_global.py"].table("FPFH (both clouds) and RANSAC")
        ratio = table.cell("open3d / jaxreg", stage=stage)
        ours, theirs = table.cell("jaxreg s", stage=stage), table.cell("open3d s", stage=stage)
        return f"{ratio}x ({ours} vs {theirs} s)", _number(ratio)

    return read


def _goals_row(script: str, goal: str) -> Callable[[Run], tuple[str, float] | None]:
    """The ``measured`` cell of the row of ``script``'s own "Goals" table whose goal starts
    with ``goal``; its number is the compared value (a ``%`` share, a ratio, a count)."""

    def read(run: Run) -> tuple[str, float] | None:
        table = run.sections[script].table("Goals")
        measured = table.cell("measured", goal=goal)
        if measured is None:
            return None
        return measured, _number(measured.split()[0])

    return read


def _real(run: Run) -> tuple[str, float]:
    table = run.sections["bench_real.py"].table("Real frames:")
    posed, instances = (table.cell(c, method="jaxreg") for c in ("posed", "instances"))
    posed = posed.split()[0]  # "35 (100%)"
    wrong = table.cell("wrong successes", method="jaxreg")
    inside = table.cell("inside allowing 2 mm", method="jaxreg")
    peer = table.cell("posed", method="Open3D")
    text = f"{posed}/{instances} posed, {wrong} wrong; box centre in the 95% region"
    text += f" (2 mm allowed): {inside}"
    if peer:
        text += f"; Open3D's pipeline {peer.split()[0]}/{instances} posed"
    return text, _number(posed) / _number(instances) * 100


GOALS = [
    Goal("single point-to-point ICP, milk.pcd at 4 mm, 40 iterations, grid built in the call",
         ">= 2x Open3D", _icp("single start: Open3D / jaxreg (builds its grid)",
                              "jaxreg icp (builds its grid)", "Open3D registration_icp"), 2),
    Goal("the same, 64 starts in one call", ">= 10x an Open3D loop",
         _icp("64 starts: Open3D loop / jaxreg multistart", "jaxreg multistart_icp",
              "Open3D loop"), 10),
    Goal("`estimate_normals`, k = 20, full milk.pcd", ">= 1.5x Open3D", _normals, 1.5),
    Goal("2,000 tags, IPPE, both candidates", ">= 5x an OpenCV loop",
         _pnp("jaxreg IPPE, batched", "OpenCV IPPE_SQUARE loop"), 5),
    Goal("2,000 tags, both candidates refined", ">= 10x an OpenCV IPPE + RefineLM loop",
         _pnp("jaxreg IPPE + LM x2 (max_iterations=100)", "OpenCV IPPE_SQUARE + RefineLM"), 10),
    Goal("batched Kabsch, 10k problems x 1k points, float32", ">= 4x a numpy SVD loop",
         _kabsch, 4),
    Goal("fresh process: import + first ICP, warm compilation cache", "<= 1.5 s", _coldstart,
         at_most=1.5),
    Goal("`import jaxreg` above `import jax`", "<= 0.5 s", _import, at_most=0.5),
    Goal("a second `jaxreg demo` process: JAX's tracing, lowering, compiling", "<= 2 s", _demo,
         at_most=2),
    Goal("pixels to pose, 50 synthetic frames: poses within 5 mm ADD-S", ">= 95%",
         _pipeline("success", ""), 95),
    Goal("pixels to pose: median warm time per frame", "<= 60 ms", _pipeline("ms", " ms"),
         at_most=60),
    Goal("pixels to pose, 8 frames in one call (`estimate_poses`)", "reported", _batch),
    Goal("basin sweep, 1,280 ICP starts, compiled", ">= 5x an Open3D loop", _basin("compiled"),
         5),
    Goal("the same, a fresh process's first call, warm compilation cache",
         ">= 3x an Open3D loop", _basin("fresh"), 3),
    Goal("FPFH on both clouds of a Kinect scene", ">= 1x Open3D", _global("fpfh"), 1),
    Goal("RANSAC with matching, the same clouds", ">= 1x Open3D", _global("ransac"), 1),
    Goal("error bars, 120 synthetic frames: the truth inside the 95% region (6-dof)",
         "85-99%", _goals_row("bench_calibration.py", "95% region covers 85-99% (6-dof)"),
         85, 99),
    Goal("real YCB-Video frames, dataset masks: posed within 10% ADD-S", "reported", _real),
    Goal("tracking, real consecutive frames: steps followed within 10% ADD-S", ">= 95%",
         _goals_row("bench_track.py", ">= 95% of the steps followed"), 95),
    Goal("tracking: a step against a warm `estimate_pose` on the same frame", "<= 0.2",
         _goals_row("bench_track.py", "a step <= 1/5"), at_most=0.2),
    Goal("held-out synthetic frames with look-alike clutter, depth alone: wrong poses claimed",
         "0", _goals_row("bench_silent.py", "no wrong pose reported as found, depth"), at_most=0),
    Goal("the same frames, depth alone: refusals", "<= 5%",
         _goals_row("bench_silent.py", "refusals <= 5%, depth"), at_most=5),
    Goal("the same frames with the model's colours: wrong poses claimed", "0",
         _goals_row("bench_silent.py", "no wrong pose reported as found, with"), at_most=0),
    Goal("the same frames with the model's colours: refusals", "<= 5%",
         _goals_row("bench_silent.py", "refusals <= 5%, with"), at_most=5),
]  # fmt: skip


def _markdown(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(cell.replace("|", "\\|") for cell in r) + " |" for r in rows]


def summary(run: Run) -> list[str]:
    """The goals table, each value as this run's log printed it."""
    return _markdown(["workload", "goal", "this run", "met?"], [g.row(run) for g in GOALS])


def _docstring(script: str) -> str:
    """The script's docstring without its usage lines."""
    text = ast.get_docstring(ast.parse((HERE / script).read_text())) or ""
    paragraphs = [p for p in text.split("\n\n") if not p.startswith("Usage:")]
    return "\n\n".join(paragraphs)


def page(run: Run, log: Path) -> str:
    """benchmarks/README.md for the run in `log`."""
    loads = [s.load for s in run.sections.values()]
    versions = ", ".join(f"{k} {v}" for k, v in run.versions.items()) or "not recorded"
    recorded = {label for label, _ in VERSIONS}
    missing = sorted(recorded - set(run.versions))
    if missing:
        versions += f"; not recorded in this log: {', '.join(missing)}"
    where = log.resolve()
    if where.is_relative_to(HERE.parent):
        where = where.relative_to(HERE.parent)
    out = [
        "# Benchmarks",
        "",
        f"<!-- Written by benchmarks/_report.py from {where}; edit the scripts, not this page. -->",
        "",
        "`make bench` runs every `bench_*.py` here with the peers in the same run, keeps the "
        f"whole output in `{where}` and writes this page from it; `make bench-report` "
        "rewrites the page (and README.md's summary) from the kept log. Each script times its "
        "contenders in interleaved rounds (every contender once per round, medians reported), "
        "so a shared machine's load falls on all alike; ratios still move by tens of percent "
        "between runs on a loaded machine.",
        "",
        "| the run shown | |",
        "|---|---|",
        f"| run | make bench, {run.date} |",
        f"| machine | {run.machine}, {run.cores} cores |",
        f"| CPU | {run.cpu or 'not recorded in this log'} |",
        f"| load average (1 minute, before each script) | {min(loads):.2f}-{max(loads):.2f} |",
        f"| versions | {versions} |",
        "",
        "## Where each goal stands",
        "",
        *summary(run),
    ]
    for script, section in run.sections.items():
        out += ["", f"## {script}", "", _docstring(script) if (HERE / script).exists() else ""]
        out += ["", f"Load average before the script: {section.load:.2f}.", "", "```text"]
        out += [*section.lines, "```"]
    return "\n".join(out) + "\n"


def summary_block(run: Run) -> list[str]:
    """README.md's lines from the start marker to the end marker: how many of the judged
    goals this run met, and where the table of them is."""
    judged = [row[3] for row in (goal.row(run) for goal in GOALS) if row[3] != "-"]
    return [
        START,
        f"From `make bench` of {run.date[:10]} ({run.machine}, {run.cores} cores): "
        f"{judged.count('yes')} of {len(judged)} judged goals met. "
        "[benchmarks/README.md](benchmarks/README.md#where-each-goal-stands) lists every goal "
        "with this run's figure, then every table.",
        END,
    ]


def write(log: Path = LOG) -> None:
    """Writes benchmarks/README.md and README.md's summary block from `log`."""
    run = parse(log.read_text())
    PAGE.write_text(page(run, log))
    readme = MAIN_README.read_text()
    if START not in readme or END not in readme:
        raise ValueError(f"README.md lacks the {START} ... {END} markers for the summary")
    before, rest = readme.split(START, 1)
    after = rest.split(END, 1)[1]
    MAIN_README.write_text(before + "\n".join(summary_block(run)) + after)


if __name__ == "__main__":
    if sys.argv[1:] == ["--header"]:
        print(header())
    else:
        write(Path(sys.argv[1]) if len(sys.argv) > 1 else LOG)
