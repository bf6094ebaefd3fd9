"""Rolling shutter (issue 10, item 1): camera model fields and their files, per-row rendering,
corners moved to the stamp before PnP, readout calibration."""

from __future__ import annotations

import math

from dataclasses import replace

import numpy as np
import pytest

from fusion.camera import CameraModel, StampRow
from fusion.cli import build_parser
from fusion.errors import CameraModelError, LogError
from fusion.geometry import R_from_euler, interpolate_poses, level_frame, make_T, so3_exp, so3_log
from fusion.log.euroc import ImuNoise
from fusion.log.kalibr import read_camchain, write_camchain
from fusion.qr.codes import classify
from fusion.qr.detect import DetectionResult, detect_frame
from fusion.qr.pnp import estimate_floor_pose, pnp_trajectory
from fusion.qr.refine import refine_frames
from fusion.qr.rolling_shutter import (
    FrameMotion,
    _body_poses_at,
    _image_reader,
    _ImuTrack,
    calibrate_readout,
    check_undeclared_readout,
    correct_flight,
    correct_frames,
    frame_motion,
    refine_at_stamp,
)
from fusion.sim.imu import synthesize_imu
from fusion.sim.render import (
    RenderEffects,
    project_code_corners,
    project_code_corners_rolling,
    render_view,
    rolling_shutter_poses,
)
from fusion.sim.scenarios import build_scenario
from fusion.sim.trajectory import KeyframeTrajectory, survey_keyframes
from fusion.types import QRDetection, Trajectory

READOUT_S = 0.02
FLIGHT_S = 3.0


@pytest.fixture(scope="module")
def scene():
    sc = build_scenario("default")
    return sc, [c for c in sc.codes() if c.is_floor]


def constant_twist(T0: np.ndarray, v_world: np.ndarray, omega_body: np.ndarray):
    """T_world_body(t) of a body moving at constant world velocity and body rate from T0."""

    def at(ts):
        ts = np.atleast_1d(np.asarray(ts, float))
        out = np.tile(np.eye(4), (len(ts), 1, 1))
        for i, t in enumerate(ts):
            out[i, :3, :3] = T0[:3, :3] @ so3_exp(omega_body * t)
            out[i, :3, 3] = T0[:3, 3] + v_world * t
        return out

    return at


# ---------------------------------------------------------------------------- camera model


def test_row_time_offset_first_and_middle():
    cam = CameraModel(640, 480, 550.0, 550.0, 320.0, 240.0, line_delay_s=READOUT_S / 480)
    assert cam.rolling_shutter and cam.readout_s == pytest.approx(READOUT_S)
    assert cam.row_time_offset_s(0.0) == 0.0
    assert cam.row_time_offset_s(480.0) == pytest.approx(READOUT_S)
    mid = replace(cam, stamp_row=StampRow.MIDDLE)
    assert mid.row_time_offset_s(239.5) == pytest.approx(0.0)
    assert mid.row_time_offset_s(0.0) == pytest.approx(-239.5 * READOUT_S / 480)
    glob = CameraModel(640, 480, 550.0, 550.0, 320.0, 240.0)
    assert not glob.rolling_shutter and np.all(glob.row_time_offset_s([0.0, 479.0]) == 0.0)


def test_sensor_yaml_round_trip_of_readout_fields():
    cam = CameraModel(640, 480, 550.0, 551.0, 321.0, 239.0, line_delay_s=3.1e-5, stamp_row=StampRow.MIDDLE)
    data = cam.to_sensor_yaml()
    assert data["line_delay_s"] == pytest.approx(3.1e-5) and data["stamp_row"] == "middle"
    back = CameraModel.from_sensor_yaml(data)
    assert back.line_delay_s == pytest.approx(3.1e-5) and back.stamp_row == StampRow.MIDDLE
    # a global-shutter camera writes no rolling-shutter keys (files stay as they were)
    glob = CameraModel.from_sensor_yaml(
        {k: v for k, v in data.items() if k not in ("line_delay_s", "stamp_row")}
    )
    assert "line_delay_s" not in glob.to_sensor_yaml() and glob.line_delay_s == 0.0
    with pytest.raises(CameraModelError, match="line_delay_s"):
        CameraModel.from_sensor_yaml({**data, "line_delay_s": 0.02})  # ms taken for s per row
    with pytest.raises(CameraModelError, match="stamp_row"):
        CameraModel.from_sensor_yaml({**data, "stamp_row": "last"})


def test_kalibr_round_trip_of_line_delay(tmp_path):
    cams = {
        "cam0": CameraModel(640, 480, 550.0, 550.0, 320.0, 240.0, line_delay_s=4e-5),
        "cam1": CameraModel(640, 480, 550.0, 550.0, 320.0, 240.0, line_delay_s=2e-5, stamp_row="middle"),
    }
    path = tmp_path / "camchain-imucam.yaml"
    write_camchain(path, cams, {})
    back = read_camchain(path)
    assert back["cam0"].camera.line_delay_s == pytest.approx(4e-5)
    assert back["cam0"].camera.stamp_row == StampRow.FIRST  # Kalibr's: the first row
    assert back["cam1"].camera.stamp_row == StampRow.MIDDLE
    text = path.read_text()
    assert "line_delay: 4.0e-05" in text or "line_delay: 4e-05" in text
    path.write_text(
        text.replace("line_delay: 4.0e-05", "line_delay: fast").replace(
            "line_delay: 4e-05", "line_delay: fast"
        )
    )
    with pytest.raises(LogError, match="line_delay"):
        read_camchain(path)


def test_cli_options():
    args = build_parser().parse_args(["simulate", "out", "--readout-ms", "20"])
    assert args.readout_ms == 20.0
    args = build_parser().parse_args(["run", "log", "--out", "o", "--calibrate-readout"])
    assert args.calibrate_readout


# ---------------------------------------------------------------------------- rendering


def test_per_row_render_corners_match_per_row_projection(scene):
    sc, codes = scene
    cam = replace(sc.cameras["cam0"], line_delay_s=0.03 / 480)
    T0 = make_T(R_from_euler("z", 0.3), [3.3, 1.4, 1.5])
    body_at = constant_twist(T0, np.array([2.0, 0.5, 0.0]), np.array([0.0, 0.0, 1.0]))
    img = render_view(
        cam, rolling_shutter_poses(cam, body_at, 0.0), codes, None, RenderEffects(noise_sigma_dn=0.0)
    )
    dets = [d for d in detect_frame(img, "cam0", 0, cam) if d.payload.startswith("0/")]
    assert len(dets) >= 2
    by_payload = {c.payload: c for c in codes}
    for d in dets:
        rolling = project_code_corners_rolling(cam, body_at, 0.0, by_payload[d.payload])
        stamp = project_code_corners(cam, cam.T_world_cam(T0), by_payload[d.payload])
        assert np.abs(d.corners_px - rolling).max() < 0.3  # refined corners: ~0.1 px
        assert np.abs(d.corners_px - stamp).max() > 3.0  # the readout moved them by pixels
    # a constant pose per row renders exactly the global-shutter image
    rows = np.repeat(cam.T_world_cam(T0)[None], cam.height, axis=0)
    glob = render_view(cam, cam.T_world_cam(T0), codes, None, RenderEffects(noise_sigma_dn=0.0))
    assert np.array_equal(render_view(cam, rows, codes, None, RenderEffects(noise_sigma_dn=0.0)), glob)


# ---------------------------------------------------------------------------- PnP


def _synthetic_frame(rng, codes, cam, body_at, sigma_px, noise_px=None):
    """Detections of the floor codes fully in view at stamp 0, corners projected per row +
    N(0, noise_px^2) (default sigma_px), covariance sigma_px^2 I."""
    dets = []
    T_wc = cam.T_world_cam(body_at(0.0)[0])
    for c in codes:
        at_stamp = project_code_corners(cam, T_wc, c)  # cheap pre-selection
        if (
            not np.all(np.isfinite(at_stamp))
            or np.any(at_stamp < -20)
            or np.any(at_stamp > [cam.width + 20, cam.height + 20])
        ):
            continue
        uv = project_code_corners_rolling(cam, body_at, 0.0, c)
        if not np.all(np.isfinite(uv)) or np.any(uv < 5) or np.any(uv > [cam.width - 6, cam.height - 6]):
            continue
        uv = uv + rng.normal(0.0, sigma_px if noise_px is None else noise_px, uv.shape)
        dets.append(QRDetection("cam0", 0, c.payload, uv, uv.copy(), corner_cov_px2=sigma_px**2 * np.eye(8)))
    return dets


def test_pnp_with_readout_correction_recovers_the_pose(scene):
    sc, codes = scene
    world = sc.layout.world
    cam = replace(sc.cameras["cam0"], line_delay_s=READOUT_S / 480)
    rng = np.random.default_rng(4)
    done = 0
    for _ in range(12):
        T0 = make_T(
            R_from_euler("zyx", [rng.uniform(-3, 3), rng.normal(0, 0.05), rng.normal(0, 0.05)]),
            [rng.uniform(2, 8), rng.uniform(0.6, 2.4), rng.uniform(1.1, 1.8)],
        )
        v = rng.normal(0.0, 1.0, 3) * [1, 1, 0.2]
        v *= 2.0 / np.linalg.norm(v)
        w = rng.normal(0.0, 0.4, 3)
        body_at = constant_twist(T0, v, w)
        # nearly noise-free corners: what is left is the correction's error
        dets = _synthetic_frame(rng, codes, cam, body_at, 0.05, noise_px=0.002)
        if not classify(dets, world).floor:
            continue
        raw = estimate_floor_pose(classify(dets, world).floor, cam)
        motion = FrameMotion(
            np.array([0]),
            T0[None] + 0.0,
            w[None],
            v[None],
            np.zeros((1, 3)),
            np.eye(3)[None] * 1e-6,
            np.array([True]),
            np.eye(3)[None] * 1e-6,
        )
        motion.T_world_body[0, :3, 3] += 0.005  # the approximate pose (depths) need not be exact
        fixed, n = correct_frames({0: dets}, cam, world, motion)
        assert n == 1
        res = estimate_floor_pose(classify(fixed[0], world).floor, cam)
        assert res is not None
        assert np.linalg.norm(res.T_world_body[:3, 3] - T0[:3, 3]) < 0.001
        assert raw is None or np.linalg.norm(raw.T_world_body[:3, 3] - T0[:3, 3]) > 0.005
        done += 1
    assert done >= 6


# ---------------------------------------------------------------------------- flight + calibration


@pytest.fixture(scope="module")
def synthetic_flight(scene):
    """A FLIGHT_S flight at up to 2 m/s with a 20 ms readout: per-row projected corners + 0.05 px
    noise (no rendering), the IMU from the same trajectory."""
    return _synthetic_flight(scene, READOUT_S, 0.05)


def _synthetic_flight(scene, readout_s: float, noise_px: float):
    sc, codes = scene
    cam = replace(sc.cameras["cam0"], line_delay_s=readout_s / 480)
    wps = [(1.0, 1.5, 1.4, 0.0), (4.0, 1.8, 1.6, 0.6), (6.5, 1.2, 1.3, -0.4)]
    traj = KeyframeTrajectory(survey_keyframes(wps, speed_m_s=2.0 / 2.1875, yaw_rate_rad_s=0.8))
    rng = np.random.default_rng(7)
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(), np.random.default_rng(8))
    dets = []
    grid = np.linspace(-0.002, READOUT_S + 0.002, 49)  # the readout, sampled (one state call)
    for t in np.arange(0.0, FLIGHT_S, 1.0 / 30.0):
        ts = int(round(t * 1e9))
        poses = traj.state(t + grid).T_world_body

        def body_at(dt, poses=poses):
            return interpolate_poses(grid, poses, np.atleast_1d(np.asarray(dt, float)))

        for d in _synthetic_frame(rng, codes, cam, body_at, 0.05, noise_px):
            dets.append(replace(d, timestamp_ns=ts))
    det = DetectionResult(dets, {})
    return det, cam, sc.layout.world, imu, traj


def test_correct_flight_recovers_the_trajectory(synthetic_flight):
    det, cam, world, imu, traj = synthetic_flight

    def err(dr):
        tr, _ = pnp_trajectory(dr.by_frame("cam0"), cam, world)
        truth = traj.state(tr.timestamps_ns * 1e-9).p_world
        return float(np.mean(np.linalg.norm(tr.T_world_body[:, :3, 3] - truth, axis=1)))

    fixed, report = correct_flight(det, {"cam0": cam}, world, imu)
    assert report.frames_corrected["cam0"] > 60
    assert report.pose_cov_added  # the motion's uncertainty enters the PnP covariance
    # the same flight with a global shutter: 4.0 mm (measured); uncorrected: 47 mm
    assert err(fixed) < 0.006 < 0.02 < err(det)


def test_an_undetermined_readout_is_not_applied_and_says_so(monkeypatch):
    """--calibrate-readout on a flight whose frames do not determine the readout (a flat cost
    profile, sigma inf): the declared line delay is kept and the run warns by name; before, the
    profile's midpoint was applied as if measured."""
    from pathlib import Path
    from types import SimpleNamespace

    from fusion import pipeline
    from fusion.qr.rolling_shutter import ReadoutCalibration, RollingShutterReport

    cam = CameraModel(640, 480, 550.0, 550.0, 320.0, 240.0, line_delay_s=0.0)
    log = SimpleNamespace(floor=SimpleNamespace(camera=cam), world=None, imu=None, cameras={})
    result = pipeline.RunResult(Path("."), {})
    cfg = pipeline.RunConfig(calibrate_readout=True)
    monkeypatch.setattr(pipeline, "correct_flight", lambda det, *a, **k: (det, RollingShutterReport()))
    for sigma, applied in ((math.inf, False), (0.0005, True)):
        monkeypatch.setattr(
            pipeline, "calibrate_readout", lambda *a, s=sigma, **k: ReadoutCalibration(0.015, s, 40, 1.0)
        )
        cam.line_delay_s = 0.0
        result.warnings.clear()
        pipeline._rolling_shutter(log, None, cfg, result)
        assert (cam.line_delay_s > 0) == applied
        assert [w.name for w in result.warnings] == ([] if applied else ["readout_not_calibrated"])


def test_calibrate_readout_recovers_a_known_value(synthetic_flight):
    det, cam, world, imu, _ = synthetic_flight
    calib = calibrate_readout(det, replace(cam, line_delay_s=0.0), world, imu, max_frames=60)
    assert calib.readout_s == pytest.approx(READOUT_S, rel=0.05)
    assert 0.0 < calib.sigma_s < 0.05 * READOUT_S
    assert abs(calib.readout_s - READOUT_S) < 4.0 * calib.sigma_s + 1e-4


@pytest.mark.parametrize("noise_px", [0.05, 0.5])
def test_an_undeclared_readout_is_found_and_a_global_shutter_is_not_blamed(scene, noise_px):
    """`check_undeclared_readout`: the 20 ms flight declared global shutter gives a readout near
    20 ms (one round from the uncorrected poses, a grid of 1/8 frame period); the same flight
    filmed with a global shutter gives none, also with corners 10x noisier than their covariance
    says (chi^2 / dof ~100: scatter the readout does not explain)."""
    det, cam, world, imu, _ = _synthetic_flight(scene, READOUT_S, noise_px)
    declared_global = replace(cam, line_delay_s=0.0)
    raw = pnp_trajectory(det.by_frame("cam0"), declared_global, world)[0]
    found = check_undeclared_readout(det, declared_global, world, imu, raw, max_frames=60)
    assert found is not None
    assert found.readout_s == pytest.approx(READOUT_S, abs=0.004)
    assert found.n_better > 0.8 * found.n_frames and found.p_value < 1e-6
    assert found.chi2_per_dof_rolling < 0.9 * found.chi2_per_dof_global
    # a camera declared rolling shutter is not checked
    assert check_undeclared_readout(det, cam, world, imu, raw, max_frames=60) is None

    det, cam, world, imu, _ = _synthetic_flight(scene, 0.0, noise_px)
    raw = pnp_trajectory(det.by_frame("cam0"), cam, world)[0]
    assert check_undeclared_readout(det, cam, world, imu, raw, max_frames=60) is None


def test_an_undeclared_readout_is_a_named_warning_of_the_run(scene, monkeypatch):
    """The pipeline's check runs only above the PnP chi^2 / dof trigger and names the readout."""
    from fusion import pipeline
    from fusion.pipeline import LocalizeResult

    det, cam, world, imu, _ = _synthetic_flight(scene, READOUT_S, 0.05)
    declared_global = replace(cam, line_delay_s=0.0)
    raw = pnp_trajectory(det.by_frame("cam0"), declared_global, world)[0]

    class Log:  # what the check reads of a FlightLog
        floor = type("Floor", (), {"camera": declared_global})()

    Log.world, Log.imu = world, imu
    cfg = pipeline.RunConfig()
    for scale, expected in ((1.2, None), (40.0, "rolling_shutter_undeclared")):
        loc = LocalizeResult({"pnp": raw}, {}, {}, {"pnp": {"noise_scale": {"scale": scale}}}, [])
        warning = pipeline.undeclared_rolling_shutter_warning(Log, det, loc, cfg)  # type: ignore[arg-type]
        assert (warning.name if warning else None) == expected
    assert "line_delay_s" in warning.message and "--calibrate-readout" in warning.message


# ---------------------------------------------------------------------------- per-row motion, stamp refine


@pytest.fixture(scope="module")
def accelerating_flight(scene):
    """2 m/s zig-zag with yaw swings (the body rate changes within a readout), its noise-free
    IMU and the true poses at 100 Hz (what PnP would give, exactly)."""
    sc, codes = scene
    wps = [(1.0, 1.5, 1.4, 0.0), (4.0, 1.8, 1.6, 0.6), (6.5, 1.2, 1.3, -0.4), (8.5, 1.6, 1.5, 0.5)]
    traj = KeyframeTrajectory(survey_keyframes(wps, speed_m_s=2.0 / 2.1875, yaw_rate_rad_s=0.8))
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(), np.random.default_rng(3), noise_free=True)
    ts_ns = np.arange(0, int(traj.duration_s * 1e9), 10_000_000, dtype=np.int64)
    truth = Trajectory("truth", ts_ns, traj.state(ts_ns * 1e-9).T_world_body)
    return sc, codes, traj, imu, truth


def _true_motion(traj, truth, stamps_ns, cam, imu=None) -> FrameMotion:
    """FrameMotion of the true states at `stamps_ns` (body rate: the true mean over the readout);
    with `imu`, the IMU's within-readout motion (frame_motion's track)."""
    st = traj.state(stamps_ns * 1e-9)
    grid = np.linspace(0.0, cam.readout_s, 21)
    rate = np.mean([traj.state(stamps_ns * 1e-9 + g).omega_body for g in grid], axis=0)
    n = len(stamps_ns)
    small = np.tile(1e-10 * np.eye(3), (n, 1, 1))
    m = FrameMotion(stamps_ns, st.T_world_body, rate, st.v_world, st.a_world, small, np.ones(n, bool), small)
    if imu is not None:
        m.track = _ImuTrack(imu, truth)
        t0 = stamps_ns * 1e-9
        m.imu_rate = m.track.mean_rate(t0, t0 + cam.readout_s)
        m.omega_body = m.imu_rate.copy()  # noise-free IMU, no bias
    return m


def test_per_row_poses_from_the_imu_beat_a_constant_twist(accelerating_flight):
    """Within a 30 ms readout the body rate changes (a multirotor tilts as its acceleration
    changes): the IMU's samples place the last row's camera far closer than the best constant
    twist (the true mean rate, velocity and acceleration at the stamp)."""
    sc, _, traj, imu, truth = accelerating_flight
    cam = replace(sc.cameras["cam0"], line_delay_s=0.03 / 480)
    stamps = np.arange(200_000_000, int((traj.duration_s - 0.2) * 1e9), 50_000_000, dtype=np.int64)
    k = np.arange(len(stamps))
    dt = np.full(len(stamps), cam.readout_s)
    true_end = traj.state(stamps * 1e-9 + cam.readout_s).T_world_body
    errs = {}
    for name, m in (
        ("twist", _true_motion(traj, truth, stamps, cam)),
        ("imu", _true_motion(traj, truth, stamps, cam, imu)),
    ):
        T = _body_poses_at(m, k, dt)
        rot = np.linalg.norm(so3_log(np.einsum("nji,njk->nik", T[:, :3, :3], true_end[:, :3, :3])), axis=1)
        errs[name] = (rot.max(), np.linalg.norm(T[:, :3, 3] - true_end[:, :3, 3], axis=1).max())
    # measured, worst frame: constant twist 16 urad / 43 um, IMU 3.5 urad / 0.6 um
    assert errs["imu"][0] < 0.4 * errs["twist"][0] and errs["imu"][1] < 0.1 * errs["twist"][1]
    assert errs["imu"][0] < 1e-5 and errs["imu"][1] < 5e-6


def test_point_map_identity_leaves_refinement_unchanged(scene):
    sc, codes = scene
    cam = sc.cameras["cam0"]
    T0 = make_T(R_from_euler("z", 0.4), [3.2, 1.5, 1.4])
    img = render_view(cam, cam.T_world_cam(T0), codes, np.random.default_rng(5), RenderEffects())
    dets = detect_frame(img, "cam0", 0, cam)
    assert dets
    raw = [[(d.corners_raw_px, None) for d in dets]]
    plain = refine_frames([img], raw, cam)[0]
    seen = []

    def identity(image, code, points):
        seen.append((image.copy(), code.copy()))
        return points

    mapped = refine_frames([img], raw, cam, point_map=identity)[0]
    assert seen and np.all(seen[0][0] == 0) and set(seen[0][1].tolist()) == set(range(len(dets)))
    for a, b in zip(plain, mapped):
        assert (a is None) == (b is None)
        if a is not None and a.stage == 2:
            np.testing.assert_allclose(b.corners_px, a.corners_px, atol=1e-9)
            np.testing.assert_allclose(b.corner_cov_px2, a.corner_cov_px2, rtol=1e-6, atol=1e-12)


class _Frames:
    """A camera stream of rendered images (timestamps_ns, load_image)."""

    def __init__(self, stamps_ns, images):
        self.timestamps_ns = np.asarray(stamps_ns, dtype=np.int64)
        self.images = images

    def load_image(self, i):
        return self.images[i]


def test_refinement_at_the_stamp_beats_correcting_refined_corners(accelerating_flight):
    """Rendered rolling-shutter frames (30 ms readout, 2 m/s, turning), true motion: the floor
    codes refined with their edge points at the stamp are closer to the true stamp projection
    than the refined (sheared) corners moved to the stamp afterwards (`correct_frames`)."""
    sc, codes, traj, imu, truth = accelerating_flight
    world = sc.layout.world
    cam = replace(sc.cameras["cam0"], line_delay_s=0.03 / 480)
    stamps = np.arange(1_000_000_000, int((traj.duration_s - 0.5) * 1e9), 400_000_000, dtype=np.int64)

    def body_at(ts):
        return traj.state(np.atleast_1d(np.asarray(ts, float))).T_world_body

    images, frames = [], {}
    for ts in stamps.tolist():
        img = render_view(
            cam,
            rolling_shutter_poses(cam, body_at, ts * 1e-9),
            codes,
            None,
            RenderEffects(noise_sigma_dn=0.0),
        )
        images.append(img)
        frames[ts] = detect_frame(img, "cam0", ts, cam)
    motion = _true_motion(traj, truth, stamps, cam, imu)
    stream = _Frames(stamps, images)
    fixed, done = refine_at_stamp(frames, _image_reader({"cam0": stream}, "cam0"), cam, world, motion)
    moved, _ = correct_frames(frames, cam, world, motion)
    by_payload = {c.payload: c for c in codes}
    e_stamp, e_moved = [], []
    for ts in stamps.tolist():
        T_wc = cam.T_world_cam(body_at(ts * 1e-9)[0])
        for i, d in enumerate(frames[ts]):
            if (ts, i) not in done:
                continue
            truth_uv = project_code_corners(cam, T_wc, by_payload[d.payload])
            e_stamp.append(np.linalg.norm(fixed[ts][i].corners_px - truth_uv, axis=1))
            e_moved.append(np.linalg.norm(moved[ts][i].corners_px - truth_uv, axis=1))
    assert len(e_stamp) >= 10
    # measured: mean 0.007 px (BR 0.011) at the stamp against 0.044 px (BR 0.086) corrected afterwards
    assert np.mean(e_stamp) < 0.7 * np.mean(e_moved)
    assert np.mean(e_stamp) < 0.05


class _SomeUnreadable(_Frames):
    """_Frames whose image 1 is a stream's skipped frame (None) and image 2 fails to read."""

    def load_image(self, i):
        if i == 1:
            return None
        if i == 2:
            raise LogError("cam0/data/2.png: unreadable")
        return self.images[i]


def test_images_unreadable_at_the_stamp_refinement_are_named_and_counted(accelerating_flight):
    """Frames whose image does not read again at the stamp refinement keep their corners moved to
    the stamp (`correct_frames`), the other frames are still refined, and the run says how many
    by name (`rolling_shutter_images_unreadable`).  Before, one image that raised dropped the
    camera's whole refinement and the note said "0 code(s) refined" with no reason; one that gave
    None was left out silently."""
    sc, codes, traj, imu, _ = accelerating_flight
    world = sc.layout.world
    cam = replace(sc.cameras["cam0"], line_delay_s=0.03 / 480)
    stamps = np.arange(1_000_000_000, 3_400_000_000, 400_000_000, dtype=np.int64)
    images, dets = [], []
    for ts in stamps.tolist():
        view = rolling_shutter_poses(cam, lambda t: traj.state(np.atleast_1d(t)).T_world_body, ts * 1e-9)
        images.append(render_view(cam, view, codes, None, RenderEffects(noise_sigma_dn=0.0)))
        dets += detect_frame(images[-1], "cam0", ts, cam)
    det = DetectionResult(dets, {})
    _, good = correct_flight(det, {"cam0": cam}, world, imu, streams={"cam0": _Frames(stamps, images)})
    _, report = correct_flight(det, {"cam0": cam}, world, imu, streams={"cam0": _SomeUnreadable(stamps, images)})
    per_frame = {ts: len(ds) for ts, ds in det.by_frame("cam0").items()}
    assert per_frame[int(stamps[1])] and per_frame[int(stamps[2])]
    assert 0 < report.refined_at_stamp["cam0"] < good.refined_at_stamp["cam0"]
    assert report.unreadable_at_stamp == {"cam0": 2}
    assert "2 image(s) did not read again" in report.notes()[0]
    from fusion.pipeline import rolling_shutter_unreadable_warning

    warning = rolling_shutter_unreadable_warning(report)
    assert warning is not None and warning.name == "rolling_shutter_images_unreadable" and warning.count == 2
    assert good.unreadable_at_stamp == {} and rolling_shutter_unreadable_warning(good) is None


def test_motion_from_the_codes_refined_at_the_stamp_in_a_fast_turn(scene, monkeypatch):
    """Rendered frames of a 1.75 rad/s turn, 30 ms readout (corrections up to ~23 px): the motion
    taken again from the poses of the codes refined at the stamp (STAMP_MOTION_PASSES) leaves
    the corrected corners several times closer to the true stamp projection than the motion from
    the refined-then-moved corners' poses, worst where the correction is largest."""
    from fusion.qr import rolling_shutter as rs_module

    sc, codes = scene
    world = sc.layout.world
    cam = replace(sc.cameras["cam0"], line_delay_s=0.03 / 480)
    wps = [(2.0, 1.5, 1.4, 0.0), (2.8, 1.6, 1.4, 2.0)]  # a yaw turn while moving, peak 1.75 rad/s
    traj = KeyframeTrajectory(survey_keyframes(wps, speed_m_s=1.0 / 2.1875, yaw_rate_rad_s=0.8))
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(), np.random.default_rng(3), noise_free=True)

    def body_at(ts):
        return traj.state(np.atleast_1d(np.asarray(ts, float))).T_world_body

    stamps = np.arange(200_000_000, int((traj.duration_s - 0.2) * 1e9), 33_333_333, dtype=np.int64)
    rng = np.random.default_rng(1)
    images, dets = [], []
    for ts in stamps.tolist():
        view = rolling_shutter_poses(cam, body_at, ts * 1e-9)
        images.append(render_view(cam, view, codes, rng, RenderEffects(noise_sigma_dn=1.0)))
        dets += detect_frame(images[-1], "cam0", ts, cam)
    det = DetectionResult(dets, {})
    by_payload = {c.payload: c for c in codes}

    def errors(passes):
        monkeypatch.setattr(rs_module, "STAMP_MOTION_PASSES", passes)
        fixed, _ = correct_flight(det, {"cam0": cam}, world, imu, streams={"cam0": _Frames(stamps, images)})
        raw = det.by_frame("cam0")
        err, move = [], []
        for ts, ds in fixed.by_frame("cam0").items():
            T_wc = cam.T_world_cam(body_at(ts * 1e-9)[0])
            for d, d0 in zip(ds, raw[ts]):
                truth_uv = project_code_corners(cam, T_wc, by_payload[d.payload])
                err.append(np.mean(np.linalg.norm(d.corners_px - truth_uv, axis=1)))
                move.append(np.mean(np.linalg.norm(d.corners_px - d0.corners_px, axis=1)))
        return np.array(err), np.array(move)

    default = rs_module.STAMP_MOTION_PASSES
    assert default >= 1
    before, move = errors(0)
    after, _ = errors(default)
    large = move > 10.0
    assert large.sum() >= 4 and move.max() > 20.0
    # measured (2 passes): corrections over 10 px 0.097 -> 0.019 px, all codes 0.032 -> 0.013 px
    assert np.mean(after[large]) < 0.3 * np.mean(before[large])
    assert np.mean(after) < 0.6 * np.mean(before)
    assert np.mean(after[large]) < 0.03


def test_motion_at_the_flight_end_from_a_one_sided_window(accelerating_flight):
    """Stamps at and after the last pose (the fit window all on one side): with an IMU the
    velocity is a line through the positions less the IMU's motion (a quadratic extrapolated
    badly there), and frames past the last pose still get a motion."""
    sc, _, traj, imu, truth = accelerating_flight
    cam = replace(sc.cameras["cam0"], line_delay_s=0.02 / 480)
    n_keep = int(np.searchsorted(truth.timestamps_ns, 3_000_000_000))
    poses = Trajectory("pnp", truth.timestamps_ns[:n_keep:3], truth.T_world_body[:n_keep:3])
    stamps = np.array([poses.timestamps_ns[-1], poses.timestamps_ns[-1] + 50_000_000], dtype=np.int64)
    m = frame_motion(poses, stamps, cam, imu)
    assert np.all(m.valid)
    st = traj.state(stamps * 1e-9)
    assert np.max(np.linalg.norm(m.v_world - st.v_world, axis=1)) < 0.02  # m/s (speed ~1.5 m/s)
    assert np.max(np.linalg.norm(m.T_world_body[:, :3, 3] - st.p_world, axis=1)) < 0.002
    without = frame_motion(poses, stamps, cam)  # no IMU: no extrapolation
    assert not without.valid[1]


# ------------------------------------------------------------- the correction's scale error


def test_correction_scale_sigma_is_proportional_to_the_frames_mean_correction():
    """kappa = CORRECTION_SIGMA_PER_PX2 x the frame's mean corner displacement, so that the
    corners' error kappa m is CORRECTION_SIGMA_PER_PX2 m^2."""
    from fusion.qr.rolling_shutter import CORRECTION_SIGMA_PER_PX2, correction_scale_sigma

    rng = np.random.default_rng(3)
    c0 = rng.uniform(100, 400, (4, 2))
    d0 = QRDetection("cam0", 5, "x", c0, c0)
    moved = [replace(d0, corners_px=c0 + [6.0, 8.0]), replace(d0, corners_px=c0 + [0.0, 20.0])]
    kappa = correction_scale_sigma({5: [d0, d0], 7: [d0]}, {5: moved, 7: [d0]})
    assert kappa[5] == pytest.approx(CORRECTION_SIGMA_PER_PX2 * 15.0)  # mean of 10 and 20 px
    assert kappa[7] == 0.0


def test_scale_sigma_adds_a_rank_one_pose_covariance_along_the_motion(synthetic_flight):
    """The correction's scale error enters the pose covariance (PnP's estimate is unchanged),
    as kappa^2 G u u^T G^T: rank one, growing as kappa^2."""
    from fusion.qr.rolling_shutter import motion_pose_covariance

    det, cam, world, imu, _ = synthetic_flight
    frames = det.by_frame("cam0")
    fixed, _ = correct_flight(det, {"cam0": cam}, world, imu)

    traj, _ = pnp_trajectory(fixed.by_frame("cam0"), cam, world)
    stamps = np.array(sorted(frames), dtype=np.int64)[40:43]
    sub = {int(t): frames[int(t)] for t in stamps}
    motion = frame_motion(traj, stamps, cam, imu)
    base = motion_pose_covariance(sub, cam, world, motion)
    k1 = motion_pose_covariance(sub, cam, world, motion, scale_sigma={int(t): 0.01 for t in stamps})
    k2 = motion_pose_covariance(sub, cam, world, motion, scale_sigma={int(t): 0.02 for t in stamps})
    assert base
    for ts in base:
        add1, add2 = k1[ts] - base[ts], k2[ts] - base[ts]
        s = np.linalg.svd(add1, compute_uv=False)
        assert s[0] > 0 and s[1] < 1e-6 * s[0]
        np.testing.assert_allclose(add2, 4.0 * add1, rtol=1e-6, atol=1e-18)


# ---------------------------------------------------------------------------- front camera's load sightings


def test_motion_sighting_covariance_matches_a_monte_carlo_of_the_motion(scene):
    """The load sightings' camera-frame covariance from the motion's uncertainty (first order,
    central differences) against the spread of the sightings corrected with motions drawn from
    that uncertainty (400 seeded draws); and add_sighting_covariance adds it to the matching
    sightings only."""
    from fusion.qr.rolling_shutter import (
        _sightings_by_key,
        add_sighting_covariance,
        motion_sighting_covariance,
    )
    from fusion.types import LoadObservation

    sc, _ = scene
    world = sc.layout.world
    cam = replace(sc.cameras["cam1"], line_delay_s=0.03 / 480)
    loads = [c for c in sc.codes() if not c.is_floor]
    T0 = sc.trajectory.state(np.array([7.5])).T_world_body[0]
    v, w = np.array([1.5, 0.4, 0.1]), np.array([0.1, -0.2, 0.6])
    body_at = constant_twist(T0, v, w)
    rng = np.random.default_rng(12)
    dets = []
    for c in loads:
        uv = project_code_corners_rolling(cam, body_at, 0.0, c)
        if np.all(np.isfinite(uv)) and np.all(uv > 10) and np.all(uv < [cam.width - 10, cam.height - 10]):
            uv = uv + rng.normal(0.0, 0.01, uv.shape)
            dets.append(QRDetection("cam1", 0, c.payload, uv, uv.copy(), corner_cov_px2=0.05**2 * np.eye(8)))
    assert len(dets) >= 3
    S_w, S_v = np.diag([2e-4, 1e-4, 3e-4]), np.diag([4e-4, 1e-4, 2e-4])  # (rad/s)^2, (m/s)^2
    motion = FrameMotion(
        np.array([0]),
        T0[None] + 0.0,
        w[None],
        v[None],
        np.zeros((1, 3)),
        S_v[None],
        np.array([True]),
        S_w[None],
    )
    frames = {0: dets}
    added = motion_sighting_covariance(frames, cam, world, motion, 0.05)
    assert len(added) == len(dets)
    draws = {key: [] for key in added}
    for _ in range(400):
        m = replace(
            motion,
            omega_body=w[None] + rng.multivariate_normal(np.zeros(3), S_w),
            v_world=v[None] + rng.multivariate_normal(np.zeros(3), S_v),
        )
        for key, p in _sightings_by_key(frames, cam, world, m, 0.05).items():
            draws[key].append(p)
    for key, C in added.items():
        mc = np.cov(np.array(draws[key]).T)
        # the sampled covariance of 400 draws: its trace within ~10 % (chi2 spread), the largest
        # direction the same
        assert np.trace(mc) == pytest.approx(np.trace(C), rel=0.2), key
        u_mc, u = np.linalg.eigh(mc)[1][:, -1], np.linalg.eigh(C)[1][:, -1]
        assert abs(u_mc @ u) > 0.95, key
    assert max(np.trace(C) for C in added.values()) > 1e-8  # m^2: not negligible (0.1 mm)
    key = next(iter(added))
    obs = [
        LoadObservation(0, key[1], np.zeros(3), p_cam=np.zeros(3), cov_cam=np.eye(3) * 1e-6),
        LoadObservation(5, key[1], np.zeros(3), p_cam=np.zeros(3), cov_cam=np.eye(3) * 1e-6),
    ]
    out = add_sighting_covariance(obs, added)
    np.testing.assert_allclose(out[0].cov_cam, np.eye(3) * 1e-6 + added[key], rtol=1e-12)
    assert out[1] is obs[1]


@pytest.mark.parametrize("yaw_rad", [0.0, 0.4])
def test_load_codes_are_corrected_on_their_own_plane(scene, monkeypatch, yaw_rad):
    """The front camera (30 ms readout) climbing at 1 m/s, square to the shelf and turned 23 deg
    from it: a load code's corners were moved at the depth of its apparent size as read, which
    the readout stretches (~3 %: the correction ~1.5 % short, 0.3 mm per m/s on the sightings,
    read as a false 0.08 deg front pitch) and which a code turned away from the camera does not
    have at every corner (0.2-0.5 px off).  Placed on the plane of their moved corners'
    homography (`code_corner_points`, two passes), the corners are within 0.005 px of the
    stamp's projection, with exact motion and noise-free corners."""
    import fusion.qr.rolling_shutter as rs_module

    sc, _ = scene
    world = sc.layout.world
    cam = replace(sc.cameras["cam1"], line_delay_s=0.03 / 480)
    loads = [c for c in sc.codes() if not c.is_floor]
    T0 = sc.trajectory.state(np.array([7.5])).T_world_body[0].copy()
    T0[:3, :3] = so3_exp(np.array([0.0, 0.0, yaw_rad])) @ T0[:3, :3]
    v, w = np.array([0.3, 0.2, 1.0]), np.array([0.1, -0.2, 0.4])
    body_at = constant_twist(T0, v, w)
    dets, truth = [], []
    for c in loads:
        uv = project_code_corners_rolling(cam, body_at, 0.0, c)
        if np.all(np.isfinite(uv)) and np.all(uv > 10) and np.all(uv < [cam.width - 10, cam.height - 10]):
            dets.append(QRDetection("cam1", 0, c.payload, uv, uv.copy(), corner_cov_px2=0.05**2 * np.eye(8)))
            truth.append(project_code_corners(cam, cam.T_world_cam(T0), c))
    assert len(dets) >= 3
    small = np.eye(3)[None] * 1e-6
    motion = FrameMotion(
        np.array([0]), T0[None] + 0.0, w[None], v[None], np.zeros((1, 3)), small, np.array([True]), small
    )

    def worst_px() -> float:
        fixed, n = correct_frames({0: dets}, cam, world, motion)
        assert n == 1
        return max(float(np.abs(np.asarray(d.corners_px) - t).max()) for d, t in zip(fixed[0], truth))

    assert worst_px() < 0.005
    monkeypatch.setattr(rs_module, "LOAD_PLANE_PASSES", 0)  # at the depth of the size as read
    assert worst_px() > 0.1


def test_code_corner_points_recover_a_tilted_code_and_refuse_a_degenerate_one():
    """A 0.12 m code 1.3 m away, turned 40 deg and off the axis, behind a distorted lens: its
    corners from the homography of its projected corners within 1e-9 m; three coincident
    corners give NaN, not a point."""
    from fusion.qr.rolling_shutter import code_corner_points

    cam = CameraModel(640, 480, 550.0, 550.0, 320.0, 240.0, distortion=np.array([-0.12, 0.03, 0.0, 0.0]))
    side = 0.12
    R = so3_exp(np.array([0.2, 0.7, 0.3]))
    square = np.array([[0.0, 0.0, 0.0], [side, 0.0, 0.0], [side, side, 0.0], [0.0, side, 0.0]])
    truth = square @ R.T + np.array([0.25, -0.15, 1.3])
    uv = cam.project(truth)
    points = code_corner_points(cam, uv, np.full(4, side))
    np.testing.assert_allclose(points, truth, atol=1e-9)
    flipped = code_corner_points(cam, uv[::-1], np.full(4, side))  # the other winding
    np.testing.assert_allclose(flipped, truth[::-1], atol=1e-9)
    bad = uv.copy()
    bad[1:] = bad[0]
    both = code_corner_points(cam, np.vstack([bad, uv]), np.full(8, side))
    assert np.all(np.isnan(both[:4])) and np.allclose(both[4:], truth, atol=1e-9)


def test_add_readout_covariances_reaches_pnp_poses_and_front_sightings_with_their_shifts():
    """pipeline.add_readout_covariances: the floor pose covariance by the floor stamps, the
    front sightings' by (stamp, load), each shifted by its camera's applied time offset (the
    floor's clock-rate correction included); and the named warning for a front camera read out
    longer than RS_SIGHTINGS_WARN_READOUT_S."""
    from fusion import pipeline
    from fusion.estimate.timeoffset import CameraOffset, ClockDrift, OffsetSource, TimeOffsets
    from fusion.qr.rolling_shutter import RollingShutterReport
    from fusion.types import LoadObservation

    est = OffsetSource.ESTIMATED
    # the floor camera's stamps moved by 7 ns and by 1 % of their distance from 0 (100 -> 108),
    # the front camera's by -3 ns
    rate = ClockDrift(0.01, 1e-4, 0, 1.0, applied=True)
    offsets = TimeOffsets(
        {
            "cam0": CameraOffset("cam0", 7e-9, 1e-9, est, 0.0, 7e-9, drift=rate),
            "cam1": CameraOffset("cam1", -3e-9, 1e-9, est, 0.0, -3e-9),
        }
    )

    C_pose, C_sight = np.eye(6) * 1e-6, np.eye(3) * 1e-8
    report = RollingShutterReport(
        readout_s={"cam0": 0.04, "cam1": 0.04},
        pose_cov_added={100: C_pose},
        sighting_cov_added={"cam1": {(200, "L1"): C_sight}},
    )
    traj = Trajectory(
        "pnp", np.array([108, 207], dtype=np.int64), np.tile(np.eye(4), (2, 1, 1)), np.zeros((2, 6, 6))
    )
    obs = [
        LoadObservation(197, "L1", np.zeros(3), p_cam=np.ones(3), cov_cam=np.zeros((3, 3))),
        LoadObservation(197, "L2", np.zeros(3), p_cam=np.ones(3), cov_cam=np.zeros((3, 3))),
        LoadObservation(200, "L1", np.zeros(3), p_cam=np.ones(3), cov_cam=np.zeros((3, 3))),
    ]
    loc = pipeline.LocalizeResult({"pnp": traj}, {}, {}, {}, camera_frame_observations=obs)
    pipeline.add_readout_covariances(loc, report, offsets)
    np.testing.assert_array_equal(loc.trajectories["pnp"].covariances, [C_pose, np.zeros((6, 6))])
    assert [float(o.cov_cam[0, 0]) for o in loc.camera_frame_observations] == [1e-8, 0.0, 0.0]
    warning = pipeline.rolling_shutter_sightings_warning(report)
    assert warning is not None and warning.name == "rolling_shutter_load_sightings" and warning.count == 1
    short = replace(report, readout_s={"cam0": 0.01, "cam1": 0.01})
    assert pipeline.rolling_shutter_sightings_warning(short) is None


@pytest.mark.parametrize("centre_px", [(320.0, 240.0), (560.0, 400.0), (80.0, 60.0)])
def test_size_depth_is_right_across_the_image_with_a_distorted_lens(centre_px):
    """A 0.15 m code facing the camera at 1.08 m: its depth from the undistorted edge within
    0.3 % anywhere in the image; the distorted-px edge (f side / edge) reads it too far near the
    border (barrel distortion shrinks the code there)."""
    from fusion.qr.rolling_shutter import size_depths

    cam = CameraModel(640, 480, 550.0, 550.0, 320.0, 240.0, distortion=np.array([-0.12, 0.03, 0.0, 0.0]))
    z, side = 1.08, 0.15
    centre = np.array([(centre_px[0] - cam.cu) / cam.fu * z, (centre_px[1] - cam.cv) / cam.fv * z, z])
    half = side / 2.0
    corners = centre + np.array(
        [[-half, -half, 0.0], [half, -half, 0.0], [half, half, 0.0], [-half, half, 0.0]]
    )
    uv = cam.project(corners)
    f = 0.5 * (cam.fu + cam.fv)
    assert size_depths(cam, uv, np.full(4, side)) == pytest.approx(np.full(4, z), rel=3e-3)
    edge_px = float(np.mean(np.linalg.norm(uv - np.roll(uv, 1, axis=0), axis=1)))
    if centre_px != (320.0, 240.0):
        assert f * side / edge_px > z * 1.01  # the old estimate near the border


def test_velocity_at_the_edges_of_a_pose_gap_takes_the_attitude_from_the_gyro(
    accelerating_flight, monkeypatch
):
    """A 1 s gap in the poses (a floor blackout) while the drone turns: the frames near its
    edges fit their velocity on one side, through the positions less the IMU's motion, whose
    world acceleration needs the attitude inside the gap.  From the gyro (anchored at the
    nearest pose) it is close to the truth; the slerp between the poses either side tilted the
    acceleration and put the realism bench's front-camera load sightings 10-22 sigma off
    (BENCHMARKS.md, rs17)."""
    sc, _, traj, imu, truth = accelerating_flight
    cam = replace(sc.cameras["cam0"], line_delay_s=0.02 / 480)
    t = truth.timestamps_ns
    keep = np.flatnonzero(((t < 2_000_000_000) | (t > 3_000_000_000)) & (t % 30_000_000 == 0))
    poses = Trajectory("pnp", t[keep], truth.T_world_body[keep])
    stamps = np.array(
        [2_060_000_000, 2_150_000_000, 2_240_000_000, 2_760_000_000, 2_850_000_000, 2_940_000_000]
    )
    v_true = traj.state(stamps * 1e-9).v_world

    def worst(m) -> float:
        assert np.all(m.valid)
        return float(np.max(np.linalg.norm(m.v_world - v_true, axis=1)))

    gyro = worst(frame_motion(poses, stamps, cam, imu))
    monkeypatch.setattr("fusion.qr.rolling_shutter.ATTITUDE_GAP_FRAMES", np.inf)
    slerp = worst(frame_motion(poses, stamps, cam, imu))
    # measured: gyro 0.12 mm/s, slerp 119 mm/s (worst of the six frames)
    assert gyro < 0.002  # m/s
    assert slerp > 20 * gyro


def test_a_one_sided_window_takes_the_accelerometer_bias_from_the_two_sided_fits(accelerating_flight):
    """An accelerometer bias the IMU track keeps (its world acceleration, 0.1 m/s^2 here): the
    two-sided fits' quadratic term takes it up; a one-sided window's line left it out and its
    velocity erred by the bias times the window's mean distance from the stamp (realism bench
    seed 0: 27-40 mm/s at a floor blackout's edges, BENCHMARKS.md, rs17).  Now the line is
    fitted less the nearest two-sided fits' quadratic term, and its spread widens the sigma."""
    sc, _, traj, imu, truth = accelerating_flight
    cam = replace(sc.cameras["cam0"], line_delay_s=0.02 / 480)
    biased = replace(imu, accel_m_s2=imu.accel_m_s2 + np.array([0.1, -0.06, 0.0]))
    n_keep = int(np.searchsorted(truth.timestamps_ns, 3_000_000_000))
    poses = Trajectory("pnp", truth.timestamps_ns[:n_keep:3], truth.T_world_body[:n_keep:3])
    last = int(poses.timestamps_ns[-1])
    stamps = np.arange(last - 1_000_000_000, last + 100_000_000, 50_000_000, dtype=np.int64)
    m = frame_motion(poses, stamps, cam, biased)
    assert np.all(m.valid)
    err = np.linalg.norm(m.v_world - traj.state(stamps * 1e-9).v_world, axis=1)
    # measured: one-sided frames 1.4-4.8 mm/s at sigma 3.2-3.4 mm/s (22-26 mm/s at 3 mm/s before)
    assert np.max(err) < 0.008  # m/s
    assert np.all(np.sqrt(m.v_cov[:, 0, 0]) >= 0.003)


def test_a_gimbaled_cameras_level_poses_get_the_bodys_tilt_from_the_imu(accelerating_flight):
    """A gimbaled floor camera's PnP poses are level (roll = pitch = 0), while the gyro and the
    accelerometer turn with the tilted body: the body's roll and pitch are restored from the IMU
    before the gyro's rate turns the stamp's attitude, so the gimbaled camera's last row sits
    where the truth puts it.  With the level attitude the body rate's roll / pitch parts leaked
    into the camera's yaw over the readout (the rendered gimbaled 20 ms flight: PnP / smoother /
    EKF NEES 24.6 / 33.2 / 32.7 with every health ok; 2.7 / 4.6 / 4.8 with the tilt restored)."""
    sc, _, traj, imu, truth = accelerating_flight
    cam = replace(sc.cameras["cam0"], line_delay_s=0.03 / 480, mount="gimbaled")
    t = truth.timestamps_ns
    keep = np.flatnonzero(t % 30_000_000 == 0)
    level = Trajectory("pnp", t[keep], level_frame(truth.T_world_body[keep]))
    stamps = np.arange(300_000_000, int((traj.duration_s - 0.6) * 1e9), 90_000_000, dtype=np.int64)
    true_body = traj.state(stamps * 1e-9).T_world_body
    tilt = np.linalg.norm(
        so3_log(np.einsum("nji,njk->nik", level_frame(true_body)[:, :3, :3], true_body[:, :3, :3])), axis=1
    )
    assert tilt.max() > 0.05  # the flight tilts (rad)
    k = np.arange(len(stamps))
    dt = np.full(len(stamps), cam.readout_s)
    true_end = cam.T_world_cam(traj.state(stamps * 1e-9 + cam.readout_s).T_world_body)
    true_stamp = cam.T_world_cam(true_body)
    true_turn = so3_log(np.einsum("nji,njk->nik", true_stamp[:, :3, :3], true_end[:, :3, :3]))

    def errors(level_poses: bool) -> tuple[float, float]:
        m = frame_motion(level, stamps, cam, imu, level_poses=level_poses)
        assert np.all(m.valid)
        att = so3_log(np.einsum("nji,njk->nik", true_body[:, :3, :3], m.T_world_body[:, :3, :3]))
        end = cam.T_world_cam(_body_poses_at(m, k, dt))
        stamp = cam.T_world_cam(m.T_world_body)
        turn = so3_log(np.einsum("nji,njk->nik", stamp[:, :3, :3], end[:, :3, :3]))
        return float(np.max(np.linalg.norm(att, axis=1))), float(
            np.max(np.linalg.norm(turn - true_turn, axis=1))
        )

    att_level, turn_level = errors(False)
    att_tilted, turn_tilted = errors(True)
    # measured (worst stamp): tilt 310 mrad; attitude error level 310 / restored 3.4 mrad; the
    # camera's turn over the 30 ms readout off by 1.92 / 0.045 mrad
    assert att_level > 0.8 * tilt.max()  # the level attitude misses the whole tilt
    assert att_tilted < 0.006  # rad
    assert turn_tilted < 0.1 * turn_level
