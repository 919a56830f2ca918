"""``jaxreg basin``: an ICP basin-of-attraction sweep (:func:`jaxreg.studies.basin_sweep`)
from the command line, on one process or several.

Without ``--source`` it sweeps the lesson's experiment: 800 points uniform in a 6 cm cube,
the scene turned 15 degrees about z and shifted, with 2 mm noise. With ``--source FILE``
(any cloud :func:`jaxreg.io.load_points` reads) the target is ``--target FILE`` with
``--truth`` the source -> target pose (a 4x4 matrix in a JSON or whitespace text file), or,
without ``--target``, the source moved by ``--truth`` (identity by default) with
``--noise`` metres of Gaussian noise.

Several processes: start the same command in each with ``--coordinator HOST:PORT
--num-processes N --process-id I``; they join with ``jax.distributed.initialize`` (gloo
collectives on CPU), each registers its share and process 0 prints the whole result.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from jaxreg.cli._processes import add_process_options, join

KERNELS = ("huber", "tukey", "cauchy", "geman_mcclure", "welsch")


def add_basin_parser(subparsers) -> argparse.ArgumentParser:
    """Adds the ``basin`` command to an ``argparse`` subparsers object and returns it."""
    p = subparsers.add_parser(
        "basin",
        help="ICP basin of attraction: success rate against the start's rotation offset",
        description=__doc__.split("\n\n")[0],
    )
    p.add_argument("--source", type=Path, help="model cloud (default: the lesson's cube)")
    p.add_argument("--target", type=Path, help="scene cloud (default: the moved source)")
    p.add_argument("--truth", type=Path, help="4x4 source -> target pose (JSON or text)")
    p.add_argument("--noise", type=float, default=0.002, help="metres, without --target")
    p.add_argument("--angles", default="15,30,45,60,90", help="degrees, comma-separated")
    p.add_argument("--samples", type=int, default=256, help="starts per angle")
    p.add_argument("--translation-offsets", default="0", help="metres, comma-separated")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--method", choices=("point_to_point", "point_to_plane"), default=None)
    p.add_argument("--max-correspondence-distance", type=float, default=0.02)
    p.add_argument("--max-iterations", type=int, default=40)
    p.add_argument("--tolerance", type=float, default=1e-6)
    p.add_argument("--trim-fraction", type=float)
    p.add_argument("--kernel", choices=KERNELS, help="robust IRLS kernel")
    p.add_argument("--kernel-scale", type=float, default=0.005, help="metres")
    p.add_argument("--success-rotation-deg", type=float, default=5.0)
    p.add_argument("--success-translation", type=float, default=0.01, help="metres")
    p.add_argument("--chunk-size", type=int, help="starts per compiled call (progress)")
    p.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    p.add_argument("--out", type=Path, help="also write DIR/basin.json")
    add_process_options(p)
    return p


def _floats(text: str, name: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ValueError(f"--{name} must be comma-separated numbers, got {text!r}") from None


def _read_matrix(path: Path) -> np.ndarray:
    text = path.read_text()
    try:
        m = np.asarray(json.loads(text), np.float64)
    except json.JSONDecodeError:
        m = np.loadtxt(path)
    if m.shape != (4, 4):
        raise ValueError(f"{path}: expected a 4x4 matrix, got shape {m.shape}")
    return m


def _problem(args):
    """``(source, target, truth, description)`` from the arguments."""
    import jax.numpy as jnp

    from jaxreg.geometry.lie import se3_from_matrix
    from jaxreg.io.clouds import load_points
    from jaxreg.studies.basin import lesson_cube

    if args.source is None:
        if args.target is not None or args.truth is not None:
            raise ValueError("--target and --truth need --source")
        model, scene, truth = lesson_cube(seed=args.seed)
        return model, scene, truth, "the lesson's cube (800 points, 6 cm, 2 mm noise)"
    source = load_points(args.source).astype(np.float32)
    matrix = np.eye(4) if args.truth is None else _read_matrix(args.truth)
    truth = se3_from_matrix(jnp.asarray(matrix, jnp.float32))
    if args.target is not None:
        target = load_points(args.target).astype(np.float32)
        return source, target, truth, f"{args.source.name} -> {args.target.name}"
    rng = np.random.default_rng(args.seed)
    target = np.asarray(truth @ source) + rng.normal(0, args.noise, source.shape)
    return source, target.astype(np.float32), truth, f"{args.source.name} (moved, noisy copy)"


def _report(sweep, description: str, seconds: float, args) -> dict:
    import jax

    def listed(x, digits=3):
        return np.round(np.asarray(x, np.float64), digits).tolist()

    wrong = np.asarray(sweep.confidently_wrong).mean(-1)
    error = np.median(np.asarray(sweep.rotation_error_deg), -1)
    return {
        "problem": description,
        "devices": len(jax.devices()),
        "processes": jax.process_count(),
        "seconds": round(seconds, 2),
        "angles_deg": listed(sweep.angles_deg),
        "translation_offsets": listed(sweep.translation_offsets, 6),
        "samples_per_angle": int(sweep.success.shape[-1]),
        "success_rate": listed(sweep.success_rate),
        "confidently_wrong_rate": listed(wrong),
        "median_rotation_error_deg": listed(error),
        "basin_radius_deg": listed(sweep.basin_radius_deg, 2),
        "success": {
            "rotation_deg": args.success_rotation_deg,
            "translation": args.success_translation,
        },
    }


def _print_table(report: dict) -> None:
    print(f"ICP basin of attraction: {report['problem']}")
    print(
        f"{report['samples_per_angle']} starts per cell on {report['devices']} device(s), "
        f"{report['processes']} process(es), {report['seconds']:.1f} s with compilation"
    )
    for t, offset in enumerate(report["translation_offsets"]):
        print(f"\ntranslation offset {offset:g}")
        print("angle deg  success  confidently wrong  median rot err deg")
        for a, angle in enumerate(report["angles_deg"]):
            print(
                f"{angle:9g}  {report['success_rate'][a][t]:7.3f}  "
                f"{report['confidently_wrong_rate'][a][t]:17.3f}  "
                f"{report['median_rotation_error_deg'][a][t]:18.2f}"
            )
        print(f"basin radius (90% success): {report['basin_radius_deg'][t]:.1f} deg")


def run_basin(args) -> int:
    """Runs ``jaxreg basin`` with parsed ``args``; returns the exit status. Bad input gives
    one line on stderr and status 1, never a traceback."""
    try:
        join(args)
        import jax

        from jaxreg.geometry import kernels
        from jaxreg.registration.solver import ICPOptions
        from jaxreg.search.normals import estimate_normals
        from jaxreg.studies.basin import basin_sweep

        source, target, truth, description = _problem(args)
        angles = _floats(args.angles, "angles")
        offsets = _floats(args.translation_offsets, "translation-offsets")
        method = args.method or "point_to_point"
        normals = estimate_normals(target, k=20) if method == "point_to_plane" else None
        kernel = None
        if args.kernel is not None:
            names = dict(
                huber=kernels.Huber, tukey=kernels.Tukey, cauchy=kernels.Cauchy,
                geman_mcclure=kernels.GemanMcClure, welsch=kernels.Welsch,
            )  # fmt: skip
            kernel = names[args.kernel](args.kernel_scale)
        options = ICPOptions(
            method=method, target_normals=normals,
            max_correspondence_distance=args.max_correspondence_distance,
            max_iterations=args.max_iterations, tolerance=args.tolerance, kernel=kernel,
            trim_fraction=args.trim_fraction,
        )  # fmt: skip
        lead = jax.process_index() == 0

        def progress(done: int, total: int) -> None:
            if lead and not args.json:
                print(f"  {done}/{total} starts", file=sys.stderr)

        start = time.perf_counter()
        sweep = basin_sweep(
            source, target, truth, angles_deg=angles, samples_per_angle=args.samples,
            key=jax.random.key(args.seed), translation_offsets=offsets,
            success_rotation_deg=args.success_rotation_deg,
            success_translation=args.success_translation, chunk_size=args.chunk_size,
            progress=progress, options=options,
        )  # fmt: skip
        report = _report(sweep, description, time.perf_counter() - start, args)
        if not lead:
            return 0
        if args.out is not None:
            args.out.mkdir(parents=True, exist_ok=True)
            (args.out / "basin.json").write_text(json.dumps(report, indent=2))
        if args.json:
            print(json.dumps(report))
        else:
            _print_table(report)
    except (ValueError, OSError) as err:
        print(f"jaxreg basin: {err}", file=sys.stderr)
        return 1
    return 0
