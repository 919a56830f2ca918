"""The 3D view (``--view``): what the scene holds, and that a browser draws it (headless
Chromium's screenshot of the served page)."""

import base64
import dataclasses
import io
import json
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
import warnings

import jax.numpy as jnp
import numpy as np
import pytest
from jaxlie import SE3, SO3
from PIL import Image
from scipy.stats import chi2

from jaxreg.camera.model import RGBDFrame
from jaxreg.cli import _view
from jaxreg.cli._report import build_report
from jaxreg.pipeline.estimate import PoseEstimate
from jaxreg.pipeline.segment import TablePlane
from jaxreg.synth.scenes import tabletop_scene
from jaxreg.uncertainty.budget import SOURCES, combine

OPENING = 0.085
SIGMAS = np.array([2e-3, 1e-3, 5e-4])  # metres along the object's x, y, z


def _estimate(scene, free_z=False):
    """An estimate of ``scene``'s box 4 mm and 3 degrees off the truth, the exact mask, the
    table z = 0, a depth term with ``SIGMAS`` (z free with ``free_z``)."""
    offset = SE3.from_rotation_and_translation(
        SO3.from_z_radians(np.radians(3.0)), jnp.array([0.004, 0.0, 0.0])
    )
    terms = {name: np.zeros((6, 6)) for name in SOURCES}
    terms["depth"] = np.diag([*SIGMAS**2, 1e-4, 1e-4, 1e-4])
    free = np.array([False, False, free_z, False, False, False])
    budget = combine(terms, free, "test" if free_z else None)
    table = TablePlane(jnp.array([0.0, 0.0, 1.0]), jnp.array(0.0), jnp.array(1), jnp.array(1.0))
    return PoseEstimate(
        scene.truth @ offset, 1e-3, 0.9, budget.total, None, "found", {}, scene.mask,
        np.zeros((0, 3), np.float32), budget, table,
    )  # fmt: skip


@pytest.fixture(scope="module")
def box():
    scene = tabletop_scene(4, object="box")
    estimate = _estimate(scene)
    report = build_report(estimate, scene.model_points, OPENING)
    return scene, estimate, report


def test_the_scene_draws_each_layer_where_the_estimate_puts_it(box):
    scene, estimate, report = box
    view = _view.view_scene(scene.frame, estimate, scene.model_points, report, truth=scene.truth)
    points = np.asarray(scene.frame.points())[::2, ::2]
    valid = np.isfinite(points).all(-1)
    assert len(view.points["object"]) == (valid & scene.mask[::2, ::2]).sum()
    assert np.abs(view.points["table"][:, 2]).max() < _view.TABLE_DISTANCE
    assert len(view.points["rest"]) > 100  # the two distractors
    pose = np.asarray(estimate.pose.as_matrix())
    np.testing.assert_allclose(
        view.model, scene.model_points @ pose[:3, :3].T + pose[:3, 3], atol=1e-6
    )
    truth = np.asarray(scene.truth.as_matrix())
    np.testing.assert_allclose(view.truth[0], truth[:3, :3] @ scene.model_points[0] + truth[:3, 3])
    # The 95% ellipsoid of the translation: radii along the object's z, y, x (smallest first).
    center, axes, radii = view.region
    np.testing.assert_allclose(center, pose[:3, 3])
    np.testing.assert_allclose(radii, np.sqrt(chi2.ppf(0.95, 3)) * SIGMAS[::-1], rtol=1e-6)
    np.testing.assert_allclose(np.abs(axes.T @ pose[:3, :3]), np.eye(3)[::-1], atol=1e-6)
    # The jaws: the opening plus a pad apart, across the grasp axis, around the model's centre.
    (a, _, sides), (b, _, _) = view.jaws
    axis = pose[:3, :3] @ np.asarray(report["grasp"]["axis"])
    np.testing.assert_allclose(np.linalg.norm(b - a), OPENING + sides[0], rtol=1e-6)
    np.testing.assert_allclose(np.abs((b - a) @ axis), np.linalg.norm(b - a), rtol=1e-6)
    centre = pose[:3, :3] @ scene.model_points.mean(0) + pose[:3, 3]
    np.testing.assert_allclose((a + b) / 2, centre, atol=1e-6)
    assert "95% region" in view.notes and "15.0 mm per side" in view.notes


def test_a_free_axis_is_drawn_at_the_models_size_and_a_failure_draws_the_frame_alone(box):
    scene, _, report = box
    free = _estimate(scene, free_z=True)
    view = _view.view_scene(scene.frame, free, scene.model_points, report)
    size = np.ptp(scene.model_points, axis=0).max()
    _, axes, radii = view.region
    along_z = np.argmax(np.abs(axes.T @ np.asarray(free.pose.as_matrix())[:3, 2]))
    np.testing.assert_allclose(radii[along_z], size, rtol=1e-5)
    assert "free axis" in view.notes
    failed = PoseEstimate(
        None, np.nan, np.nan, np.full((6, 6), np.nan), "register", "the model is not there", {},
        scene.mask, np.zeros((0, 3), np.float32), None, free.table,
    )  # fmt: skip
    report = {"pose": None, "failed_stage": "register", "reason": "the model is not there"}
    view = _view.view_scene(scene.frame, failed, scene.model_points, report)
    assert view.model is None and view.region is None and view.jaws == []
    assert len(view.points["object"]) > 0 and "register failed" in view.notes
    # A frame without a single depth: nothing to draw, and still a viewpoint (no NaN).
    blank = RGBDFrame(
        np.full(scene.mask.shape, np.nan, np.float32), scene.frame.intrinsics,
        base_T_camera=scene.frame.base_T_camera,
    )  # fmt: skip
    nothing = dataclasses.replace(failed, mask=np.zeros_like(scene.mask), table=None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        view = _view.view_scene(blank, nothing, scene.model_points, report)
    assert sum(len(p) for p in view.points.values()) == 0
    assert np.isfinite([*view.eye, *view.look_at, view.point_size]).all()


def _pixels_of(image: np.ndarray, color) -> int:
    """Pixels of ``image`` ``(H, W, 3)`` showing ``color`` as the renderer may light it: the
    colour itself or lightened toward white by up to half the way."""
    color = np.asarray(color, np.float64)
    white = 255.0 - color
    pixels = image.astype(np.float64) - color
    t = np.clip(pixels @ white / max(white @ white, 1.0), 0.0, 0.5)
    return int((np.linalg.norm(pixels - t[..., None] * white, axis=-1) < 12).sum())


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
SEGMENTS_AND_MODEL = ("table", "object", "rest", "model")


def _layer_pixels(png: bytes) -> dict[str, int]:
    """Pixels of a screenshot showing each layer's colour, and ``"all"`` pixels."""
    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
    counts = {name: _pixels_of(image, _view.COLORS[name]) for name in SEGMENTS_AND_MODEL}
    return {**counts, "all": image.shape[0] * image.shape[1]}


def _drawn(counts: dict[str, int]) -> bool:
    """The scene's layers are on screen: the table on 5% of the pixels, the object's segment,
    the rest and the model each on 0.2% (an empty scene's page: table 0.6%, the others at most
    18 pixels)."""
    area = counts["all"]
    return counts["table"] > 0.05 * area and all(
        counts[name] > 0.002 * area for name in ("object", "rest", "model")
    )


def _watch(url: str, profile, size=(960, 640), deadline_s=90.0) -> tuple[bytes, dict]:
    """Opens ``url`` in headless Chromium (WebGL by SwiftShader, no GPU needed) and takes a
    screenshot every second through the DevTools protocol until the scene is drawn or
    ``deadline_s`` passes (the page, its scripts and the scene arrive at their own pace on a
    loaded machine); the last screenshot (PNG) and its layer pixel counts."""
    from websockets.sync.client import connect

    browser = subprocess.Popen(
        [CHROMIUM, "--headless", "--no-sandbox", "--use-angle=swiftshader",
         "--enable-unsafe-swiftshader", f"--user-data-dir={profile}",
         f"--window-size={size[0]},{size[1]}", "--remote-debugging-port=0", "about:blank"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        for line in browser.stderr:
            if line.startswith("DevTools listening on "):
                port = line.split()[-1].split("/")[2].split(":")[1]
                break
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json", timeout=30) as response:
            page = next(t for t in json.load(response) if t["type"] == "page")
        with connect(page["webSocketDebuggerUrl"], max_size=None) as devtools:
            calls = iter(range(1, 1_000_000))

            def call(method, **params):
                number = next(calls)
                devtools.send(json.dumps({"id": number, "method": method, "params": params}))
                while (answer := json.loads(devtools.recv(timeout=60))).get("id") != number:
                    pass
                return answer["result"]

            call("Page.navigate", url=url)
            end = time.monotonic() + deadline_s
            while True:
                time.sleep(1.0)
                png = base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
                counts = _layer_pixels(png)
                if _drawn(counts) or time.monotonic() > end:
                    return png, counts
    finally:
        browser.terminate()
        browser.wait(timeout=30)


@pytest.mark.skipif(
    CHROMIUM is None, reason="chromium is not installed (make test installs Debian's as root)"
)
def test_headless_chromium_draws_the_served_scene(box, tmp_path):
    scene, estimate, report = box
    view = _view.view_scene(scene.frame, estimate, scene.model_points, report, truth=scene.truth)
    shots = []
    url = _view.serve(view, port=0, until=lambda url: shots.append(_watch(url, tmp_path / "p")))
    ((png, counts),) = shots
    (tmp_path / "view.png").write_bytes(png)
    assert _drawn(counts), (url, counts, tmp_path / "view.png")


@pytest.mark.skipif(
    signal.getsignal(signal.SIGINT) is not signal.default_int_handler,
    reason="Ctrl-C is not delivered as KeyboardInterrupt in this process",
)
def test_serving_stops_at_ctrl_c(box):
    scene, estimate, report = box
    view = _view.view_scene(scene.frame, estimate, scene.model_points, report)
    urls, pages, returned, stuck = queue.Queue(), [], threading.Event(), []

    def visit_then_interrupt():
        try:
            with urllib.request.urlopen(urls.get(timeout=60), timeout=30) as response:
                pages.append(response.read())
        finally:
            # Ctrl-C landing on a thread other than the main one (the kernel's choice).
            signal.pthread_kill(threading.get_ident(), signal.SIGINT)
            if not returned.wait(5.0):  # not honoured: interrupt the main thread's wait itself
                stuck.append(True)
                signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)

    class Log:
        def write(self, text):
            if text.startswith("3D view at "):
                urls.put(text.split()[3])

        def flush(self):
            pass

    visitor = threading.Thread(target=visit_then_interrupt)
    visitor.start()
    _view.serve(view, port=0, log=Log())  # returns at the interrupt instead of raising it
    returned.set()
    visitor.join()
    assert pages and b"<title>Viser</title>" in pages[0]
    assert not stuck, "serving went on for 5 s after Ctrl-C"


def test_import_jaxreg_and_the_command_line_do_not_import_viser():
    code = "import sys, jaxreg, jaxreg.cli.commands; print('viser' in sys.modules)"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.stdout.strip() == "False", run.stderr
