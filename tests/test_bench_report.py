"""benchmarks/_report.py: the benchmark page and README.md's summary are what the kept
`make bench` log says, and nothing else."""

import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("_report", ROOT / "benchmarks" / "_report.py")
report = importlib.util.module_from_spec(_spec)
sys.modules["_report"] = report  # dataclasses look their module up while the file runs
_spec.loader.exec_module(report)

LOG = """make bench, 2031-01-02 03:04 UTC, aarch64, 8 cores
cpu: Some CPU
versions: jax 9.9.9, jaxlib 9.9.9, numpy 3.0, scipy 2.0, open3d absent, small_gicp 2.0, opencv 6.0
== bench_kabsch.py (load average 0.50 0.40 0.30, 03:04 UTC)

Kabsch throughput: 10,000 problems x 1,000 points, float32, cpu (aarch64)
                       solver  median ms  problems/s  time vs jaxreg  max rot err deg
-----------------------------  ---------  ----------  --------------  ---------------
 jaxreg.kabsch (jit, batched)        1.0      10,000            1.0x           0.1000
numpy SVD loop (timed on 10)         3.0       3,333            3.0x           0.1000
== bench_global.py (load average 2.00 1.00 1.00, 03:05 UTC)
\x1b[1;33m[Open3D WARNING] a peer's coloured warning\x1b[0;m

FPFH (both clouds) and RANSAC (matching included)
 stage  jaxreg s  open3d s  open3d / jaxreg
------  --------  --------  ---------------
  fpfh     0.500     1.000             2.00
ransac     0.400     0.200             0.50
"""


def _rows(run):
    return {row[0]: row for row in (goal.row(run) for goal in report.GOALS)}


def test_goals_are_read_from_the_log_and_judged():
    run = report.parse(LOG)
    assert (run.date, run.machine, run.cores, run.cpu) == ("2031-01-02 03:04 UTC", "aarch64",
                                                          "8", "Some CPU")  # fmt: skip
    assert run.versions["jax"] == "9.9.9" and run.versions["open3d"] == "absent"
    rows = _rows(run)
    kabsch = rows["batched Kabsch, 10k problems x 1k points, float32"]
    assert kabsch[2:] == ["3.0x (1.0 vs 3.0 ms)", "no"]  # goal: >= 4x
    assert rows["FPFH on both clouds of a Kinect scene"][2:] == ["2.00x (0.500 vs 1.000 s)", "yes"]
    assert rows["RANSAC with matching, the same clouds"][3] == "no"
    # A script missing from the log is said to be missing, not guessed.
    assert rows["the same, 64 starts in one call"][2:] == ["not in this log", "-"]
    assert not any("WARNING" in line for line in run.sections["bench_global.py"].lines)
    # A run of another size is not the goal's workload.
    smaller = report.parse(LOG.replace("10,000 problems x 1,000", "1,000 problems x 200"))
    assert _rows(smaller)[kabsch[0]][2] == "not in this log"


def test_page_shows_the_run_and_every_script():
    run = report.parse(LOG)
    page = report.page(run, ROOT / "benchmarks" / "results" / "make_bench.txt")
    assert "| run | make bench, 2031-01-02 03:04 UTC |" in page
    assert "| load average (1 minute, before each script) | 0.50-2.00 |" in page
    assert "## bench_kabsch.py" in page and "## bench_global.py" in page
    assert "Some CPU" in page and "small_gicp 2.0" in page


def test_a_log_not_written_by_make_bench_is_refused():
    with pytest.raises(ValueError, match="make bench"):
        report.parse("Kabsch throughput\n")


def test_the_pages_match_the_kept_log():
    """README.md's summary and benchmarks/README.md's numbers are what `make bench-report`
    writes from benchmarks/results/make_bench.txt: a number edited by hand fails here. (The
    scripts' docstrings on the page may lag an edit until the page is regenerated.)"""
    run = report.parse(report.LOG.read_text())
    assert all(row[2] != "not in this log" for row in _rows(run).values())
    page = (ROOT / "benchmarks" / "README.md").read_text()
    expected = report.page(run, report.LOG)
    head = expected.split("\n## bench_", 1)[0]
    assert page.startswith(head), "benchmarks/README.md: run `make bench-report`"
    for section in run.sections.values():
        assert "\n".join(["```text", *section.lines, "```"]) in page, section.script
    readme = (ROOT / "README.md").read_text()
    block = readme.split(report.START, 1)[1].split(report.END, 1)[0]
    assert block == "\n".join(["", *report.summary_block(run)[1:-1], ""])


TRACK_AND_SILENT = """make bench, 2031-01-02 03:04 UTC, aarch64, 8 cores
== bench_real.py (load average 0.50 0.40 0.30, 03:04 UTC)

Real frames: 4 YCB-Video instances, dataset masks, default settings (posed: ...)
method  instances  posed     wrong successes  refused  centre inside  inside allowing 2 mm
------  ---------  --------  ---------------  -------  -------------  --------------------
jaxreg          4  3 (75%)                0        1            2/3                   3/3
Open3D          4  4 (100%)               0        0              -                     -
== bench_silent.py (load average 0.50 0.40 0.30, 03:05 UTC)

Goals
                                                     goal  measured    met
---------------------------------------------------------  --------  -----
              no wrong pose reported as found, depth only   1 wrong  False
                               refusals <= 5%, depth only     12.5%  False
no wrong pose reported as found, with the model's colours   0 wrong   True
                 refusals <= 5%, with the model's colours      4.5%   True
== bench_track.py (load average 0.50 0.40 0.30, 03:06 UTC)

Goals
                                 goal  measured    met
-------------------------------------  --------  -----
         >= 95% of the steps followed       96%   True
a step <= 1/5 of a warm estimate_pose      0.21  False
"""


def test_goals_read_from_the_scripts_own_goal_tables():
    """The tracking, held-out and real-frame rows read the scripts' own tables; a goal a
    script judges is judged again here from its number, not from the script's verdict."""
    rows = _rows(report.parse(TRACK_AND_SILENT))
    held_out = "held-out synthetic frames with look-alike clutter, depth alone"
    assert rows[f"{held_out}: wrong poses claimed"][2:] == ["1 wrong", "no"]
    assert rows["the same frames, depth alone: refusals"][2:] == ["12.5%", "no"]
    colours = "the same frames with the model's colours"
    assert rows[f"{colours}: wrong poses claimed"][2:] == ["0 wrong", "yes"]
    assert rows[f"{colours}: refusals"][2:] == ["4.5%", "yes"]
    followed = "tracking, real consecutive frames: steps followed within 10% ADD-S"
    assert rows[followed][2:] == ["96%", "yes"]
    step = "tracking: a step against a warm `estimate_pose` on the same frame"
    assert rows[step][2:] == ["0.21", "no"]
    real = rows["real YCB-Video frames, dataset masks: posed within 10% ADD-S"]
    assert real[2] == (
        "3/4 posed, 0 wrong; box centre in the 95% region (2 mm allowed): 3/3; "
        "Open3D's pipeline 4/4 posed"
    )
