"""QR detection and sub-pixel corners on rendered frames (fusion.sim.render), flight detection,
the detections.csv cache."""

from __future__ import annotations

import math
import re
import shutil

import numpy as np
import pytest
import zxingcpp

from fusion.camera import CameraModel
from fusion.errors import DetectionError, LogError
from fusion.geometry import make_T, rot_z
from fusion.log import FlightLogWriter, read_flight
from fusion.pipeline import RunConfig, run
from fusion.qr.detect import (
    CameraStats,
    detect_flight,
    detect_frame,
    detect_image,
    read_cache,
)
from fusion.qr.refine import (
    _POLISH_MAX_MOVE_PX,
    POLISHED_CAMERAS,
    estimate_modules,
    modules_for_version,
    refine_code,
    refine_frames,
)
from fusion.sim.render import (
    PlacedCode,
    RenderEffects,
    placed_floor_codes,
    project_code_corners,
    render_view,
)
from fusion.world import World

R_DOWN = np.diag([1.0, -1.0, -1.0])  # camera z = world -z (looking at the floor)


def _camera(distortion=(0.0, 0.0, 0.0, 0.0)) -> CameraModel:
    return CameraModel(640, 480, 520.0, 518.0, 322.0, 237.0, distortion=np.array(distortion))


def _pose(yaw: float, xy=(0.0, 0.0), height=0.8, tilt=(0.0, 0.0)) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    R_tilt = Rotation.from_euler("xy", tilt).as_matrix()
    return make_T(rot_z(yaw) @ R_tilt @ R_DOWN, [xy[0], xy[1], height])


def _code(payload: str, side_m: float = 0.2, xy=(0.0, 0.0)) -> PlacedCode:
    return PlacedCode(payload, make_T(np.eye(3), [xy[0], xy[1], 0.0]), side_m)


def _render(camera, T_world_cam, codes, seed=0, noise=0.0, blur=0.0):
    rng = np.random.default_rng(seed)
    img = render_view(
        camera, T_world_cam, codes, rng, RenderEffects(noise_sigma_dn=noise, blur_px=blur, blur_angle_rad=0.7)
    )
    truth = {c.payload: project_code_corners(camera, T_world_cam, c) for c in codes}
    return img, truth


# ============================================================================ corner order


@pytest.mark.parametrize("backend", ["zxing", "aruco"])
@pytest.mark.parametrize("yaw_deg", [0, 90, 180, 270, 33, -127])
def test_corner_order_follows_the_finder_patterns(backend, yaw_deg):
    camera = _camera()
    # 0.3 m at 0.8 m: OpenCV's detector misses some angles of smaller codes (zxing does not)
    img, truth = _render(camera, _pose(math.radians(yaw_deg)), [_code("0/3/-4", 0.3)], noise=1.0)
    dets = detect_frame(img, "cam0", 5, camera, backend)
    assert len(dets) == 1
    d = dets[0]
    assert d.payload == "0/3/-4" and d.camera == "cam0" and d.timestamp_ns == 5
    gt = truth["0/3/-4"]
    # every raw corner is nearest to its own true corner (order TL, TR, BR, BL), within a few px
    dist = np.linalg.norm(d.corners_raw_px[:, None] - gt[None], axis=2)
    assert np.all(np.argmin(dist, axis=1) == np.arange(4))
    assert np.all(np.diag(dist) < 4.0)
    assert np.max(np.linalg.norm(d.corners_px - gt, axis=1)) < 0.2


# ============================================================================ accuracy


def test_refined_corners_within_a_fraction_of_a_pixel_on_clean_renders():
    camera = _camera((-0.28, 0.08, 0.0006, -0.0004))
    rng = np.random.default_rng(3)
    codes = placed_floor_codes(np.array([[0, 0], [1, 0], [0, 1], [1, 1]]), 0.35, 0.2)
    err_raw, err_ref = [], []
    for _ in range(6):
        T = _pose(
            rng.uniform(-np.pi, np.pi),
            rng.uniform(0.0, 0.35, 2),
            rng.uniform(0.7, 1.3),
            rng.normal(0.0, 0.12, 2),
        )
        img, truth = _render(camera, T, codes, noise=0.5)
        for d in detect_frame(img, "cam0", 0, camera):
            err_raw.append(np.linalg.norm(d.corners_raw_px - truth[d.payload], axis=1))
            err_ref.append(np.linalg.norm(d.corners_px - truth[d.payload], axis=1))
    err_raw, err_ref = np.array(err_raw), np.array(err_ref)
    assert len(err_ref) >= 10
    assert err_ref.mean() < 0.1  # measured 0.02 px (raw zxing: 0.7-1.0 px)
    assert err_ref.max() < 0.25
    assert err_raw.mean() > 3 * err_ref.mean()


def test_undistorted_line_fits_beat_fitting_in_the_distorted_image():
    camera = _camera((-0.35, 0.12, 0.0, 0.0))
    # a code near the image corner, where distortion bends its edges most
    T = _pose(0.4, (0.0, 0.0), 0.75)
    code = _code("1/pallet-0042", 0.2, (0.2, 0.12))
    img, truth = _render(camera, T, [code])
    [raw] = detect_image(img)
    with_cam = refine_code(img, raw.corners_px, raw.modules, camera).corners_px
    without = refine_code(img, raw.corners_px, raw.modules, None).corners_px
    e_cam = np.linalg.norm(with_cam - truth[code.payload], axis=1).mean()
    e_none = np.linalg.norm(without - truth[code.payload], axis=1).mean()
    assert e_cam < 0.15 and e_cam < 0.5 * e_none


@pytest.mark.parametrize("payload", ["0/1/2", "1/" + "x" * 30, "1/" + "load-" * 12])
def test_module_count_estimated_from_the_finders(payload):
    camera = _camera()
    img, truth = _render(camera, _pose(0.6), [_code(payload, 0.25)])
    [raw] = detect_image(img)
    assert raw.modules == PlacedCode(payload, np.eye(4), 0.2).modules
    assert estimate_modules(img, raw.corners_px) == raw.modules
    # refinement without the version (aruco path) lands on the same corners
    a = refine_code(img, raw.corners_px, None)
    b = refine_code(img, raw.corners_px, raw.modules)
    assert a is not None and np.allclose(a.corners_px, b.corners_px)


def test_finder_homography_improves_the_bottom_right_corner():
    camera = _camera((-0.2, 0.05, 0.0, 0.0))
    err = {True: [], False: []}
    for yaw in np.linspace(0.0, 2.0 * np.pi, 9)[:-1]:
        T = _pose(yaw, tilt=(0.12 * np.sin(yaw), 0.12 * np.cos(yaw)))
        img, truth = _render(camera, T, [_code("0/7/7", 0.2)], noise=1.0, seed=int(10 * yaw))
        [raw] = detect_image(img)
        for fh in err:
            c = refine_code(img, raw.corners_px, raw.modules, camera, finder_homography=fh).corners_px
            err[fh].append(np.linalg.norm(c - truth["0/7/7"], axis=1))
    with_h, lines_only = np.array(err[True]), np.array(err[False])
    assert with_h[:, 2].mean() < 0.75 * lines_only[:, 2].mean()  # measured 0.025 vs 0.038 px
    assert with_h.mean() < 0.03 and with_h.max() < 0.15


def _blurred_renders(blurs, n_per_blur, seed, noise=2.0):
    """(image, raw corners, true corners, modules, blur px) of one 0.2 m floor code seen from
    0.9-1.5 m (3.3-5.5 px per module) with motion blur `blur` px in a random image direction.  The raw
    corners are the truth plus 0.7 px noise, rounded (a decoder's), so heavy blur that zxing
    cannot decode still tests the refinement."""
    camera = _camera((-0.05, 0.012, 4e-4, -3e-4))
    rng = np.random.default_rng(seed)
    code = _code("0/2/5", 0.2)
    out = []
    for blur in blurs:
        for _ in range(n_per_blur):
            T = _pose(
                rng.uniform(-np.pi, np.pi),
                rng.uniform(-0.2, 0.2, 2),
                rng.uniform(0.9, 1.5),
                rng.normal(0.0, 0.05, 2),
            )
            img = render_view(
                camera,
                T,
                [code],
                rng,
                RenderEffects(noise_sigma_dn=noise, blur_px=blur, blur_angle_rad=rng.uniform(0.0, np.pi)),
            )
            truth = project_code_corners(camera, T, code)
            raw = np.round(truth + rng.normal(0.0, 0.7, truth.shape))
            out.append((camera, img, raw, truth, code.modules, blur))
    return out


def test_motion_blur_does_not_push_the_corners_outwards():
    """A symmetric motion blur wider than a module greys the finder's 1-module ring; fitting the
    finder's blurred module sequence keeps the edges in place (the 50 % crossing moved them
    outwards by 0.2-1 px at 4-8 px blur)."""
    outward, err = [], []
    for camera, img, raw, truth, modules, blur in _blurred_renders([2, 4, 6, 8], 6, seed=11):
        res = refine_code(img, raw, modules, camera)
        assert res is not None
        c = res.corners_px
        centre = truth.mean(axis=0)
        radial = (truth - centre) / np.linalg.norm(truth - centre, axis=1, keepdims=True)
        outward.append(np.sum((c - truth) * radial, axis=1))
        err.append(np.linalg.norm(c - truth, axis=1))
    outward, err = np.array(outward), np.array(err)
    assert abs(outward.mean()) < 0.1  # measured +0.004 px
    assert err.mean() < 0.2  # measured 0.041 px
    assert err[-6:].mean() < 0.2  # 8 px blur alone: measured 0.095 px


def test_refining_frames_together_equals_one_at_a_time():
    """refine_frames (all codes of several images in one batch) = refine_code per code."""
    data = _blurred_renders([0, 3, 6], 2, seed=5)
    images = [img for _, img, _, _, _, _ in data]
    codes = [[(raw, modules)] for _, _, raw, _, modules, _ in data]
    camera = data[0][0]
    together = refine_frames(images, codes, camera)
    for img, c, [res] in zip(images, codes, together):
        alone = refine_code(img, *c[0], camera)
        assert res is not None and res.stage == 2
        np.testing.assert_allclose(res.corners_px, alone.corners_px, rtol=0, atol=1e-9)
        np.testing.assert_allclose(res.corner_cov_px2, alone.corner_cov_px2, rtol=1e-9)


def test_refinement_failure_gives_none():
    img = np.full((120, 160), 200, np.uint8)  # nothing to fit
    raw = np.array([[40.0, 30.0], [100.0, 30.0], [100.0, 90.0], [40.0, 90.0]])
    assert refine_code(img, raw, 21) is None
    assert refine_frames([img, img], [[(raw, 21)], []]) == [[None], []]
    assert modules_for_version(1) == 21 and modules_for_version(40) == 177


# ============================================================================ payloads


def test_foreign_payload_is_returned_as_is():
    camera = _camera()
    text = 'hello, "world"\nline2 \u00e9'
    img, _ = _render(camera, _pose(0.2), [_code(text, 0.25)])
    [d] = detect_frame(img, "cam1", 9, camera)
    assert d.payload == text


def test_binary_payload_is_dropped_and_counted_not_raised():
    bc = zxingcpp.create_barcode(b"\xff\xfe1/abc", zxingcpp.BarcodeFormat.QRCode)
    img = np.pad(np.asarray(bc.to_image(scale=6)), 30, constant_values=255)
    stats = CameraStats()
    assert detect_frame(img, "cam1", 0, None, "zxing", stats) == []
    assert stats.payloads_dropped == 1


def test_unknown_backend_raises():
    with pytest.raises(DetectionError, match="backend"):
        detect_image(np.zeros((10, 10), np.uint8), "wechat")


# ============================================================================ flights + cache


def _write_flight(root, n0=4):
    """cam0: n0 frames seeing floor codes at several yaws, one of them corrupted later;
    cam1: 2 frames of a load code and a foreign payload."""
    camera = _camera((-0.1, 0.02, 0.0, 0.0))
    floor = placed_floor_codes(np.array([[0, 0], [1, 0]]), 0.3, 0.2)
    front = [_code("1/box-7", 0.2, (0.0, 0.0)), _code("not, ours", 0.2, (0.3, 0.0))]
    with FlightLogWriter(root) as w:
        w.write_world(World(floor_side_m=0.2, payload_unit_m=0.3))
        w.add_camera("cam0", camera)
        w.add_camera("cam1", camera)
        for i in range(n0):
            img, _ = _render(camera, _pose(0.5 * i, (0.15, 0.0), 0.9), floor, seed=i, noise=1.0)
            w.write_frame("cam0", 1000 + i, img)
        for i in range(2):
            img, _ = _render(camera, _pose(0.3 + i, (0.15, 0.0), 0.9), front, seed=10 + i)
            w.write_frame("cam1", 5000 + i, img)
    (root / "mav0" / "cam0" / "data" / "1002.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    return root


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    return _write_flight(tmp_path_factory.mktemp("flight") / "log")


def test_detect_flight_counts_frames_and_skips_a_corrupt_png(flight):
    res = detect_flight(read_flight(flight), workers=1, progress=False)
    s0, s1 = res.stats["cam0"], res.stats["cam1"]
    assert (s0.frames_total, s0.frames_skipped, s0.frames_with_code) == (4, 1, 3)
    assert (s1.frames_total, s1.frames_skipped, s1.frames_with_code) == (2, 0, 2)
    assert len(res.skipped) == 1 and "1002.png" in res.skipped[0] and "data.csv:4" in res.skipped[0]
    by0 = res.by_frame("cam0")
    assert sorted(by0) == [1000, 1001, 1003]
    assert all(sorted(d.payload for d in v) == ["0/0/0", "0/1/0"] for v in by0.values())
    by1 = res.by_frame("cam1")
    assert sorted(d.payload for d in by1[5000]) == ["1/box-7", "not, ours"]
    assert all(d.corners_px.shape == (4, 2) for d in res.detections)


def test_parallel_equals_serial(flight):
    log = read_flight(flight)
    a = detect_flight(log, workers=1, progress=False)
    b = detect_flight(read_flight(flight), workers=2, progress=False, chunk_frames=1)
    assert [(d.camera, d.timestamp_ns, d.payload) for d in a.detections] == [
        (d.camera, d.timestamp_ns, d.payload) for d in b.detections
    ]
    assert all(np.array_equal(x.corners_px, y.corners_px) for x, y in zip(a.detections, b.detections))
    assert a.stats == b.stats and a.skipped == b.skipped


def test_cache_round_trip_and_invalidation(tmp_path):
    root = _write_flight(tmp_path / "log", n0=3)
    cache = tmp_path / "out" / "detections.csv"
    first = detect_flight(read_flight(root), cache, workers=1, progress=False)
    assert cache.is_file() and not first.from_cache
    again = detect_flight(read_flight(root), cache, workers=1, progress=False)
    assert again.from_cache
    assert again.stats == first.stats and again.skipped == first.skipped
    assert [(d.camera, d.timestamp_ns, d.payload) for d in again.detections] == [
        (d.camera, d.timestamp_ns, d.payload) for d in first.detections
    ]
    for x, y in zip(first.detections, again.detections):
        assert np.array_equal(x.corners_px, y.corners_px)  # repr() floats round-trip
        assert np.array_equal(x.corners_raw_px, y.corners_raw_px)
        assert x.corner_sigma_px == y.corner_sigma_px and x.corner_sigma_px > 0
        assert np.array_equal(x.corner_cov_px2, y.corner_cov_px2)
        assert x.corner_cov_px2.shape == (8, 8)
    # another backend: recomputed
    assert not detect_flight(read_flight(root), cache, backend="aruco", workers=1, progress=False).from_cache
    # a changed data.csv (last frame dropped): recomputed, and the new counts are right
    detect_flight(read_flight(root), cache, workers=1, progress=False)
    csv_path = root / "mav0" / "cam0" / "data.csv"
    csv_path.write_text("".join(csv_path.read_text().splitlines(keepends=True)[:-1]))
    changed = detect_flight(read_flight(root), cache, workers=1, progress=False)
    assert not changed.from_cache and changed.stats["cam0"].frames_total == 2


def test_malformed_cache_raises_naming_file_and_line(tmp_path, flight):
    cache = tmp_path / "detections.csv"
    res = detect_flight(read_flight(flight), cache, workers=1, progress=False)
    lines = cache.read_text().splitlines(keepends=True)
    assert len(lines) == 3 + len(res.detections)
    bad = lines[:4] + ["cam0,12,x,1,2,3\n"] + lines[4:]
    cache.write_text("".join(bad))
    with pytest.raises(DetectionError, match=r"detections\.csv:5: expected 23 fields"):
        detect_flight(read_flight(flight), cache, workers=1, progress=False)
    cache.write_text("".join(lines[:4] + ['cam0,12,"p",' + ",".join(["nan"] * 16) + ",1,0.1,,0\n"]))
    with pytest.raises(DetectionError, match=r"detections\.csv:5: .*non-finite"):
        read_cache(cache)
    good_row = lines[3].rstrip("\n").rsplit(",", 2)[0]
    cache.write_text("".join(lines[:3] + [good_row + ",1 2 3,0\n"]))
    with pytest.raises(DetectionError, match=r"detections\.csv:4: corner_cov_px2 needs 36"):
        read_cache(cache)
    cache.write_text("timestamp,whatever\n")
    with pytest.raises(DetectionError, match=r"detections\.csv:1: not a fusion detection cache"):
        detect_flight(read_flight(flight), cache, workers=1, progress=False)


def _calibration_renders(n, seed):
    """(corner error (8,), RefineResult, blur px) of one 0.3 m code seen from 0.8-2.5 m
    (3-9 px per module) with blur 0-8 px and noise 0.5-4 DN; raw corners as in _blurred_renders."""
    camera = _camera((-0.05, 0.012, 4e-4, -3e-4))
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        code = _code(["0/2/5", "1/" + "x" * 20][i % 2], 0.3)
        T = _pose(
            rng.uniform(-np.pi, np.pi),
            rng.uniform(-0.2, 0.2, 2),
            rng.uniform(0.8, 2.5),
            rng.normal(0.0, 0.08, 2),
        )
        blur = rng.uniform(0.0, 8.0)
        img = render_view(
            camera,
            T,
            [code],
            rng,
            RenderEffects(
                noise_sigma_dn=rng.uniform(0.5, 4.0), blur_px=blur, blur_angle_rad=rng.uniform(0.0, np.pi)
            ),
        )
        truth = project_code_corners(camera, T, code)
        res = refine_code(img, np.round(truth + rng.normal(0.0, 0.7, truth.shape)), code.modules, camera)
        if res is not None:
            out.append(((res.corners_px - truth).reshape(-1), res, blur))
    return out


def test_corner_covariance_is_calibrated_over_heights_blur_and_noise():
    """The (8, 8) corner covariance: 8-D NEES near 8 on seeded renders the calibration
    (scripts/bench_detect.py --calibrate) did not see, in every blur bin; corner_sigma_px is the
    root of its mean diagonal; the corners are correlated (one homography)."""
    data = _calibration_renders(80, seed=2024)
    assert len(data) >= 76
    nees, blur = [], []
    for e, res, b in data:
        C = res.corner_cov_px2
        assert C.shape == (8, 8) and np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0)
        assert res.corner_sigma_px == pytest.approx(np.sqrt(np.mean(np.diag(C))))
        nees.append(e @ np.linalg.solve(C, e))
        blur.append(b)
    nees, blur = np.array(nees), np.array(blur)
    assert 0.7 * 8 <= nees.mean() <= 1.4 * 8, nees.mean()  # measured 7.3
    for lo in (0, 4):
        sel = (blur >= lo) & (blur < lo + 4)
        assert 0.6 * 8 <= nees[sel].mean() <= 1.5 * 8, (lo, nees[sel].mean())
    # one homography: the corners' errors are correlated (largest |rho| per code 0.35-0.94)
    rho = [
        np.max(np.abs(C / np.sqrt(np.outer(np.diag(C), np.diag(C))) - np.eye(8)))
        for C in (res.corner_cov_px2 for _, res, _ in data)
    ]
    assert np.median(rho) > 0.3


# ---------------------------------------------------------------------------- speed rewrites
# (issue 13: refine.py's inner loops reshaped for speed; each piece checked against a plain
# reference so a later rewrite cannot change what it computes)


def test_blurred_steps_match_a_numerical_convolution_and_their_derivatives():
    from fusion.qr.refine import _MODEL_STEPS, _blurred_steps

    rng = np.random.default_rng(3)
    P, K = 7, 9
    x = rng.uniform(-2.0, 3.0, (P, K))
    a = rng.uniform(0.2, 1.5, (P, 1))
    b = rng.uniform(0.2, 1.5, (P, 1))
    F, F_x, F_a = _blurred_steps(x, a, b)
    assert F.shape == F_x.shape == F_a.shape == (len(_MODEL_STEPS), P, K)
    # reference: the CDF of box(a) * box(b) at x - step, by dense numerical convolution
    t = np.linspace(-2.0, 2.0, 8001)
    dt = t[1] - t[0]
    for p in range(P):
        box_a = (np.abs(t) <= a[p, 0] / 2) / a[p, 0]
        box_b = (np.abs(t) <= b[p, 0] / 2) / b[p, 0]
        cdf = np.cumsum(np.convolve(box_a, box_b, mode="same") * dt) * dt
        for j, step in enumerate(_MODEL_STEPS):
            np.testing.assert_allclose(F[j, p], np.interp(x[p] - step, t, cdf), atol=2e-3)
    h = 1e-6
    np.testing.assert_allclose(
        F_x, (_blurred_steps(x + h, a, b)[0] - _blurred_steps(x - h, a, b)[0]) / (2 * h), atol=1e-5
    )
    np.testing.assert_allclose(
        F_a, (_blurred_steps(x, a + h, b)[0] - _blurred_steps(x, a - h, b)[0]) / (2 * h), atol=1e-5
    )
    # the second box's width (the fitted PSF): same F and derivatives, dF/db as a fourth
    F2, F2_x, F2_a, F_b = _blurred_steps(x, a, b, psf_derivative=True)
    np.testing.assert_array_equal(F2, F)
    np.testing.assert_array_equal(F2_a, F_a)
    np.testing.assert_allclose(
        F_b, (_blurred_steps(x, a, b + h)[0] - _blurred_steps(x, a, b - h)[0]) / (2 * h), atol=1e-5
    )


def test_level_fit_equals_least_squares_profile_by_profile():
    from fusion.qr.refine import _levels

    rng = np.random.default_rng(4)
    P, K = 11, 19
    D, Dd = rng.uniform(0, 1, (P, K)), rng.uniform(0, 1, (P, K))
    y = rng.uniform(0, 255, (P, K))
    m = (rng.uniform(size=(P, K)) > 0.2).astype(float)
    lev, r, A, Ninv = _levels(D, Dd, y, m)
    for p in range(P):
        B = np.column_stack([m[p], D[p] * m[p], Dd[p] * m[p]])
        ref = np.linalg.lstsq(B, y[p] * m[p], rcond=None)[0]
        np.testing.assert_allclose(lev[p], ref, rtol=1e-4, atol=1e-3)
        np.testing.assert_allclose(r[p], B @ lev[p] - y[p] * m[p], atol=1e-6)
        N = B.T @ B + np.diag([1e-9, 1e-9, 1e-6])
        v = rng.normal(size=3)
        np.testing.assert_allclose(Ninv.matvec(np.tile(v, (P, 1)))[p], np.linalg.solve(N, v), rtol=1e-6)


def test_sampling_frames_in_any_order_gives_the_same_values():
    from fusion.qr.refine import _Distortion, _rows_by_image, _sample_profiles

    rng = np.random.default_rng(5)
    images = [rng.integers(0, 256, (48, 64), dtype=np.uint8) for _ in range(3)]
    R, K = 12, 5
    rows = np.sort(rng.integers(0, 3, R))
    H = np.tile(np.diag([4.0, 4.0, 1.0]), (R, 1, 1))
    uv = rng.uniform(0.5, 10.0, (R, 2))
    step = rng.normal(size=(R, 2))
    s = rng.uniform(-1, 1, (R, K))
    vals, inside, clipped = _sample_profiles(images, rows, _Distortion(None), H, uv, step, s)
    order = rng.permutation(R)  # unsorted rows: the boolean-mask path
    v2, i2, c2 = _sample_profiles(
        images, rows[order], _Distortion(None), H[order], uv[order], step[order], s[order]
    )
    np.testing.assert_array_equal(v2, vals[order])
    np.testing.assert_array_equal(i2, inside[order])
    assert isinstance(_rows_by_image(rows, 3)[0][1], slice)
    assert not isinstance(_rows_by_image(rows[order], 3)[0][1], slice) or np.all(np.diff(rows[order]) >= 0)
    # each row read from its own image
    for k in range(R):
        x = H[k, 0, 0] * (uv[k, 0] + s[k] * step[k, 0])
        y = H[k, 1, 1] * (uv[k, 1] + s[k] * step[k, 1])
        ok = (x >= 0) & (y >= 0) & (x <= 63) & (y <= 47)
        xi, yi = np.round(x[ok]).astype(int), np.round(y[ok]).astype(int)
        near = np.abs(x[ok] - xi) + np.abs(y[ok] - yi) < 0.02
        np.testing.assert_allclose(vals[k][ok][near], images[rows[k]][yi[near], xi[near]], atol=1.0)


def test_a_floor_camera_with_no_readable_frame_is_an_error_naming_the_file(tmp_path, flight):
    """sensor.yaml's resolution unlike every image's (a calibration of another camera): each frame
    is skipped, and the run stops with the first frame's file and line instead of writing the
    outputs of a flight without codes."""
    root = tmp_path / "log"
    shutil.copytree(flight, root)
    yaml_path = root / "mav0" / "cam0" / "sensor.yaml"
    text = yaml_path.read_text()
    yaml_path.write_text(re.sub(r"resolution: \[\d+, \d+\]", "resolution: [1280, 720]", text))
    expected = r"cam0/data.csv:2: image 1000.png is .* sensor.yaml says 1280x720 .*4 unreadable"
    with pytest.raises(LogError, match=expected):
        run(root, tmp_path / "out", RunConfig(workers=1), until="detect")


def test_the_front_cameras_sharp_codes_are_polished_from_whole_pixels():
    """Codes at ~4 px per module, sharp: bilinear samples read their edges with a phase error of
    a few hundredths of a pixel.  The front camera's codes (POLISHED_CAMERAS) are placed again
    from whole pixels: closer to the truth, moved by at most _POLISH_MAX_MOVE_PX, their covariance
    (the bilinear passes' edge sigmas) kept; the floor camera's are not polished."""
    assert POLISHED_CAMERAS == {"cam1"}
    camera = _camera()
    rng = np.random.default_rng(8)
    codes = placed_floor_codes(np.array([[0, 0], [1, 0], [0, 1], [1, 1]]), 0.3, 0.2)
    err = {"cam0": [], "cam1": []}
    for _ in range(6):
        T = _pose(
            rng.uniform(-np.pi, np.pi),
            rng.uniform(0.0, 0.3, 2),
            rng.uniform(1.1, 1.4),
            rng.normal(0.0, 0.1, 2),
        )
        img, truth = _render(camera, T, codes, noise=0.5)
        floor, front = detect_frame(img, "cam0", 0, camera), detect_frame(img, "cam1", 0, camera)
        assert [d.payload for d in floor] == [d.payload for d in front]
        for a, b in zip(floor, front):
            assert np.max(np.linalg.norm(a.corners_px - b.corners_px, axis=1)) <= _POLISH_MAX_MOVE_PX + 1e-9
            np.testing.assert_allclose(b.corner_cov_px2, a.corner_cov_px2, rtol=0.05, atol=1e-6)
            err["cam0"].append(np.linalg.norm(a.corners_px - truth[a.payload], axis=1))
            err["cam1"].append(np.linalg.norm(b.corners_px - truth[b.payload], axis=1))
    e0, e1 = np.mean(err["cam0"]), np.mean(err["cam1"])
    assert len(err["cam1"]) >= 10
    assert e1 < 0.7 * e0, (e0, e1)
