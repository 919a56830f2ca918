"""Cold start: a fresh Python process imports jaxreg and runs its first ICP, compile included.

Usage: python benchmarks/bench_coldstart.py [--data DIR] [--runs 3] [--skip-demo]

Each run is a new interpreter (``subprocess``), timed stage by stage: ``import jax``, ``import
jaxreg`` (which loads no submodule), loading the modules ``jr.icp`` and ``jr.build_grid`` need
(their first use), the first neighbour-grid build (numba loads its compiled loops from the
on-disk cache), the first ``icp`` call (tracing and XLA compilation, or loading) and a second
call (the steady state). Reading the cloud (``jr.io``, PCD parsing, voxel downsampling) is
timed apart and left out of the total, as Open3D's is. Source: milk.pcd at 4 mm (3.7k points)
against a moved copy, 2 cm, 40 iterations; the same as ``bench_icp.py``. Three settings, each
after one process filled its cache: no cache; JAX's persistent compilation cache alone
(``JAX_COMPILATION_CACHE_DIR``, a user setting: the library never changes JAX's configuration
itself); and ``jr.enable_compilation_cache(folder)``, which adds jaxreg's program store (the
ICP loop's executable loaded with no tracing or lowering). Runs are interleaved with Open3D's
import and first ``registration_icp``, timed the same way, and the medians printed.

Second ``jaxreg demo`` process: the command keeps JAX's compilation cache and, beside it, the
pipeline's compiled programs (:mod:`jaxreg.core._program_cache`: XLA executables, loaded with no
tracing or lowering). After one run fills both, fresh processes run ``jaxreg demo`` with the
XLA cache alone and with the program store too; each reports the seconds JAX spent tracing,
lowering and compiling or loading executables (its own ``jax.monitoring`` events, plus the
store's ``/jaxreg/program_cache/executable_load_duration``, which JAX's events do not see),
which is what the issue's "under 2 s compiling" is about, the process's CPU seconds in those
steps, and how many programs it compiled or loaded (each eager JAX operation on new shapes is
one).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from _timing import DATA, print_table

JAXREG_RUN = r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np
import jax
t1 = time.perf_counter()
import jaxreg as jr
t2 = time.perf_counter()
if sys.argv[2]:
    jr.enable_compilation_cache(sys.argv[2])
icp, build_grid = jr.icp, jr.build_grid
t3 = time.perf_counter()
points = jr.voxel_downsample(jr.io.load_points(sys.argv[1]), 0.004).astype(np.float32)
moved = points @ np.array([[1, -0.05, 0], [0.05, 1, 0], [0, 0, 1]], np.float32).T + 0.005
t4 = time.perf_counter()
grid = build_grid(moved, 0.02)
t5 = time.perf_counter()
options = dict(max_correspondence_distance=0.02, max_iterations=40, tolerance=0.0)
jax.block_until_ready(icp(points, moved, neighbors=grid, **options))
t6 = time.perf_counter()
jax.block_until_ready(icp(points, moved, **options))
t7 = time.perf_counter()
print(json.dumps({"import jax": t1 - t0, "import jaxreg": t2 - t1,
                  "load icp's modules": t3 - t2, "read the cloud (not counted)": t4 - t3,
                  "grid build": t5 - t4, "first icp": t6 - t5,
                  "second icp (builds its grid)": t7 - t6,
                  "total to first result": t6 - t0 - (t4 - t3)}))
"""

OPEN3D_RUN = r"""
import json, sys, time
t0 = time.perf_counter()
import numpy as np
import open3d as o3d
t1 = time.perf_counter()
cloud = o3d.io.read_point_cloud(sys.argv[1]).voxel_down_sample(0.004)
points = np.asarray(cloud.points)
moved = points @ np.array([[1, -0.05, 0], [0.05, 1, 0], [0, 0, 1]]).T + 0.005
src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(moved))
t2 = time.perf_counter()
reg = o3d.pipelines.registration
reg.registration_icp(src, tgt, 0.02, np.eye(4), reg.TransformationEstimationPointToPoint(),
                     reg.ICPConvergenceCriteria(0.0, 0.0, 40))
t3 = time.perf_counter()
print(json.dumps({"import open3d": t1 - t0, "first registration_icp": t3 - t2,
                  "total to first result": t3 - t0 - (t2 - t1)}))
"""


DEMO_RUN = r"""
import collections, json, sys, time
t0 = time.perf_counter()
from jax import monitoring
seconds = collections.defaultdict(float)
names = {"jaxpr_trace_duration": "tracing", "jaxpr_to_mlir_module_duration": "lowering",
         "backend_compile_duration": "compiling or loading",
         "executable_load_duration": "compiling or loading"}
def listen(event, duration, **_):
    name = names.get(event.rsplit("/", 1)[-1])
    if name:
        seconds[name] += duration
    if name == "compiling or loading":
        seconds["programs compiled or loaded (count)"] += 1
monitoring.register_event_duration_secs_listener(listen)
from jax._src import compiler
from jaxreg.core import _program_cache
def cpu_seconds(fn):  # the process's CPU seconds (all threads) inside fn
    def timed(*args, **kwargs):
        start = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            seconds["CPU, compiling or loading"] += time.process_time() - start
    return timed
compiler.compile_or_get_cached = cpu_seconds(compiler.compile_or_get_cached)
_program_cache._load = cpu_seconds(_program_cache._load)
from jaxreg.cli import commands as cli
parser, _ = cli.build_parser()
args = parser.parse_args(["demo", "--json"])
cli.enable_compilation_cache()
if sys.argv[1] == "xla-only":
    _program_cache.set_folder(None)
args.run(args)
seconds["in all (JAX)"] = sum(seconds[name] for name in set(names.values()))
seconds["wall, whole process"] = time.perf_counter() - t0
print(json.dumps(seconds))
"""


def run(script: str, env: dict, *args: str | Path) -> dict:
    out = subprocess.run(
        [sys.executable, "-c", script, *map(str, args)], env=env, capture_output=True, text=True
    )
    if out.returncode != 0:
        raise RuntimeError(out.stderr[-2000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--skip-demo", action="store_true", help="only the first-ICP rows")
    args = parser.parse_args()
    pcd = args.data / "pcl" / "milk.pcd"
    if not pcd.is_file():
        raise SystemExit(f"milk.pcd not found under {args.data}/pcl: pass --data or JAXREG_DATA")
    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    try:
        import open3d  # noqa: F401

        have_o3d = True
    except ImportError:
        have_o3d = False
        print("open3d unavailable: its rows are skipped")
    with tempfile.TemporaryDirectory() as xla, tempfile.TemporaryDirectory() as store:
        xla_only = dict(env, JAX_COMPILATION_CACHE_DIR=xla)
        xla_only["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
        settings = {
            "jaxreg, no cache": (env, ""),
            "jaxreg, JAX's compilation cache only": (xla_only, ""),
            "jaxreg, jr.enable_compilation_cache": (env, store),
        }
        run(JAXREG_RUN, xla_only, pcd, "")  # fills the caches
        run(JAXREG_RUN, env, pcd, store)
        samples = {name: [] for name in settings}
        samples["Open3D"] = []
        for _ in range(args.runs):  # interleaved, so that load falls on all alike
            for name, (environ, folder) in settings.items():
                samples[name].append(run(JAXREG_RUN, environ, pcd, folder))
            if have_o3d:
                samples["Open3D"].append(run(OPEN3D_RUN, env, pcd))
    rows = []
    for name, runs in samples.items():
        for stage in runs[0] if runs else []:
            median = statistics.median(r[stage] for r in runs)
            rows.append([name, stage, f"{median:.2f}"])
    print_table(
        f"Cold start, fresh process each run (median of {args.runs}), milk.pcd @ 4 mm, "
        f"{os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}",
        ["setting", "stage", "seconds"],
        rows,
    )
    if not args.skip_demo:
        demo_second_process(env, args.runs)


def demo_second_process(env: dict, runs: int) -> None:
    """``jaxreg demo`` in fresh processes after a first run filled the caches."""
    with tempfile.TemporaryDirectory() as cache:
        cached = dict(env, JAXREG_CACHE_DIR=cache)
        run(DEMO_RUN, cached, "store")  # fills the XLA cache and the program store
        run(DEMO_RUN, cached, "xla-only")  # and the XLA cache for the unstored programs
        samples = {"XLA cache only": [], "XLA cache + program store": []}
        for _ in range(runs):
            samples["XLA cache only"].append(run(DEMO_RUN, cached, "xla-only"))
            samples["XLA cache + program store"].append(run(DEMO_RUN, cached, "store"))
    rows = [
        [name, stage, f"{statistics.median(r.get(stage, 0.0) for r in found):.{digits}f}"]
        for name, found in samples.items()
        for stage, digits in (("tracing", 2), ("lowering", 2), ("compiling or loading", 2),
                              ("in all (JAX)", 2), ("CPU, compiling or loading", 2),
                              ("wall, whole process", 2),
                              ("programs compiled or loaded (count)", 0))
    ]  # fmt: skip
    print_table(
        f"A second `jaxreg demo` process (median of {runs}): JAX's seconds by step, "
        f"{os.cpu_count()} cores",
        ["caches", "step", "seconds"],
        rows,
    )


if __name__ == "__main__":
    main()
