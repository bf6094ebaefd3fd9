"""report.html: self-contained (plotly.js embedded, no network), ids HTML-escaped, and it loads in
a real headless browser (Debian's chromium driven by selenium) with no JavaScript error and a
screenshot that is not blank.  The browser test is skipped only outside CI when chromium,
chromedriver or selenium is absent; in CI (CI set) it must run."""

import math
import os
import re
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from fusion.geometry import make_T, rot_z
from fusion.types import LoadEstimate, LoadMap, Trajectory
from fusion.warehouse.inventory import Status
from fusion.warehouse.manifest import ExpectedLoad
from fusion.warehouse.view3d import MAX_DISPLAY_POSES, REPORT_HTML, build_figure, write_html

EVIL_ID = "</script><img src=x onerror=alert(1)>"
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--enable-unsafe-swiftshader",
    "--window-size=1200,900",
)
MIN_COLOURED_PIXELS = 500  # trace colours (saturated) a drawn 3D scene shows at least


def _trajectory(name, rng, n=300):
    t = np.linspace(0, 2 * math.pi, n)
    p = np.column_stack([3 + 2 * np.cos(t), 3 + 1.5 * np.sin(t), 1.4 + 0.2 * np.sin(3 * t)])
    p += 0.01 * rng.normal(size=p.shape)
    T = np.array([make_T(rot_z(a + math.pi / 2), q) for a, q in zip(t, p, strict=False)])
    return Trajectory(name, np.arange(n, dtype=np.int64) * 33_000_000, T)


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    rng = np.random.default_rng(0)
    trajs = {"pnp": _trajectory("pnp", rng), "smoother": _trajectory("smoother", rng)}
    loads = LoadMap(
        "smoother",
        [
            LoadEstimate("P-01-1", np.array([1.5, 2.7, 0.7]), np.diag([1e-4, 4e-4, 1e-4]), 12),
            LoadEstimate(EVIL_ID, np.array([3.5, 2.7, 1.4]), np.diag([4e-4, 1e-4, 1e-4]), 5),
            LoadEstimate("Q-01-1", np.array([1.5, 4.3, 0.7]), None, 3),
        ],
    )
    statuses = {
        "P-01-1": Status.PRESENT,
        EVIL_ID: Status.MOVED,
        "Q-01-1": Status.UNEXPECTED,
        "GONE": Status.MISSING,
    }
    expected = [
        ExpectedLoad("GONE", np.array([5.5, 2.7, 1.4]), 0.01, "A-01-03", 2),
        ExpectedLoad(EVIL_ID, np.array([3.4, 2.7, 1.4]), 0.01, None, 3),
    ]
    floor = np.array([(x, y) for x in range(7) for y in range(6)], dtype=float)
    fig = build_figure(trajs, loads, floor, 1.0, statuses, expected)
    return write_html(tmp_path_factory.mktemp("view") / REPORT_HTML, fig), fig


def test_html_self_contained_and_escaped(page):
    path, fig = page
    html = path.read_text(encoding="utf-8")
    assert re.search(r"<script[^>]*\bsrc\s*=", html) is None  # nothing fetched
    assert len(html) > 1_000_000  # plotly.js itself is in the file
    assert EVIL_ID not in html and "<img src=x" not in html
    assert "load &lt;\\u002fscript&gt;&lt;img" in html  # escaped, then JSON-encoded
    names = [t.name for t in fig.data]
    assert "floor codes" in names and "smoother trajectory" in names
    assert len(fig.layout.sliders[0].steps) > 10  # the time slider
    hover = " ".join(
        str(h)
        for t in fig.data
        if t.hovertext is not None
        for h in (t.hovertext if isinstance(t.hovertext, tuple) else [t.hovertext])
    )
    assert "floor code 0/3/2" in hover and "load P-01-1" in hover and "expected GONE" in hover


def _browser_or_skip():
    chromium = shutil.which("chromium")
    driver = shutil.which("chromedriver")
    try:
        import selenium  # noqa: F401
    except ImportError:
        selenium = None
    if chromium and driver and selenium is not None:
        return chromium, driver
    reason = (
        f"headless browser test needs Debian's chromium and chromium-driver and selenium "
        f"(chromium: {chromium}, chromedriver: {driver}, selenium: {selenium is not None})"
    )
    if os.environ.get("CI"):
        pytest.fail(reason + " - required in CI")
    pytest.skip(reason + "; not in CI")


def _load_in_chromium(path: Path):
    """(state, SEVERE browser log entries, screenshot PNG) of `path` opened in headless chromium
    with a fresh profile; state = [typeof Plotly, traces in the plot, canvases]."""
    chromium, driver_path = _browser_or_skip()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="fusion-chromium-")
    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for flag in (*CHROMIUM_FLAGS, f"--user-data-dir={profile}"):
        opts.add_argument(flag)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(driver_path), options=opts)
    try:
        driver.set_page_load_timeout(600)
        driver.get(path.resolve().as_uri())
        state = driver.execute_script(
            "const gd = document.querySelector('.js-plotly-plot');"
            "return [typeof Plotly, gd ? gd.data.length : -1,"
            " document.querySelectorAll('canvas').length];"
        )
        errors = [e for e in driver.get_log("browser") if e["level"] == "SEVERE"]
        png = driver.get_screenshot_as_png()
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)
    return state, errors, png


def test_report_html_in_headless_chromium(page):
    state, errors, png = _load_in_chromium(page[0])
    assert errors == []
    assert state[0] == "object" and state[1] > 5 and state[2] >= 1
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(int)
    saturation = img.max(axis=2) - img.min(axis=2)
    assert img.std() > 5.0  # not one flat colour
    assert np.count_nonzero(saturation > 80) >= MIN_COLOURED_PIXELS  # traces were drawn


def test_browser_check_sees_errors_and_blank_pages(tmp_path):
    """The control: a page that throws and draws nothing fails both checks."""
    path = tmp_path / "broken.html"
    path.write_text(
        "<!doctype html><html><body><script>throw new Error('boom');</script></body></html>", encoding="utf-8"
    )
    state, errors, png = _load_in_chromium(path)
    assert any("boom" in e["message"] for e in errors) and state[0] == "undefined"
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR).astype(int)
    assert np.count_nonzero(img.max(axis=2) - img.min(axis=2) > 80) < MIN_COLOURED_PIXELS


def test_floor_grid_from_payloads_equals_the_grid_read_from_detections_csv(tmp_path):
    """The run takes the faint floor-code grid from its detections in memory; `fusion inventory`
    redraws report.html from detections.csv: the same codes, each once, sorted, in metres."""
    from fusion.qr.detect import CameraStats, DetectionResult, write_cache
    from fusion.types import QRDetection
    from fusion.warehouse.view3d import floor_codes_from_detections, floor_codes_from_payloads

    corners = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    payloads = ["0/3/2", "0/1/2", "1/box-7", "0/3/2", "junk", "0/1/-4.5", "0/x/2"]
    dets = [
        QRDetection("cam0" if i % 4 else "cam1", 1000 + i, p, corners, corners)
        for i, p in enumerate(payloads + payloads)
    ]
    write_cache(DetectionResult(dets, {"cam0": CameraStats()}), tmp_path / "detections.csv", "f" * 64)
    floor = [d.payload for d in dets if d.camera == "cam0"]
    from_csv = floor_codes_from_detections(tmp_path, 0.5)
    from_payloads = floor_codes_from_payloads(floor, 0.5)
    assert from_csv is not None and from_payloads is not None
    assert from_payloads.tobytes() == from_csv.tobytes()
    np.testing.assert_array_equal(from_payloads, [[0.5, -2.25], [0.5, 1.0], [1.5, 1.0]])
    assert floor_codes_from_payloads(["1/box-7", "junk"], 0.5) is None


def test_ground_truth_drawn_from_positions_equals_the_one_drawn_from_poses():
    """report.html draws the ground truth from its positions (hook.groundtruth_track), not from
    (N, 4, 4) poses: the figure must not change, decimated rows and the time slider's marker
    (taken from every row) included; float32 positions as read are drawn as float64."""
    from fusion.log.euroc import GroundTruth
    from fusion.warehouse.hook import groundtruth_track

    rng = np.random.default_rng(3)
    n = 5 * MAX_DISPLAY_POSES + 7  # decimated, and the slider's times fall between drawn rows
    t_ns = np.cumsum(rng.integers(4_000_000, 6_000_000, n)).astype(np.int64)
    q = rng.normal(size=(n, 4))
    gt = GroundTruth(
        t_ns,
        (rng.normal(size=(n, 3)) * 3).astype(np.float32),
        q / np.linalg.norm(q, axis=1, keepdims=True),
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        np.zeros((n, 3)),
    )
    trajs = {"smoother": _trajectory("smoother", rng)}
    from_poses = build_figure(trajs, None, groundtruth=Trajectory("groundtruth", t_ns, gt.T_world_body))
    from_positions = build_figure(trajs, None, groundtruth=groundtruth_track(gt))
    assert from_positions.to_json() == from_poses.to_json()
    assert from_poses.data[0].name == "groundtruth trajectory"
    assert len(from_poses.data[0].x) == MAX_DISPLAY_POSES  # the truth was decimated
