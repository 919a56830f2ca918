"""Real frames: jaxreg.estimate_pose on YCB-Video's object instances by prompt (the dataset's
label mask, its 2D box, or none), beside an Open3D pipeline given the same label mask.

Usage: python benchmarks/bench_real.py [--data PATH] [--csv PATH] [--no-open3d]
                                       [--prompts {mask,box,none} ...]

Frames: every frame that ``jaxreg.io.read_ycbv(PATH)`` reads (default: the shipped frames,
``$JAXREG_DATA/ycbv``, else ``../shared/data/ycbv``; any folder of the same layout works): real
Asus Xtion captures, PoseCNN's point models (metres), the annotated poses and 2D boxes. Every
annotated instance is one problem per prompt (``--prompts``, default all three):

* mask: ``label == class_index``, as a user's segmenter would give it, background and occluder
  pixels at its edges included: ``estimate_pose(..., mask=mask)``;
* box: the instance's line of the frame's ``-box.txt`` (``YcbvInstance.box``, ``(u0, v0, u1,
  v1)`` pixels), as a 2D detector would give it: ``estimate_pose(..., box=box)``, the table
  route told where the object is;
* none: no prompt, the table route: ``estimate_pose`` chooses among every cluster of the frame
  (the frame's other annotated objects among them).

The contenders:

* jaxreg: ``estimate_pose(frame, model_points, depth_noise=noise, <prompt>)`` with its default
  settings and the camera's published noise model (``DepthNoise.structured_light``: the Xtion
  is a structured-light camera of the Kinect v1 class), as a user states their camera. Each
  instance and prompt is run once untimed (a new segment size may compile) and once timed; the
  first call's time (compiles included) is reported apart, per prompt: the first instance's
  and the largest.
* Open3D (0.18+), the best a user builds from its toolbox with the mask prompt's mask: the
  masked pixels lifted to camera-frame points, ``remove_statistical_outlier`` (20 neighbours, 2
  sigma), a 4 mm voxel downsample; the model's points (about 2,620) with normals
  (``estimate_normals``, 20 neighbours) as the target; point-to-plane ``registration_icp``
  (15 mm, 50 iterations) from the 24 rotations of the cube's rotation group, the model centred
  on the segment's centroid; the best start by fitness, then inlier RMSE. It always answers: its
  wrong answers are wrong successes. Timed from the lifted pixels (the model's normals are
  computed once per object).

Scores: ADD and ADD-S (``jaxreg.add``, ``jaxreg.add_s``) over the model's points; posed means
found with ADD-S < 10% of the model's diameter (its largest point-to-point distance); a wrong
success is found with ADD-S >= 10%. A posed answer with ADD >= 10% is turned from the truth (a
turn depth cannot see); its truth is listed when the answer or one of its ``equivalent_poses``
is within 10% by ADD (``listed_add_mm``: the nearest of them), the spin about a rotation axis the
estimate leaves free (``budget.free``: a can's label is not in the depth) aside.

Box-centre coverage (jaxreg's reported covariance): ``c`` is the centre of the model points'
axis-aligned bounding box (object frame), which the half turns of boxes and cans leave in place.
With the covariance ``Sigma`` of the right perturbation ``(v, w)`` of the estimate
(``T_true = T_est exp(delta)``), c's error in object axes is ``J delta``, ``J = [I, -skew(c)]``;
the measured error is ``e = R_est^T (T_true c - T_est c)``. Tangent axes with an infinite
variance (free axes) move c without bound along their columns of ``J``: the distance is
minimised over them, ``d2 = min_x |W (e - J_free x)|^2`` with ``W^T W`` the inverse of
``J Sigma J^T`` over the finite axes, and compared with the chi-square 95% quantile for the
``3 - rank(W J_free)`` directions left (7.815 with no free direction moving c; with none left,
c is unconstrained and counts as inside). "Allowing 2 mm" also minimises over a shift ``b`` of
the truth, ``|b_i| <= 2 mm`` per camera axis (rotated into object axes), as a bounded least-squares
problem (``scipy.optimize.lsq_linear``): the dataset's truth is good to a few millimetres. Both
coverages are over jaxreg's posed instances.

Tables: the mask prompt's, Open3D beside jaxreg (``Real frames: ...``); jaxreg by prompt; the
wrong successes; jaxreg's refusals by prompt and reason (``reason_group``: its words before the
first number), then each refusal's reason in full; the posed answers turned from the truth and
the equivalent poses, by prompt.

The rows, one per instance, prompt and method (``prompt``: mask, box or none; Open3D's are the
mask's), go to ``benchmarks/results/bench_real.csv`` (or ``--csv``).
"""

from __future__ import annotations

import argparse
import csv
import itertools
import platform
import re
import statistics
import time
from pathlib import Path

import jax
import numpy as np
from _timing import DATA, print_table
from scipy.optimize import lsq_linear
from scipy.spatial import ConvexHull
from scipy.stats import chi2

import jaxreg as jr

CSV = Path(__file__).resolve().parent / "results" / "bench_real.csv"
FIELDS = [
    "frame", "object", "prompt", "method", "found", "reason", "add_mm", "adds_mm", "diameter_mm",
    "centre_err_mm", "centre_d2", "centre_inside", "centre_inside_allowing", "listed_add_mm",
    "ms",
]  # fmt: skip
PROMPTS = ("mask", "box", "none")
POSED = 0.1  # ADD-S below this fraction of the diameter
TRUTH_BOX = 0.002  # metres per camera axis: the dataset's truth error allowed
VOXEL, ICP_DISTANCE, ICP_ITERATIONS = 0.004, 0.015, 50


def diameter(points: np.ndarray) -> float:
    """The largest distance between two of `points` (metres): between hull vertices."""
    hull = points[ConvexHull(points).vertices].astype(np.float64)
    return float(np.sqrt(((hull[:, None] - hull[None]) ** 2).sum(-1).max()))


def _skew(c: np.ndarray) -> np.ndarray:
    return np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])


def centre_error(est_T: np.ndarray, true_T: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``e = R_est^T (T_true c - T_est c)`` (metres, object axes); `est_T`, `true_T` `(4, 4)`
    object -> camera, `c` `(3,)` object frame."""
    moved = (true_T[:3, :3] - est_T[:3, :3]) @ c + true_T[:3, 3] - est_T[:3, 3]
    return est_T[:3, :3].T @ moved


def centre_coverage(e: np.ndarray, R: np.ndarray, sigma: np.ndarray, c: np.ndarray):
    """``(d2, inside, inside allowing TRUTH_BOX)`` of the box centre `c`'s error `e` (see the
    module docstring) under the covariance `sigma` `(6, 6)` of an estimate with rotation `R`."""
    J = np.hstack([np.eye(3), -_skew(c)])
    free = ~np.isfinite(np.diag(sigma))
    finite = sigma[np.ix_(~free, ~free)]
    S = J[:, ~free] @ finite @ J[:, ~free].T
    values, vectors = np.linalg.eigh((S + S.T) / 2)
    W = vectors.T / np.sqrt(np.maximum(values, 1e-18))[:, None]  # W^T W = S^-1
    moves = W @ J[:, free]  # whitened directions the free axes move c along, unbounded
    dof = 3 - (np.linalg.matrix_rank(moves, tol=1e-9) if free.any() else 0)
    quantile = chi2.ppf(0.95, dof) if dof else np.inf
    target = W @ e
    unbounded = np.full(moves.shape[1], np.inf)
    if free.any():
        x = np.linalg.lstsq(moves, target, rcond=None)[0]
        d2 = float(np.sum((target - moves @ x) ** 2))
    else:
        d2 = float(target @ target)
    # the truth may sit anywhere in a box of +-TRUTH_BOX per camera axis: e - R^T b
    system = np.hstack([W @ R.T, moves])
    bound = np.concatenate([np.full(3, TRUTH_BOX), unbounded])
    fit = lsq_linear(system, target, bounds=(-bound, bound))
    d2_allowing = float(np.sum((system @ fit.x - target) ** 2))
    return d2, bool(d2 <= quantile), bool(d2_allowing <= quantile)


def reason_group(reason: str) -> str:
    """The words of a refusal's reason before its first number, at most ten."""
    head = re.split(r"[\d(]", reason, maxsplit=1)[0]
    return " ".join(head.split()[:10]) or reason[:40]


# ---------------------------------------------------------------------------------------------
# Open3D


def open3d_unless(skip: bool):
    """Open3D's module, or ``None`` when ``skip`` (``--no-open3d``) or when it does not import
    (said on stdout: the jaxreg rows still run)."""
    if skip:
        return None
    try:
        import open3d
    except (ImportError, OSError) as err:
        print(f"Open3D unavailable ({err}): jaxreg only")
        return None
    return open3d


def model_target(o3d, points: np.ndarray):
    """The model's points ``(M, 3)`` (metres) as Open3D's ICP target: a cloud with normals
    from 20 neighbours."""
    target = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(np.float64)))
    target.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    return target


def cube_rotations() -> np.ndarray:
    """``(24, 3, 3)`` the rotations of the cube: signed permutation matrices with det +1."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1, -1), repeat=3):
            matrix = np.zeros((3, 3))
            matrix[range(3), perm] = signs
            if np.linalg.det(matrix) > 0:
                out.append(matrix)
    return np.stack(out)


def run_open3d(o3d, frame, mask, target, model_centre) -> tuple[np.ndarray, float]:
    """``(camera_T_object (4, 4), ms)`` from Open3D's toolbox (see the module docstring);
    `target` is the model's point cloud with normals."""
    reg = o3d.pipelines.registration
    start = time.perf_counter()
    points = np.asarray(frame.points(mask)).reshape(-1, 3)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[np.isfinite(points[:, 0])]))
    cloud, _ = cloud.remove_statistical_outlier(nb_neighbors=20, std_ratio=2.0)
    source = cloud.voxel_down_sample(VOXEL)
    centroid = source.get_center()
    best, best_key = None, None
    for rotation in cube_rotations():
        # the model turned by `rotation` with its centre on the segment's centroid; ICP moves
        # the segment onto the model, so it starts from that pose's inverse
        pose = np.eye(4)
        pose[:3, :3], pose[:3, 3] = rotation, centroid - rotation @ model_centre
        fit = reg.registration_icp(
            source, target, ICP_DISTANCE, np.linalg.inv(pose),
            reg.TransformationEstimationPointToPlane(),
            reg.ICPConvergenceCriteria(max_iteration=ICP_ITERATIONS),
        )  # fmt: skip
        key = (-fit.fitness, fit.inlier_rmse)
        if best_key is None or key < best_key:
            best, best_key = np.linalg.inv(fit.transformation), key
    return best, (time.perf_counter() - start) * 1e3


# ---------------------------------------------------------------------------------------------


def score(instance, pose: np.ndarray | None, model_diameter: float) -> dict:
    if pose is None:
        return {"add_mm": "", "adds_mm": "", "diameter_mm": f"{model_diameter * 1e3:.1f}"}
    est = jr.SE3.from_matrix(pose.astype(np.float32))
    points = instance.model_points
    return {
        "add_mm": f"{float(jr.add(points, est, instance.truth)) * 1e3:.2f}",
        "adds_mm": f"{float(jr.add_s(points, est, instance.truth)) * 1e3:.2f}",
        "diameter_mm": f"{model_diameter * 1e3:.1f}",
    }


def prompt_options(instance, prompt: str) -> dict:
    """``estimate_pose``'s keywords for `prompt`: ``mask`` the instance's label mask ``(H, W)``
    bool, ``box`` its ``(u0, v0, u1, v1)`` box (pixels), ``none`` nothing."""
    if prompt == "mask":
        return {"mask": instance.mask}
    if prompt == "box":
        return {"box": instance.box}
    return {}


def run_jaxreg(frame, instance, prompt: str):
    """``(camera_T_object (4, 4) or None, reason, PoseEstimate or None, ms)`` of
    ``estimate_pose`` on `instance` given `prompt`; a ``ValueError`` is a refusal."""
    start = time.perf_counter()
    try:
        intrinsics = frame.frame.intrinsics
        noise = jr.DepthNoise.structured_light((float(intrinsics.fx), float(intrinsics.fy)))
        est = jr.estimate_pose(
            frame.frame, instance.model_points, depth_noise=noise,
            **prompt_options(instance, prompt),
        )  # fmt: skip
    except ValueError as error:  # a refusal by exception still answers the user
        return None, f"ValueError: {error}", None, (time.perf_counter() - start) * 1e3
    ms = (time.perf_counter() - start) * 1e3
    if not est.success:
        return None, est.reason, est, ms
    return np.asarray(est.pose.as_matrix(), np.float64), est.reason, est, ms


def jaxreg_row(frame, instance, prompt: str, model_diameter: float, box_centre: np.ndarray):
    """``(row, equivalent poses)``: the CSV row of jaxreg on `instance` given `prompt` (the
    second of two calls timed, the first's ms as ``first_ms``) and the number of the estimate's
    ``equivalent_poses`` (``None`` when refused or not reported)."""
    first_ms = run_jaxreg(frame, instance, prompt)[-1]  # may compile
    pose, reason, est, ms = run_jaxreg(frame, instance, prompt)
    row = {"frame": frame.name, "object": instance.model_name, "prompt": prompt,
           "method": "jaxreg", "found": pose is not None, "reason": reason, "ms": ms,
           "first_ms": first_ms, **score(instance, pose, model_diameter)}  # fmt: skip
    if pose is None:
        return row, None
    truth = np.asarray(instance.truth.as_matrix(), np.float64)
    e = centre_error(pose, truth, box_centre)
    sigma = np.asarray(est.covariance, np.float64)
    d2, inside, allowing = centre_coverage(e, pose[:3, :3], sigma, box_centre)
    row |= {"centre_err_mm": f"{np.linalg.norm(e) * 1e3:.2f}", "centre_d2": f"{d2:.2f}",
            "centre_inside": inside, "centre_inside_allowing": allowing}  # fmt: skip
    turns = getattr(est, "equivalent_poses", None)
    listed = [est.pose, *(turn.pose for turn in turns or ())]
    free = np.flatnonzero(np.asarray(est.budget.free)[3:])
    spin = None if not len(free) else jr.Symmetry(np.eye(3)[None], axis=np.eye(3)[free[0]])
    truths = [instance.truth if spin is None else jr.canonicalise(instance.truth, p, spin)
              for p in listed]  # fmt: skip
    pairs = zip(listed, truths, strict=True)
    nearest = min(float(jr.add(instance.model_points, p, t)) for p, t in pairs)
    row["listed_add_mm"] = f"{nearest * 1e3:.2f}"
    return row, None if turns is None else len(turns)


def summarise(name: str, rows: list[dict], first_ms: float | None) -> list[object]:
    found = [r for r in rows if r["found"]]
    posed = [r for r in found if r["posed"]]
    wrong = [r for r in found if not r["posed"]]
    refused = len(rows) - len(found)
    covered = [r for r in posed if r["centre_inside"] != ""]
    inside = sum(r["centre_inside"] for r in covered)
    allowing = sum(r["centre_inside_allowing"] for r in covered)
    coverage = f"{inside}/{len(covered)}" if covered else "-"
    coverage_allowing = f"{allowing}/{len(covered)}" if covered else "-"
    return [
        name, len(rows), f"{len(posed)} ({len(posed) / len(rows):.0%})", len(wrong), refused,
        coverage, coverage_allowing, f"{statistics.median(r['ms'] for r in rows):.0f}",
        "-" if first_ms is None else f"{first_ms:.0f}",
    ]  # fmt: skip


SUMMARY_COLUMNS = ["instances", "posed", "wrong successes", "refused", "centre inside",
                   "inside allowing 2 mm", "ms", "first call ms"]  # fmt: skip
SCORES = (f"posed: ADD-S < {POSED:.0%} of the diameter; box centre in the 95% region, over the "
          "posed; ms: median per instance, warm")  # fmt: skip


def print_refusals(rows: dict[str, list[dict]]) -> None:
    """jaxreg's refusals (`rows`: prompt -> rows) grouped by prompt and ``reason_group``, then
    each one's reason in full."""
    refused = [r for prompt_rows in rows.values() for r in prompt_rows if not r["found"]]
    if not refused:
        print("\njaxreg's refusals: none")
        return
    groups: dict[tuple[str, str], int] = {}
    for row in refused:
        key = (row["prompt"], reason_group(row["reason"]))
        groups[key] = groups.get(key, 0) + 1
    order = {prompt: i for i, prompt in enumerate(rows)}
    ranked = sorted(groups.items(), key=lambda kv: (order[kv[0][0]], -kv[1]))
    print_table(
        "jaxreg's refusals by prompt and reason (its words before the first number)",
        ["prompt", "reason", "instances"],
        [[prompt, group, n] for (prompt, group), n in ranked],
    )
    print("\njaxreg's refusals, each reason in full (frame, object, prompt: reason):")
    for row in refused:
        print(f"{row['frame']}  {row['object']}  {row['prompt']}: {row['reason']}")


def print_turned(rows: dict[str, list[dict]]) -> None:
    """jaxreg's posed answers turned from the truth, by prompt (`rows`: prompt -> rows), and
    those whose truth is not among their equivalent poses."""
    print(f"\njaxreg's posed answers turned from the truth (ADD >= {POSED:.0%} of the diameter), "
          "and those whose truth is one of their equivalent_poses (by ADD, the spin about an "
          "axis the estimate leaves free aside):")  # fmt: skip
    unlisted = []
    for prompt, prompt_rows in rows.items():
        turned = [r for r in prompt_rows if r["posed"] and float(r["add_mm"]) >= POSED * float(
            r["diameter_mm"])]  # fmt: skip
        missed = [r for r in turned if float(r["listed_add_mm"]) >= POSED * float(
            r["diameter_mm"])]  # fmt: skip
        unlisted += missed
        print(f"{prompt}: {len(turned)} turned, the truth listed on {len(turned) - len(missed)}")
    if unlisted:
        print_table(
            "Turned answers whose truth is not among the equivalent poses",
            ["prompt", "frame", "object", "ADD mm", "nearest listed ADD mm", "diameter mm"],
            [[r["prompt"], r["frame"], r["object"], r["add_mm"], r["listed_add_mm"],
              r["diameter_mm"]] for r in unlisted],
        )  # fmt: skip


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA / "ycbv",
                        help="YCB-Video folder (default $JAXREG_DATA/ycbv)")  # fmt: skip
    parser.add_argument("--csv", type=Path, default=CSV, help=f"per-instance rows (default {CSV})")
    parser.add_argument("--no-open3d", action="store_true")
    parser.add_argument("--prompts", nargs="+", choices=PROMPTS, default=list(PROMPTS),
                        help="how jaxreg is told the object (default: all three)")  # fmt: skip
    args = parser.parse_args()
    prompts = list(dict.fromkeys(args.prompts))
    if not args.data.exists():
        raise SystemExit(f"no YCB-Video frames at {args.data}: pass --data or set JAXREG_DATA")
    frames = jr.io.read_ycbv(args.data)
    problems = [(f, i) for f in frames for i in f.instances]
    if any(i.model_points is None for _, i in problems):
        raise SystemExit(f"no models/ beside {args.data}'s data/: the scores need the models")
    if "box" in prompts and any(i.box is None for _, i in problems):
        raise SystemExit(f"an instance of {args.data} has no box (its frame's -box.txt): the "
                         "box prompt needs them (--prompts mask none)")  # fmt: skip
    o3d = open3d_unless(args.no_open3d or "mask" not in prompts)
    print(f"{platform.processor() or platform.machine()}, {jax.devices()[0].platform}, "
          f"jax {jax.__version__}" + (f", Open3D {o3d.__version__}" if o3d else "")
          + f"; {len(problems)} instances in {len(frames)} frames of {args.data}; prompts "
          + ", ".join(prompts))  # fmt: skip

    models = {}
    for _, instance in problems:
        if instance.model_name not in models:
            points = instance.model_points.astype(np.float64)
            box_centre = (points.min(0) + points.max(0)) / 2
            target = None if o3d is None else model_target(o3d, points)
            models[instance.model_name] = (diameter(points), box_centre, target, points.mean(0))

    print("per instance: frame  object  prompt  jaxreg found  ADD-S mm  first call ms  ms  "
          "| Open3D ADD-S mm  ms")  # fmt: skip
    rows = {prompt: [] for prompt in prompts}
    equivalent = {prompt: [] for prompt in prompts}
    peer = []
    for frame, instance in problems:
        model_diameter, box_centre, target, centroid = models[instance.model_name]
        for prompt in prompts:
            row, turns = jaxreg_row(frame, instance, prompt, model_diameter, box_centre)
            rows[prompt].append(row)
            if row["found"]:
                equivalent[prompt].append(turns)
            line = f"{frame.name}  {instance.model_name}  {prompt}  {row['found']}  "
            line += f"{row['adds_mm'] or '-'}  {row['first_ms']:.0f}  {row['ms']:.0f}"
            if o3d is not None and prompt == "mask":
                pose, ms = run_open3d(o3d, frame.frame, instance.mask, target, centroid)
                truth = np.asarray(instance.truth.as_matrix(), np.float64)
                err = np.linalg.norm(centre_error(pose, truth, box_centre))
                peer.append({
                    "frame": frame.name, "object": instance.model_name, "prompt": "mask",
                    "method": "Open3D", "found": True, "reason": "", "ms": ms,
                    **score(instance, pose, model_diameter), "centre_err_mm": f"{err * 1e3:.2f}",
                })  # fmt: skip
                line += f"  |  {peer[-1]['adds_mm']}  {ms:.0f}"
            print(line, flush=True)

    every = [r for prompt_rows in rows.values() for r in prompt_rows] + peer
    for row in every:
        row["posed"] = row["found"] and float(row["adds_mm"]) < POSED * float(row["diameter_mm"])
        for key in FIELDS:
            row.setdefault(key, "")
    if "mask" in prompts:
        print_table(
            f"Real frames: {len(problems)} YCB-Video instances, dataset masks, default settings "
            f"({SCORES})",
            ["method", *SUMMARY_COLUMNS],
            [summarise("jaxreg", rows["mask"], rows["mask"][0]["first_ms"])]
            + ([summarise("Open3D", peer, None)] if peer else []),
        )  # fmt: skip
    print_table(
        f"jaxreg by prompt: {len(problems)} YCB-Video instances each, default settings (mask: "
        "the label's mask; box: the dataset's 2D box; none: no prompt, the table route; "
        f"{SCORES})",
        ["prompt", *SUMMARY_COLUMNS],
        [summarise(p, rows[p], rows[p][0]["first_ms"]) for p in prompts],
    )  # fmt: skip
    print("\njaxreg's first call on each instance (compiles for new sizes included):")
    for prompt in prompts:
        first = [r["first_ms"] for r in rows[prompt]]
        print(f"{prompt}: the first instance {first[0] / 1e3:.1f} s, the largest "
              f"{max(first) / 1e3:.1f} s, {sum(t > 10e3 for t in first)} over 10 s")  # fmt: skip
    wrong = [r for r in every if r["found"] and not r["posed"]]
    if wrong:
        print_table(
            "Wrong successes (found, ADD-S >= 10% of the diameter)",
            ["method", "prompt", "frame", "object", "ADD-S mm", "ADD mm", "diameter mm"],
            [[r["method"], r["prompt"], r["frame"], r["object"], r["adds_mm"], r["add_mm"],
              r["diameter_mm"]] for r in wrong],
        )  # fmt: skip
    else:
        print("\nWrong successes (found, ADD-S >= 10% of the diameter): none")
    print_refusals(rows)
    print_turned(rows)
    reported = [n for found in equivalent.values() for n in found]
    counts = sorted({n for n in reported if n is not None})
    if reported and not counts:
        print("\njaxreg equivalent_poses: not reported (PoseEstimate has no equivalent_poses)")
    elif counts:
        print_table(
            "jaxreg equivalent_poses per estimate found, by prompt",
            ["equivalent poses", *prompts],
            [[n, *(equivalent[p].count(n) for p in prompts)] for n in counts],
        )

    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with args.csv.open("w", newline="") as file:
        writer = csv.DictWriter(file, FIELDS, extrasaction="ignore")
        writer.writeheader()
        for row in every:
            writer.writerow(row | {"ms": f"{row['ms']:.0f}"})
    shown = args.csv.resolve()
    if shown.is_relative_to(Path.cwd()):
        shown = shown.relative_to(Path.cwd())
    print(f"\nper-instance rows: {shown}")


if __name__ == "__main__":
    main()
