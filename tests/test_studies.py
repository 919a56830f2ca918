import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3

from jaxreg.geometry.metrics import Symmetry, rotation_error
from jaxreg.registration.icp import ICPOptions
from jaxreg.studies import basin_radius, basin_starts, basin_sweep, lesson_cube

HERE = Path(__file__).resolve().parent
REPO = HERE.parent


SWEEP = dict(angles_deg=[10.0, 40.0, 120.0], samples_per_angle=8, max_iterations=30)


def small_sweep():
    model, scene, truth = lesson_cube(n=300)
    return basin_sweep(
        model, scene, truth, key=jax.random.key(3), max_correspondence_distance=0.02, **SWEEP
    )


def fingerprint(sweep) -> dict:
    return dict(
        success=np.asarray(sweep.success).ravel().tolist(),
        rotation_error_deg=np.asarray(sweep.rotation_error_deg).ravel().tolist(),
        iterations=np.asarray(sweep.iterations).ravel().tolist(),
    )


@pytest.fixture(scope="module")
def sweep():
    return small_sweep()


def test_starts_sit_at_the_requested_offsets():
    model, _, truth = lesson_cube(n=300)
    starts = basin_starts(
        model, truth, angles_deg=[5.0, 60.0], samples_per_angle=50, key=jax.random.key(0),
        translation_offsets=[0.0, 0.03],
    )  # fmt: skip
    assert starts.get_batch_axes() == (2, 2, 50)
    angles = np.rad2deg(np.asarray(rotation_error(starts, truth)))
    np.testing.assert_allclose(angles[0], 5.0, atol=2e-3)
    np.testing.assert_allclose(angles[1], 60.0, atol=2e-3)
    centroid = model.mean(0)
    shift = np.linalg.norm(np.asarray(starts @ centroid - truth @ centroid), axis=-1)
    np.testing.assert_allclose(shift[:, 0], 0.0, atol=1e-6)
    np.testing.assert_allclose(shift[:, 1], 0.03, atol=1e-6)
    # the axes are spread over the sphere, not one axis repeated
    axes = np.asarray((truth.inverse() @ starts).rotation().log())[1, 0]
    axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    assert np.linalg.norm(axes.mean(0)) < 0.4


def test_small_offsets_recover_the_truth_large_ones_end_confidently_wrong(sweep):
    assert sweep.success.shape == (3, 1, 8)
    rate = np.asarray(sweep.success_rate)[:, 0]
    assert rate[0] == 1.0 and rate[2] < 0.5
    # the lesson: inside the basin the rotation comes back to a fraction of a degree
    assert np.median(np.asarray(sweep.rotation_error_deg)[0]) < 1.0
    # outside, some starts converge (ICP's own test passes) at a wrong pose
    assert np.asarray(sweep.confidently_wrong)[2].any()
    wrong = np.asarray(sweep.confidently_wrong)
    assert not np.asarray(sweep.success)[wrong].any()
    np.testing.assert_array_equal(wrong, np.asarray(sweep.converged & ~sweep.success))
    radius = float(sweep.basin_radius_deg[0])
    assert 10.0 <= radius <= 120.0
    np.testing.assert_allclose(radius, basin_radius(SWEEP["angles_deg"], rate, 0.9))


def test_options_and_keywords_give_the_same_sweep(sweep):
    model, scene, truth = lesson_cube(n=300)
    options = ICPOptions(max_correspondence_distance=0.02, max_iterations=30)
    cells = dict(angles_deg=SWEEP["angles_deg"], samples_per_angle=SWEEP["samples_per_angle"])
    again = basin_sweep(model, scene, truth, key=jax.random.key(3), options=options, **cells)
    for a, b in zip(jax.tree.leaves(sweep), jax.tree.leaves(again), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(TypeError, match=r"basin_sweep\(\) got unknown keyword argument 'max_iter'"):
        basin_sweep(model, scene, truth, key=jax.random.key(3), max_iter=30, **cells)


def test_basin_radius_interpolates_the_crossing():
    angles = [10.0, 20.0, 30.0]
    np.testing.assert_allclose(basin_radius(angles, [1.0, 0.8, 0.2], 0.9), 15.0)
    np.testing.assert_allclose(basin_radius(angles, [1.0, 1.0, 0.95], 0.9), 30.0)  # >= widest
    np.testing.assert_allclose(basin_radius(angles, [0.5, 0.2, 0.0], 0.9), 0.0)
    both = basin_radius(angles, np.array([[1.0, 1.0], [0.7, 1.0], [0.0, 0.0]]), 0.9)
    np.testing.assert_allclose(both, [10 + 10 * 0.1 / 0.3, 20 + 10 * 0.1 / 1.0])


def test_symmetric_object_scores_equivalent_poses_as_success():
    """A 3 x 2 x 1 box has four poses that fit it exactly: starts half a turn away that
    land on another one fail without the symmetry and succeed with it."""
    rng = np.random.default_rng(1)
    half = np.array([0.03, 0.02, 0.01])
    points = rng.uniform(-half, half, (400, 3))
    face = rng.integers(0, 3, 400)
    points[np.arange(400), face] = np.sign(rng.normal(size=400)) * half[face]
    points = points.astype(np.float32)
    truth = SE3.from_translation(jnp.array([0.1, 0.0, 0.0]))
    target = np.asarray(truth @ points)
    flips = np.stack(
        [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    )
    common = dict(
        angles_deg=[170.0], samples_per_angle=16, key=jax.random.key(2),
        max_correspondence_distance=0.03, max_iterations=30,
    )  # fmt: skip
    plain = basin_sweep(points, target, truth, **common)
    aware = basin_sweep(points, target, truth, symmetry=Symmetry(flips), **common)
    np.testing.assert_array_equal(plain.pose.wxyz_xyz, aware.pose.wxyz_xyz)
    assert float(aware.success_rate[0, 0]) > float(plain.success_rate[0, 0])
    assert np.all(
        np.asarray(aware.rotation_error_deg) <= np.asarray(plain.rotation_error_deg) + 1e-3
    )


def test_bad_arguments_raise():
    model, scene, truth = lesson_cube(n=50)
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="increasing"):
        basin_sweep(model, scene, truth, angles_deg=[30.0, 10.0], samples_per_angle=2, key=key)
    with pytest.raises(ValueError, match="samples_per_angle"):
        basin_sweep(model, scene, truth, angles_deg=[10.0], samples_per_angle=0, key=key)
    with pytest.raises(ValueError, match="basin_level"):
        basin_sweep(
            model, scene, truth, angles_deg=[10.0], samples_per_angle=2, key=key, basin_level=0
        )


SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax
    if len(sys.argv) > 2:  # coordinator, number of processes, process id
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(sys.argv[2], int(sys.argv[3]), int(sys.argv[4]))
    sys.path.insert(0, sys.argv[1])
    from test_studies import fingerprint, small_sweep
    assert len(jax.devices()) == 2, jax.devices()
    print(json.dumps(fingerprint(small_sweep())))
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_same_answer_on_one_device_two_devices_and_two_processes(sweep):
    """The acceptance check of the sharded sweep: one device here, two forced host devices
    in one process, and two processes (one device each) joined by jax.distributed."""
    expected = fingerprint(sweep)
    base = dict(os.environ, JAX_PLATFORMS="cpu")
    base.pop("XLA_FLAGS", None)
    two_devices = dict(base, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    address = f"127.0.0.1:{_free_port()}"
    runs = [
        subprocess.Popen(
            [sys.executable, "-c", SCRIPT, str(HERE)],
            env=two_devices,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
    ]
    runs += [
        subprocess.Popen([sys.executable, "-c", SCRIPT, str(HERE), address, "2", str(i)],
                         env=base, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for i in range(2)
    ]  # fmt: skip
    outputs = []
    for proc in runs:
        stdout, stderr = proc.communicate(timeout=400)
        assert proc.returncode == 0, stderr[-3000:]
        outputs.append(json.loads(stdout.strip().splitlines()[-1]))
    for got in outputs:
        assert got["success"] == expected["success"]
        assert got["iterations"] == expected["iterations"]
        np.testing.assert_allclose(
            got["rotation_error_deg"], expected["rotation_error_deg"], atol=1e-3
        )


def run_cli(argv):
    import argparse

    from jaxreg.cli._basin import add_basin_parser, run_basin

    parser = argparse.ArgumentParser(prog="jaxreg")
    add_basin_parser(parser.add_subparsers(dest="command", required=True))
    return run_basin(parser.parse_args(argv))


def test_basin_command_prints_the_sweep_and_rejects_bad_input(capsys):
    assert run_cli(["basin", "--samples", "4", "--angles", "10,120", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["processes"] == 1 and report["samples_per_angle"] == 4
    assert report["success_rate"][0] == [1.0]
    assert len(report["success_rate"]) == len(report["median_rotation_error_deg"]) == 2
    assert run_cli(["basin", "--angles", "30,10"]) == 1
    assert "increasing" in capsys.readouterr().err
    assert run_cli(["basin", "--num-processes", "2"]) == 1
    assert "--coordinator" in capsys.readouterr().err
