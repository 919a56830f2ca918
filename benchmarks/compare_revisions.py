"""A warm ``estimate_pose`` frame in the working tree beside the same frame at another revision,
and where the working tree's time goes: the error budget's probes and perturbed fits, the
coarse search, the rest. A tool for a change's author, not part of ``make bench``.

Usage: python benchmarks/compare_revisions.py --against REV [--seeds 900 901] [--rounds 5]

The other contender is the library as ``git archive REV`` gives it, unpacked in a temporary
folder (the repository's history is needed). Each contender runs in its own process (one
``PYTHONPATH`` each, the same interpreter and packages), and the two are timed frame by frame
in rounds, the order turning each round, so the machine's load falls on both alike.

Frames: ``jaxreg.synth.tabletop_scene(seed, object=...)`` for every seed and every object,
``estimate_pose`` with the scene's symmetry and defaults. Each frame is run twice untimed in
each process (the first compiles), then once per round; a frame's figure is the median of its
rounds, the table's the median of the frames'.

The working tree's own parts, timed inside the same calls: the answer's probes
(``_answer._probe``: the answer turned about the model's axes, refined and judged, for the
winner and for a rival the twin check refines), the pose budget (``pose_budget``: the perturbed
fits and every other term) and the coarse search. "without the budget" is the frame less the
probes and the budget: what a frame would cost if the error budget cost nothing.
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

from _timing import print_table

from jaxreg.synth import OBJECTS

ROOT = Path(__file__).resolve().parents[1]

# A contender's process: reads "seed object" lines, answers one JSON line per frame (its
# milliseconds, success, translation error, and the parts it has).
WORKER = r"""
import collections, importlib, json, sys, time
import jaxreg as jr

parts = collections.defaultdict(float)

def timed(module, name, label):
    try:
        module = importlib.import_module(module)
        inner = getattr(module, name)
    except (ImportError, AttributeError):
        return  # the other revision may not have it

    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            parts[label] += time.perf_counter() - start

    setattr(module, name, wrapper)

timed("jaxreg.pipeline._answer", "_probe", "probes")  # the answer's
timed("jaxreg.pipeline._register_stage", "_probe", "probes")  # a rival's, at older revisions
timed("jaxreg.pipeline._fits", "_probe", "probes")  # a rival's
timed("jaxreg.pipeline._register_stage", "pose_budget", "budget")
timed("jaxreg.pipeline.estimate", "coarse_search", "coarse")
scenes = {}
for line in sys.stdin:
    seed, name = line.split()
    if (seed, name) not in scenes:
        scenes[seed, name] = jr.synth.tabletop_scene(seed=int(seed), object=name)
    scene = scenes[seed, name]
    parts.clear()
    start = time.perf_counter()
    est = jr.estimate_pose(scene.frame, scene.model_points, symmetry=scene.symmetry)
    ms = (time.perf_counter() - start) * 1e3
    error = None
    if est.success:
        error = float(jr.pose_error(est.pose, scene.truth, symmetry=scene.symmetry)[0]) * 1e3
    out = dict(ms=ms, ok=bool(est.success), mm=error, parts={k: v * 1e3 for k, v in parts.items()})
    print(json.dumps(out), flush=True)
"""


class Contender:
    """One library checkout in its own process (``path`` first on its ``PYTHONPATH``)."""

    def __init__(self, name: str, path: Path):
        self.name = name
        env = dict(os.environ, PYTHONPATH=str(path))
        self.process = subprocess.Popen(
            [sys.executable, "-c", WORKER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            text=True, env=env, cwd=tempfile.gettempdir(),
        )  # fmt: skip

    def frame(self, seed: int, name: str) -> dict:
        self.process.stdin.write(f"{seed} {name}\n")
        self.process.stdin.flush()
        line = self.process.stdout.readline()
        if not line:
            raise SystemExit(f"the {self.name} process ended (its error is above)")
        return json.loads(line)

    def close(self) -> None:
        self.process.stdin.close()
        self.process.wait()


def revision_tree(commit: str, into: Path) -> Path:
    """The library's files at ``commit`` unpacked under ``into`` (``git archive``)."""
    archive = subprocess.run(
        ["git", "-C", str(ROOT), "archive", commit, "jaxreg"], capture_output=True, check=False
    )
    if archive.returncode:
        raise SystemExit(
            f"git archive {commit} failed ({archive.stderr.decode().strip()}): comparing "
            "needs the repository's history (a full clone, not a shallow one)"
        )
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive.stdout, check=True)
    return into


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", required=True, help="the other revision (a commit, a tag)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[900, 901])
    parser.add_argument("--rounds", type=int, default=5)
    args = parser.parse_args()
    frames = [(seed, name) for seed in args.seeds for name in OBJECTS]
    with tempfile.TemporaryDirectory() as folder:
        contenders = [
            Contender("working tree", ROOT),
            Contender(args.against, revision_tree(args.against, Path(folder))),
        ]
        for frame in frames:
            for contender in contenders:
                contender.frame(*frame)
                contender.frame(*frame)
        runs = {c.name: {frame: [] for frame in frames} for c in contenders}
        for round_ in range(args.rounds):
            for k, frame in enumerate(frames):
                turn = (round_ + k) % len(contenders)
                for contender in contenders[turn:] + contenders[:turn]:
                    runs[contender.name][frame].append(contender.frame(*frame))
        for contender in contenders:
            contender.close()

    ours, theirs = (runs[c.name] for c in contenders)

    def median(records, key=None):
        return statistics.median(
            r["ms"] if key is None else r["parts"].get(key, 0.0) for r in records
        )

    rows, medians = [], {"ours": [], "theirs": [], "bare": []}
    for frame in frames:
        mine, base = ours[frame], theirs[frame]
        ms, then = median(mine), median(base)
        probes, budget, coarse = (median(mine, key) for key in ("probes", "budget", "coarse"))
        bare = statistics.median(
            r["ms"] - r["parts"].get("probes", 0.0) - r["parts"].get("budget", 0.0) for r in mine
        )
        medians["ours"].append(ms)
        medians["theirs"].append(then)
        medians["bare"].append(bare)
        error = "refused" if mine[0]["mm"] is None else f"{mine[0]['mm']:.2f}"
        rows.append([
            f"{frame[0]} {frame[1]}", f"{then:.0f}", f"{ms:.0f}", f"{then / ms:.2f}x",
            f"{coarse:.0f}", f"{probes:.0f}", f"{budget:.0f}", f"{bare:.0f}", error,
        ])  # fmt: skip
    then, ms, bare = (statistics.median(medians[k]) for k in ("theirs", "ours", "bare"))
    rows.append([
        "median", f"{then:.0f}", f"{ms:.0f}", f"{then / ms:.2f}x", "", "", "", f"{bare:.0f}", "",
    ])  # fmt: skip
    print_table(
        f"Warm estimate_pose per frame (ms, median of {args.rounds} interleaved rounds): at "
        f"{args.against} and in the working tree, with the working tree's parts",
        ["frame", args.against, "now", "speed-up", "coarse", "probes", "budget",
         "without the budget", "error mm"],
        rows,
    )  # fmt: skip
    print(
        f"\n{args.against} / working tree: {then / ms:.2f}x; without the working tree's error "
        f"budget: {then / bare:.2f}x"
    )


if __name__ == "__main__":
    main()
