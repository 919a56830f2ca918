"""``jaxreg bop DATASET``: the pipeline on every target of a BOP dataset split
(:func:`jaxreg.studies.bop_run.run_bop`), its estimates written as BOP's result CSV and scored
with BOP's metrics (:func:`jaxreg.studies.bop_scores`): recall per object and the average
recall (AR) printed. A split whose models are points (no faces, e.g. one written by
``jaxreg convert-ycbv``) has no VSD: it is printed as n/a with the reason, and the AR is the
mean of the MSSD and MSPD recalls.

The CSV goes to ``--out`` (default ``jaxreg_<dataset folder>-<split>.csv``, BOP's naming of
result files). Each target is segmented by its visible mask (mask_visib) unless
``--no-masks``, which uses the table route. Progress goes to stderr.

``jaxreg convert-ycbv SRC OUT [--split test]`` writes YCB-Video frames
(:func:`jaxreg.io.read_ycbv`'s ``path``) as such a split (:func:`jaxreg.io.ycbv_to_bop`).

Several processes: start the same command in each with ``--coordinator HOST:PORT
--num-processes N --process-id I``; they join with ``jax.distributed.initialize`` (gloo
collectives on CPU), image ``i`` is estimated by process ``i % N``, and process 0 gathers
the rows, writes the CSV and prints the scores.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from jaxreg.cli._processes import add_process_options, join


def add_bop_parser(subparsers) -> argparse.ArgumentParser:
    """Adds the ``bop`` command to an ``argparse`` subparsers object and returns it."""
    p = subparsers.add_parser(
        "bop",
        help="estimate every target of a BOP dataset split, write BOP's CSV, print the AR",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("dataset", type=Path, help="the BOP dataset's folder (holding models/)")
    p.add_argument("--split", default="test", help="the split folder (default test)")
    p.add_argument("--objects", help="object ids, comma-separated (default every target's)")
    p.add_argument("--scenes", help="scene ids, comma-separated (default every scene)")
    p.add_argument(
        "--out", type=Path, help="the results CSV (default jaxreg_<dataset>-<split>.csv)"
    )
    p.add_argument("--no-masks", action="store_true", help="segment by the table route")
    add_process_options(p)
    return p


def _ids(text: str | None, name: str) -> list[int] | None:
    if text is None:
        return None
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--{name} must be comma-separated integer ids, got {text!r}") from None


def _progress_bar(label: str):
    """`progress(done, total)` drawing a bar on stderr (one line per update off a terminal)."""
    start = time.perf_counter()
    live = sys.stderr.isatty()

    def progress(done: int, total: int) -> None:
        filled = round(24 * done / max(total, 1))
        bar = "#" * filled + "." * (24 - filled)
        text = f"{label}[{bar}] {done}/{total} images, {time.perf_counter() - start:.0f} s"
        end = "\n" if done == total or not live else ""
        print(("\r" if live else "") + text, end=end, file=sys.stderr, flush=True)

    return progress


def _print_scores(scores) -> None:
    """Recall per object and the AR (BOP19's VSD, MSSD and MSPD recalls and their mean; n/a
    and the mean of two where VSD is unavailable, with the reason)."""

    def vsd(value: float, width: int) -> str:
        return f"{'n/a':>{width}}" if math.isnan(value) else f"{value:{width}.3f}"

    print(
        f"{'object':>6}  {'targets':>7}  {'AR_VSD':>6}  {'AR_MSSD':>7}  {'AR_MSPD':>7}  {'AR':>6}"
    )
    for obj_id, row in sorted(scores.per_object.items()):
        print(
            f"{obj_id:>6}  {int(row['targets']):>7}  {vsd(row['ar_vsd'], 6)}  "
            f"{row['ar_mssd']:7.3f}  {row['ar_mspd']:7.3f}  {row['ar']:6.3f}"
        )
    if scores.vsd_unavailable is not None:
        print(
            f"AR {scores.ar:.3f} of MSSD {scores.ar_mssd:.3f} and MSPD {scores.ar_mspd:.3f} "
            f"over {len(scores.errors)} targets; VSD not scored: {scores.vsd_unavailable}"
        )
        return
    print(
        f"AR {scores.ar:.3f} (VSD {scores.ar_vsd:.3f}, MSSD {scores.ar_mssd:.3f}, "
        f"MSPD {scores.ar_mspd:.3f}) over {len(scores.errors)} targets"
    )


def run_bop_command(args) -> int:
    """Runs ``jaxreg bop`` with parsed ``args``; returns the exit status. Bad input gives one
    line on stderr and status 1, never a traceback."""
    try:
        join(args)
        import jax

        from jaxreg.io.bop import read_bop, write_bop_results
        from jaxreg.studies.bop_run import gather_bop_results, run_bop
        from jaxreg.studies.bop_scores import bop_scores

        split = read_bop(
            args.dataset,
            args.split,
            objects=_ids(args.objects, "objects"),
            scenes=_ids(args.scenes, "scenes"),
        )
        index, count = jax.process_index(), jax.process_count()
        targets = split.targets()
        if args.no_masks:
            route = "the table route"
        elif split.mask(targets[0]) is None:
            route = "the table route (the split has no mask_visib)"
        else:
            route = "mask_visib"
        points_only = sorted(o for o, model in split.models.items() if model.mesh is None)
        if index == 0:
            print(
                f"jaxreg bop: {args.dataset}/{args.split}: {len(split.images)} images, "
                f"{len(targets)} targets, objects {sorted(split.models)}, segmented "
                f"by {route}, {count} process(es) (the first image compiles: ~1 min)",
                file=sys.stderr,
            )
            if points_only:
                print(
                    f"  objects {points_only} are point models (no mesh): VSD, which renders "
                    "a mesh, will not be scored; MSSD and MSPD use their points",
                    file=sys.stderr,
                )
        label = f"  process {index}: " if count > 1 else "  "
        results = run_bop(
            split,
            use_masks=not args.no_masks,
            process_index=index,
            process_count=count,
            progress=_progress_bar(label),
        )
        results = gather_bop_results(results)
        if index != 0:
            return 0
        out = args.out or Path(f"jaxreg_{args.dataset.resolve().name}-{args.split}.csv")
        write_bop_results(out, results)
        print(f"wrote {len(results)} estimates to {out}")
        _print_scores(bop_scores(split, results))
    except (ValueError, OSError) as err:
        print(f"jaxreg bop: {err}", file=sys.stderr)
        return 1
    return 0


def add_convert_ycbv_parser(subparsers) -> argparse.ArgumentParser:
    """Adds the ``convert-ycbv`` command to an ``argparse`` subparsers object and returns it."""
    p = subparsers.add_parser(
        "convert-ycbv",
        help="write YCB-Video frames as a BOP dataset split that `jaxreg bop` scores",
        description="Write YCB-Video frames (colour, depth, label, meta) as a BOP split: depth, "
        "rgb, mask_visib from the labels, the truth, and the point models in mm (VSD, which "
        "renders meshes, cannot score them; MSSD and MSPD can).",
    )  # fmt: skip
    p.add_argument(
        "source", type=Path,
        help="a YCB-Video sequence folder, one frame's prefix or the dataset root",
    )  # fmt: skip
    p.add_argument("out", type=Path, help="the BOP dataset folder to write")
    p.add_argument("--split", default="test", help="the split folder (default test)")
    p.add_argument("--models", type=Path, help="models folder (default: beside data/)")
    return p


def run_convert_ycbv(args) -> int:
    """Runs ``jaxreg convert-ycbv`` with parsed ``args``; returns the exit status (0)."""
    from jaxreg.io import ycbv_to_bop
    from jaxreg.io.bop import read_bop

    folder = ycbv_to_bop(args.source, args.out, args.split, models=args.models)
    split = read_bop(args.out, args.split)
    print(
        f"wrote {args.source} to {folder}: the split holds {len(split.images)} images, "
        f"{len(split.targets())} targets and the point models of objects "
        f"{sorted(split.models)}; score estimates with jaxreg bop {args.out} --split "
        f"{args.split} (MSSD and MSPD; VSD needs meshes)"
    )
    return 0
