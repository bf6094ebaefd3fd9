"""Codes tracked through frames where they do not decode (fusion.qr.track): identity from the
prediction, gated; counted; written to and read from the detection cache."""

from __future__ import annotations

import numpy as np
import pytest

from fusion.camera import CameraModel
from fusion.geometry import make_T
from fusion.qr.detect import CameraStats, detect_frames
from fusion.qr.track import CodeTracker
from fusion.sim.render import PlacedCode, RenderEffects, project_code_corners, render_view
from fusion.types import QRDetection

CAMERA = CameraModel(640, 480, 520.0, 520.0, 320.0, 240.0)
CODE = PlacedCode("0/1/2", np.eye(4), 0.20)
R_DOWN = np.diag([1.0, -1.0, -1.0])
SPEED_M_S = 0.6
RATE_HZ = 30.0


def _frames(n: int, blur_from: int, seed: int = 0, occlude_from: int | None = None):
    """A down-looking camera 0.9 m above the code moving along x at SPEED_M_S: frames, stamps,
    true corners; frames from `blur_from` on have 10 px motion blur (the decoder fails)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        T = make_T(R_DOWN, [-0.15 + SPEED_M_S * k / RATE_HZ, 0.02, 0.9])
        blur = 10.0 if k >= blur_from else 0.0
        img = render_view(CAMERA, T, [CODE], rng, RenderEffects(1.5, 1.0, blur, 0.0))
        truth = project_code_corners(CAMERA, T, CODE)
        if occlude_from is not None and k >= occlude_from:
            img[:, :] = 128  # the code is gone: nothing may be tracked
        out.append((img, int(k * 1e9 / RATE_HZ), truth))
    return out


def test_code_tracked_through_motion_blur_with_its_identity_and_counted():
    frames = _frames(8, blur_from=2)
    tracker = CodeTracker(CAMERA)
    stats = CameraStats()
    per_frame = detect_frames(
        [f[0] for f in frames], "cam0", [f[1] for f in frames], CAMERA, stats=stats, tracker=tracker
    )
    assert [len(d) for d in per_frame[:2]] == [1, 1] and not any(
        d.tracked for d in per_frame[0] + per_frame[1]
    )
    tracked = [d for dets in per_frame[2:] for d in dets]
    assert len(tracked) == 6 and all(d.tracked and d.payload == CODE.payload for d in tracked)
    for d, (_, ts, truth) in zip(tracked, frames[2:]):
        assert d.timestamp_ns == ts
        assert np.max(np.linalg.norm(d.corners_px - truth, axis=1)) < 0.5
        assert d.corner_cov_px2 is not None
    assert stats.tracked == 6 and stats.frames_with_tracked_only == 6 and stats.detections == 8
    assert tracker.stats.tracked == 6


def test_nothing_is_tracked_where_the_code_is_gone():
    frames = _frames(5, blur_from=2, occlude_from=2)
    tracker = CodeTracker(CAMERA)
    per_frame = detect_frames([f[0] for f in frames], "cam0", [f[1] for f in frames], CAMERA, tracker=tracker)
    assert [len(d) for d in per_frame] == [1, 1, 0, 0, 0]
    assert tracker.stats.refine_failed >= 1 and tracker.stats.tracked == 0
    assert not tracker.tracks  # dropped after TRACK_MAX_MISSES frames without a sighting


def test_a_prediction_off_by_more_than_the_gate_gives_no_identity():
    """A code predicted 3 modules from where a (visible, undecodable) code lies: refinement may
    lock onto the real symbol, but the innovation gate refuses to name it."""
    ((img, ts, truth),) = _frames(1, blur_from=0)
    module = np.linalg.norm(truth[1] - truth[0]) / CODE.modules
    tracker = CodeTracker(CAMERA)
    pred = truth + [3.0 * module, 0.0]
    out = tracker.step(img, "cam0", ts, [], [], {"0/5/5": (pred, 1.0, CODE.modules)})
    assert out == []
    assert tracker.stats.gated + tracker.stats.refine_failed == 1
    ok = tracker.step(img, "cam0", ts + 1, [], [], {"0/1/2": (truth + 0.8, 1.5, CODE.modules)})
    assert len(ok) == 1 and ok[0].payload == "0/1/2" and ok[0].tracked


def test_no_track_where_a_decoded_code_lies():
    ((img, ts, truth),) = _frames(1, blur_from=0)
    decoded = QRDetection("cam0", ts, "0/1/2", truth, truth, 0.05, 0.0025 * np.eye(8))
    tracker = CodeTracker(CAMERA)
    out = tracker.step(img, "cam0", ts, [decoded], [21], {"0/9/9": (truth + 1.0, 1.5, 21)})
    assert out == [] and tracker.stats.ambiguous == 1


def test_tracked_flag_survives_the_detection_cache(tmp_path):
    from fusion.qr.detect import DetectionResult, read_cache, write_cache

    c = np.array([[10.0, 10.0], [50.0, 10.0], [50.0, 50.0], [10.0, 50.0]])
    dets = [
        QRDetection("cam0", 1, "0/1/2", c, c + 0.5, 0.05, 0.0025 * np.eye(8)),
        QRDetection("cam0", 2, "0/1/2", c + 1, c + 1.2, 0.05, 0.0025 * np.eye(8), tracked=True),
    ]
    stats = {"cam0": CameraStats(frames_total=2, detections=2, tracked=1)}
    write_cache(DetectionResult(dets, stats), tmp_path / "detections.csv", "f" * 64)
    back = read_cache(tmp_path / "detections.csv", "f" * 64)
    assert back is not None and [d.tracked for d in back.detections] == [False, True]
    assert back.stats["cam0"].tracked == 1


# ============================================================================ the track pass


def _flight_pose(t_s: float) -> np.ndarray:
    """Body pose of a drone 0.9 m above the floor moving along x at SPEED_M_S, yawing slowly."""
    from fusion.geometry import rot_z

    return make_T(rot_z(0.2 * t_s), [0.1 + SPEED_M_S * t_s, 0.05, 0.9])


class _Stream:
    """A floor-camera stream of rendered frames (what track_flight reads of a CameraStream)."""

    def __init__(self, camera, images, stamps):
        self.camera, self.images = camera, images
        self.timestamps_ns = np.asarray(stamps, dtype=np.int64)

    def __len__(self):
        return len(self.images)

    def load_image(self, i):
        return self.images[i]


def _track_flight_fixture(n: int = 14, blurred=range(3, 11), seed: int = 3, occluded=(), ecc: str = "L"):
    """A body-fixed down-looking floor camera (default mount) over floor codes on a 1 m grid;
    the frames in `blurred` carry 12 px of motion blur (undecodable), those in `occluded` the
    simulator's 10 % strip occluder over every code, from side k mod 4 in frame k (no finder
    left whole: undecodable).  Returns (log-like object, DetectionResult, first-pass PnP
    trajectory, true corners per frame {payload: (4, 2)})."""
    from types import SimpleNamespace

    from fusion.qr.detect import DetectionResult
    from fusion.qr.pnp import pnp_trajectory
    from fusion.sim.render import placed_floor_codes
    from fusion.world import World
    from tests.test_restamp import _strip

    camera = CameraModel(640, 480, 520.0, 520.0, 320.0, 240.0, T_body_cam=make_T(R_DOWN, np.zeros(3)))
    world = World(0.20, 0.5, 0.15, placement_sigma_m=0.0, placement_sigma_deg=0.0)  # 0.5 m apart: two in view
    codes = placed_floor_codes(np.array([[0, 0], [1, 0], [0, 1], [1, 1]]), 0.5, 0.20, ecc)
    rng = np.random.default_rng(seed)
    images, stamps, truths = [], [], []
    for k in range(n):
        T_body = _flight_pose(k / RATE_HZ)
        T_cam = camera.T_world_cam(T_body)
        blur = 12.0 if k in blurred else 0.0
        img = render_view(camera, T_cam, codes, rng, RenderEffects(1.5, 1.0, blur, 0.0))
        truth = {c.payload: project_code_corners(camera, T_cam, c) for c in codes}
        if k in occluded:
            for quad in truth.values():
                if np.all(np.isfinite(quad)):
                    img = _strip(img, quad, k % 4)
        images.append(img)
        stamps.append(int(round(k * 1e9 / RATE_HZ)))
        truths.append(truth)
    stats = CameraStats()
    per_frame = detect_frames(images, "cam0", stamps, camera, stats=stats)
    det = DetectionResult([d for ds in per_frame for d in ds], {"cam0": stats})
    traj, _ = pnp_trajectory(det.by_frame("cam0"), camera, world)
    log = SimpleNamespace(floor=_Stream(camera, images, stamps), world=world, cameras={"cam0": None})
    return log, det, traj, truths


def test_pose_predictor_interpolates_and_extrapolates_constant_motion_exactly():
    from fusion.qr.predict import MAX_EXTRAPOLATION_S, PosePredictor

    stamps = np.array([0, 2, 4, 10, 12]) * int(1e9 / RATE_HZ)
    poses = np.array([_flight_pose(t * 1e-9) for t in stamps])
    pred = PosePredictor(stamps, poses)
    for k in (0, 3, 6, 11, 14, 20):  # on a pose, between poses, after and before
        t = int(k * 1e9 / RATE_HZ)
        T, horizon = pred.predict(t)
        T_true = _flight_pose(t * 1e-9)
        assert np.allclose(T[:3, 3], T_true[:3, 3], atol=1e-9) and np.allclose(
            T[:3, :3], T_true[:3, :3], atol=1e-9
        )
        assert horizon == pytest.approx(np.min(np.abs(stamps - t)) * 1e-9)
    assert pred.predict(int(stamps[-1] + (MAX_EXTRAPOLATION_S + 0.01) * 1e9)) is None
    # a pose the pass found replaces extrapolation from older ones
    t_new = int(15 * 1e9 / RATE_HZ)
    T_off = _flight_pose(t_new * 1e-9) @ make_T(np.eye(3), [0.0, 0.0, 0.01])
    pred.add(t_new, T_off)
    T, horizon = pred.predict(int(16 * 1e9 / RATE_HZ))
    assert horizon == pytest.approx(1 / RATE_HZ) and abs(T[2, 3] - _flight_pose(16 / RATE_HZ)[2, 3]) > 0.005


def _accelerating_pose(t_s: float) -> np.ndarray:
    """A body accelerating along x while it pitches and yaws (what a multirotor does entering a
    cruise): the geodesic interpolation between two poses misses its rotation in between."""
    from fusion.geometry import R_from_euler

    R = R_from_euler("zyx", [0.3 * t_s, 0.25 * np.sin(2.0 * t_s), 0.1 * np.sin(3.0 * t_s)])
    return make_T(R, [0.4 * t_s**2, 0.2 * np.sin(2.0 * t_s), 1.2 + 0.1 * t_s])


def _imu_of(
    pose_fn, t_end_s: float, rate_hz: float = 400.0, accel_bias=(0.0, 0.0, 0.0), gyro_bias=(0.0, 0.0, 0.0)
):
    """IMU samples (body frame = IMU frame) of `pose_fn` by central differences: gyro
    Log(R(t - h)^T R(t + h)) / 2h, specific force R^T (p'' - g)."""
    from types import SimpleNamespace

    from fusion.geometry import so3_log

    h = 1e-4
    ts = np.arange(0.0, t_end_s + 1e-9, 1.0 / rate_hz)
    gyro, force = [], []
    for t in ts:
        Ta, Tb, Tc = pose_fn(t - h), pose_fn(t), pose_fn(t + h)
        gyro.append(so3_log(Ta[:3, :3].T @ Tc[:3, :3]) / (2 * h) + np.asarray(gyro_bias))
        acc = (Ta[:3, 3] - 2 * Tb[:3, 3] + Tc[:3, 3]) / h**2
        force.append(Tb[:3, :3].T @ (acc - np.array([0.0, 0.0, -9.81])) + np.asarray(accel_bias))
    return SimpleNamespace(
        timestamps_ns=np.round(ts * 1e9).astype(np.int64),
        gyro_rad_s=np.array(gyro),
        accel_m_s2=np.array(force),
        T_body_imu=np.eye(4),
    )


def _pose_error(T, T_true) -> tuple[float, float]:
    """(position error m, rotation error rad)."""
    from fusion.geometry import so3_log

    return float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])), float(
        np.linalg.norm(so3_log(T[:3, :3].T @ T_true[:3, :3]))
    )


def test_imu_bridge_meets_both_poses_and_follows_the_motion_between():
    from fusion.qr.predict import ImuBridge

    bridge = ImuBridge(_imu_of(_accelerating_pose, 3.0))
    t0, t1 = int(0.5e9), int(2.0e9)
    T0, T1 = _accelerating_pose(0.5), _accelerating_pose(2.0)
    for t in (t0, int(0.9e9), int(1.25e9), int(1.7e9), t1):
        T, v0, v1 = bridge.bridge(t0, T0, t1, T1, t)
        dp, dr = _pose_error(T, _accelerating_pose(t * 1e-9))
        assert dp < 1e-3 and dr < 1e-3, (t, dp, dr)
    # the geodesic interpolation is centimetres and degrees off in the middle
    from fusion.geometry import interpolate_pose

    dp, dr = _pose_error(interpolate_pose(T0, T1, 0.5), _accelerating_pose(1.25))
    assert dp > 0.05 and dr > 0.02
    # velocities at both ends: the true ones
    for t_s, v in ((0.5, v0), (2.0, v1)):
        v_true = (_accelerating_pose(t_s + 1e-4)[:3, 3] - _accelerating_pose(t_s - 1e-4)[:3, 3]) / 2e-4
        assert np.allclose(v, v_true, atol=2e-3)
    # forward and backward extrapolation from a pose and its velocity
    for t_from, v, t_to in ((2.0, v1, 2.4), (0.5, v0, 0.1)):
        T = bridge.extrapolate(int(t_from * 1e9), _accelerating_pose(t_from), v, int(t_to * 1e9))
        dp, dr = _pose_error(T, _accelerating_pose(t_to))
        assert dp < 2e-3 and dr < 1e-3, (t_to, dp, dr)


def test_imu_bridge_with_an_accelerometer_bias_stays_within_b_t2_over_8():
    from fusion.qr.predict import ImuBridge

    rng = np.random.default_rng(7)
    bias = rng.normal(0.0, 0.05, 3)
    bridge = ImuBridge(_imu_of(_accelerating_pose, 3.0, accel_bias=bias))
    t0, t1 = 0.5, 2.0
    worst = 0.0
    for t in np.linspace(t0, t1, 13):
        T, _, _ = bridge.bridge(
            int(t0 * 1e9), _accelerating_pose(t0), int(t1 * 1e9), _accelerating_pose(t1), int(t * 1e9)
        )
        worst = max(worst, _pose_error(T, _accelerating_pose(t))[0])
    bound = np.linalg.norm(bias) * (t1 - t0) ** 2 / 8
    assert 0.2 * bound < worst < 1.2 * bound


def test_pose_predictor_with_an_imu_bridges_gaps_the_geodesic_cannot():
    from fusion.qr.predict import MAX_EXTRAPOLATION_S, MAX_IMU_BRIDGE_S, ImuBridge, PosePredictor

    stamps = np.array([0.2, 0.3, 1.6, 1.7]) * 1e9
    stamps = stamps.astype(np.int64)
    poses = np.array([_accelerating_pose(t * 1e-9) for t in stamps])
    with_imu = PosePredictor(stamps, poses, ImuBridge(_imu_of(_accelerating_pose, 3.0)))
    without = PosePredictor(stamps, poses)
    for t_s in (0.5, 0.95, 1.4):  # inside the 1.3 s gap
        T, horizon = with_imu.predict(int(t_s * 1e9))
        dp, dr = _pose_error(T, _accelerating_pose(t_s))
        assert dp < 2e-3 and dr < 2e-3
        assert horizon == pytest.approx(min(t_s - 0.3, 1.6 - t_s))
        geo = without.predict(int(t_s * 1e9))  # none (gap over 1 s) or constant velocity: far off
        assert geo is None or _pose_error(geo[0], _accelerating_pose(t_s))[0] > 10 * dp
    for t_s in (1.7 + 0.8 * MAX_EXTRAPOLATION_S, 0.2 - 0.3 * MAX_EXTRAPOLATION_S):  # ahead, behind
        T, _ = with_imu.predict(int(t_s * 1e9))
        dp, dr = _pose_error(T, _accelerating_pose(t_s))
        assert dp < 5e-3 and dr < 2e-3, (t_s, dp, dr)
    # beyond the bridge's span: extrapolation only, and nothing beyond that
    far = PosePredictor(stamps[[0, 1]], poses[[0, 1]], ImuBridge(_imu_of(_accelerating_pose, 3.0)))
    assert far.predict(int((0.3 + MAX_EXTRAPOLATION_S + 0.05) * 1e9)) is None
    assert MAX_IMU_BRIDGE_S >= 1.3


def test_track_chunks_start_at_posed_frames_and_cover_the_flight():
    from fusion.qr import predict

    stamps = np.arange(1000) * int(1e9 / RATE_HZ)
    posed = stamps[(np.arange(1000) % 7 == 0) | (np.arange(1000) % 7 == 1)]
    chunks = predict.track_chunks(posed, stamps, len(stamps))
    assert chunks[0][0] == 0 and chunks[-1][1] == 1000
    assert all(a[1] == b[0] for a, b in zip(chunks, chunks[1:]))
    assert all(stamps[a] in set(posed) for a, _ in chunks[1:])
    assert all(b - a >= predict.TRACK_CHUNK_FRAMES for a, b in chunks[:-1])
    # no pose at all: one chunk
    assert predict.track_chunks(np.zeros(0, np.int64), stamps, len(stamps)) == [(0, 1000)]


def test_track_pass_names_blurred_floor_codes_from_the_predicted_pose_and_counts_them():
    from fusion.qr.predict import track_flight, without_tracked

    log, det, traj, truths = _track_flight_fixture()
    blurred_ts = {int(round(k * 1e9 / RATE_HZ)) for k in range(3, 11)}
    assert not blurred_ts & {d.timestamp_ns for d in det.detections}  # 12 px blur: none decode
    out, rep = track_flight(log, det, traj, 0.15)
    tracked = [d for d in out.detections if d.tracked]
    assert rep.skipped_reason == "" and rep.catalogue >= 2
    assert {d.timestamp_ns for d in tracked} >= blurred_ts  # every blurred frame followed
    for d in tracked:  # identity from the prediction: the code really there, corners on it
        k = int(round(d.timestamp_ns * RATE_HZ * 1e-9))
        truth = truths[k][d.payload]
        module_px = np.linalg.norm(truth[1] - truth[0]) / 21
        assert np.max(np.linalg.norm(d.corners_px - truth, axis=1)) < 0.5 * module_px
        assert d.corner_cov_px2 is not None and d.corner_sigma_px > 0
    st = out.stats["cam0"]
    assert st.tracked == len(tracked) == rep.stats.tracked
    assert st.frames_with_tracked_only == rep.frames_tracked_only == len(blurred_ts)
    assert st.frames_with_code == det.stats["cam0"].frames_with_code + len(blurred_ts)
    assert rep.poses_added == len(blurred_ts)
    assert all(rep.frame_outcomes[t] == "posed" for t in blurred_ts)
    assert rep.as_dict()["frames_posed"] == rep.outcome_counts()["posed"] >= len(blurred_ts)
    back = without_tracked(out)
    assert vars(back.stats["cam0"]) == vars(det.stats["cam0"]) and len(back.detections) == len(det.detections)


def test_track_pass_does_not_name_a_code_that_is_not_there():
    """The same flight with the blurred frames blank: the pose predicts codes in view, none is
    found, nothing is named."""
    from fusion.qr.predict import track_flight

    log, det, traj, _ = _track_flight_fixture()
    for k in range(3, 11):
        log.floor.images[k] = np.full_like(log.floor.images[k], 128)
    out, rep = track_flight(log, det, traj, 0.15)
    assert out is det and rep.stats.tracked == 0 and rep.stats.attempts > 0
    assert rep.stats.refine_failed + rep.stats.gated == rep.stats.attempts
    blank = [rep.frame_outcomes[int(round(k * 1e9 / RATE_HZ))] for k in range(3, 11)]
    assert set(blank) <= {"refine_failed", "gated"}


def test_track_pass_with_two_workers_equals_one(monkeypatch):
    from fusion.qr import predict

    log, det, traj, _ = _track_flight_fixture()
    monkeypatch.setattr(predict, "TRACK_CHUNK_FRAMES", 4)  # several chunks (cut in this process)
    one, rep1 = predict.track_flight(log, det, traj, 0.15, workers=1)
    two, rep2 = predict.track_flight(log, det, traj, 0.15, workers=2)
    assert rep1.chunks == rep2.chunks > 1
    a = [(d.timestamp_ns, d.payload, d.corners_px.tolist()) for d in one.detections]
    b = [(d.timestamp_ns, d.payload, d.corners_px.tolist()) for d in two.detections]
    assert a == b


def _blurred_sample_flight(tmp_path):
    """The committed sample flight with every third floor frame motion-blurred (a 12 px box
    along x) so that its codes no longer decode."""
    import shutil
    from pathlib import Path

    import cv2

    src = Path(__file__).resolve().parents[1] / "data" / "sample-flight"
    log = tmp_path / "log"
    shutil.copytree(src, log)
    paths = sorted((log / "mav0" / "cam0" / "data").glob("*.png"))
    for p in paths[1::3]:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(p), cv2.blur(img, (12, 1)))
    return log


def test_pipeline_track_stage_adds_counts_caches_and_can_be_turned_off(tmp_path):
    from fusion.pipeline import RunConfig, run
    from fusion.qr.detect import CACHE_NAME, read_cache

    log = _blurred_sample_flight(tmp_path)
    out = tmp_path / "out"
    on = run(log, out, RunConfig(workers=1, progress=False, force=True, track=True), until="localize")
    tracking = on.detection_stats["tracking"]
    assert tracking["tracker_tracked"] > 0 and tracking["skipped_reason"] == ""
    assert on.detection_stats["refinement"]["cam0"]["tracked"] == tracking["tracker_tracked"]
    assert any("track pass:" in n for n in on.notes)
    cached = read_cache(out / CACHE_NAME)
    assert cached is not None and sum(d.tracked for d in cached.detections) == tracking["tracker_tracked"]
    # run again: the tracked cache is reused as it is
    again = run(log, out, RunConfig(workers=1, progress=False, force=True, track=True), until="localize")
    assert again.detection_stats["cache"] == "reused" and "tracking" not in again.detection_stats
    assert again.detection_stats["refinement"]["cam0"]["tracked"] == tracking["tracker_tracked"]
    assert len(again.trajectories["pnp"]) == len(on.trajectories["pnp"])
    # --no-track: the tracked sightings are left out of the outputs and the cache
    no = run(log, out, RunConfig(workers=1, progress=False, force=True, track=False), until="localize")
    assert no.detection_stats["refinement"]["cam0"]["tracked"] == 0
    assert len(on.trajectories["pnp"]) == len(no.trajectories["pnp"]) + tracking["poses_added"]
    assert tracking["poses_added"] > 0
    assert len(on.trajectories["paper"]) == len(no.trajectories["paper"])  # decoded codes only
    back = read_cache(out / CACHE_NAME)
    assert back is not None and not any(d.tracked for d in back.detections)


@pytest.mark.parametrize("seed", [0, 1])
def test_locate_symbol_finds_a_blurred_code_several_px_from_its_prediction(seed):
    from fusion.qr.track import TRACK_LOCATE_MIN_NCC, locate_symbol

    rng = np.random.default_rng(seed)
    frames = _frames(4, blur_from=0, seed=seed)
    img, _, truth = frames[3]
    offset = rng.uniform(-6.0, 6.0, 2)
    found = locate_symbol(img, truth + offset, 21, 8.0)
    assert found is not None
    shift, ncc = found
    assert ncc > 0.6 and np.all(np.abs(shift + offset) <= 1.0)
    # nothing there: a weak best match; no room for the search window: None
    assert locate_symbol(np.full_like(img, 128), truth, 21, 8.0)[1] < TRACK_LOCATE_MIN_NCC
    noise = rng.integers(0, 255, img.shape).astype(np.uint8)
    assert locate_symbol(noise, truth, 21, 8.0)[1] < TRACK_LOCATE_MIN_NCC
    assert locate_symbol(img, truth - truth.min(axis=0) + 2.0, 21, 8.0) is None


def test_function_pattern_template_has_the_finders_separators_and_timing():
    from fusion.qr.track import function_pattern_template

    g = function_pattern_template(25)
    assert g.shape == (27, 27)
    sym = g[1:-1, 1:-1]
    assert np.all(sym[0, :7] == 0) and np.all(sym[1, 1:6] == 1) and np.all(sym[2:5, 2:5] == 0)
    assert np.all(sym[7, :8] == 1) and np.all(sym[:8, 17] == 1)  # separators
    assert list(sym[6, 8:17]) == [0, 1, 0, 1, 0, 1, 0, 1, 0]  # timing: dark at even indices
    assert np.isnan(sym[20, 20]) and np.all(g[0] == 1)  # data unknown, quiet zone light


def test_track_pass_drops_tracked_codes_whose_pose_disagrees_with_the_prediction(monkeypatch):
    """With a pose gate no PnP pose can meet (1 um), every blurred frame's tracked codes are
    dropped and counted as pose-gated, none is written; with the default gate they are kept."""
    from fusion.qr import predict

    log, det, traj, _ = _track_flight_fixture()
    monkeypatch.setattr(predict, "POSE_GATE_M", 1e-6)
    monkeypatch.setattr(predict, "POSE_GATE_M_PER_S", 0.0)
    out, rep = predict.track_flight(log, det, traj, 0.15)
    blurred_ts = [int(round(k * 1e9 / RATE_HZ)) for k in range(3, 11)]
    assert out is det and rep.stats.tracked == 0 and rep.stats.pose_gated >= len(blurred_ts)
    assert all(rep.frame_outcomes[t] == "pose_gated" for t in blurred_ts)
    assert rep.frames_tracked == rep.poses_added == 0


def test_track_pass_decodes_strip_occluded_codes_by_restamping_and_counts_them_apart():
    """Every frame strip-occluded (ECC H): nothing decodes, no first-pass pose; the pass decodes
    the codes with re-stamped finders (their identity from the decode), poses the frames, and
    counts them apart from the tracked ones."""
    from fusion.qr.pnp import pnp_trajectory
    from fusion.qr.predict import track_flight

    n = 8
    log, det, traj, truths = _track_flight_fixture(n=n, blurred=(), occluded=range(n), ecc="H")
    assert det.detections == [] and len(traj) == 0
    out, rep = track_flight(log, det, traj, 0.15)
    found = [d for d in out.detections if d.tracked]
    assert rep.restamped == len(rep.restamped_keys) > 0 and rep.frames_restamp_tried == n
    assert rep.restamp_poses > 0 and rep.skipped_reason == ""
    assert {(d.timestamp_ns, d.payload) for d in found} >= rep.restamped_keys
    for d in found:  # the right code, its corners on it
        truth = truths[int(round(d.timestamp_ns * RATE_HZ * 1e-9))][d.payload]
        module_px = np.linalg.norm(truth[1] - truth[0]) / 21
        assert np.max(np.linalg.norm(d.corners_px - truth, axis=1)) < 0.5 * module_px
    st = out.stats["cam0"]
    assert st.tracked == len(found) == rep.restamped + rep.stats.tracked
    assert st.frames_with_tracked_only == st.frames_with_code == len({d.timestamp_ns for d in found})
    posed, _ = pnp_trajectory(out.by_frame("cam0"), log.floor.camera, log.world)
    assert len(posed) >= rep.restamp_poses
    summary = rep.as_dict()
    assert summary["restamped"] == rep.restamped and "restamped_keys" not in summary
    assert summary["frames_with_restamped"] == len({t for t, _ in rep.restamped_keys})
    assert summary["frames_restamped"] == rep.outcome_counts()["restamped"] > 0


def test_match_square_reorders_a_matching_square_and_refuses_other_shapes():
    from fusion.qr.track import TRACK_GATE_MODULES, match_square

    pred = np.array([[100.0, 100.0], [184.0, 104.0], [180.0, 188.0], [96.0, 184.0]])  # 4 px / module
    module = 4.0
    square = np.roll(pred + [1.5, -1.0], 2, axis=0)  # another start corner, 1.8 px off
    got = match_square([square], pred, 21)
    assert got is not None and np.allclose(got, pred + [1.5, -1.0])
    far = pred + [TRACK_GATE_MODULES * module + 1.0, 0.0]  # the centre beyond the gate
    assert match_square([far], pred, 21) is None
    centre = pred.mean(axis=0)
    bigger = centre + 1.1 * (pred - centre)  # corners ~4 px (1 module) out: another shape
    assert match_square([bigger], pred, 21) is None
    assert match_square([], pred, 21) is None
    # the nearest of two matching squares
    near, other = pred + [0.5, 0.0], pred + [3.0, 0.0]
    assert np.allclose(match_square([other, near], pred, 21), near)


def test_pose_predictor_prefers_the_first_pass_bridge_and_uses_added_poses_on_both_sides():
    from fusion.qr.predict import ImuBridge, PosePredictor

    imu = ImuBridge(_imu_of(_accelerating_pose, 3.0))
    stamps = (np.array([0.2, 0.3, 1.6, 1.7]) * 1e9).astype(np.int64)
    poses = np.array([_accelerating_pose(t * 1e-9) for t in stamps])
    pred = PosePredictor(stamps, poses, imu)
    off = _accelerating_pose(0.9)
    off[:3, 3] += [0.05, 0.0, 0.0]  # a pose the pass found, 5 cm off
    pred.add(int(0.9e9), off)
    T, _ = pred.predict(int(1.0e9))  # bridged between the first pass's 0.3 and 1.6 s
    assert _pose_error(T, _accelerating_pose(1.0))[0] < 2e-3 and pred.last_kind == "bridge"
    assert pred.predict(int(stamps[1]))[1] == 0.0 and pred.last_kind == "own"
    # no first-pass pose within reach: the added ones, after t (backward sweep) or before it
    late = PosePredictor(stamps[2:], poses[2:], imu)
    assert late.predict(int(0.9e9)) is None  # 0.7 s before the first pose
    late.add(int(1.0e9), _accelerating_pose(1.0))
    T, horizon = late.predict(int(0.9e9))
    assert horizon == pytest.approx(0.1) and _pose_error(T, _accelerating_pose(0.9))[0] < 2e-3
    assert late.last_kind == "other"  # the pose gate's looser limit (predict.POSE_GATE_M)
    early = PosePredictor(stamps[:2], poses[:2], imu)
    assert early.predict(int(1.0e9)) is None
    early.add(int(0.7e9), _accelerating_pose(0.7))
    T, horizon = early.predict(int(1.0e9))
    assert horizon == pytest.approx(0.3) and _pose_error(T, _accelerating_pose(1.0))[0] < 5e-3


def test_track_pass_backward_sweep_poses_frames_before_the_first_decode(monkeypatch):
    """Blur over the first 8 frames, extrapolation limited to 0.1 s: the forward sweep reaches
    back 3 frames from the first decode, the backward sweep chains its poses back to frame 0."""
    from fusion.qr import predict

    monkeypatch.setattr(predict, "MAX_EXTRAPOLATION_S", 0.1)
    log, det, traj, truths = _track_flight_fixture(n=12, blurred=range(0, 8))
    blurred_ts = [int(round(k * 1e9 / RATE_HZ)) for k in range(0, 8)]
    assert not set(blurred_ts) & {d.timestamp_ns for d in det.detections}
    out, rep = predict.track_flight(log, det, traj, 0.15)
    assert rep.frames_backward > 0 and rep.poses_backward >= 4
    assert all(rep.frame_outcomes[t] == "posed" for t in blurred_ts)
    for d in out.detections:
        if d.tracked:  # the code really there, corners on it
            truth = truths[int(round(d.timestamp_ns * RATE_HZ * 1e-9))][d.payload]
            assert np.max(np.linalg.norm(d.corners_px - truth, axis=1)) < 1.0


def _noisy_poses(pose_fn, times_s, rng, sigma_m: float, sigma_rad: float):
    """[(t_ns, T_world_body)] of `pose_fn` with Gaussian position and rotation noise."""
    from fusion.geometry import so3_exp

    out = []
    for t in times_s:
        T = pose_fn(t).copy()
        T[:3, :3] = T[:3, :3] @ so3_exp(rng.normal(0.0, sigma_rad, 3))
        T[:3, 3] += rng.normal(0.0, sigma_m, 3)
        out.append((int(round(t * 1e9)), T))
    return out


def test_imu_fit_recovers_the_gyro_and_accelerometer_biases_from_exact_poses():
    """Exact poses over 1 s, an IMU with body-frame biases: the fit's biases are the true ones
    and its pose 0.5 s after the last one exact (the bias Jacobian and the integrals checked)."""
    from fusion.qr.predict import ImuBridge, ImuFit

    b_g, b_a = np.array([0.002, -0.001, 0.0015]), np.array([0.05, -0.03, 0.04])
    imu = ImuBridge(_imu_of(_accelerating_pose, 3.0, accel_bias=b_a, gyro_bias=b_g))
    poses = [(int(round(t * 1e9)), _accelerating_pose(t)) for t in np.arange(0.5, 1.5 + 1e-9, 1 / 30)]
    t = poses[-1][0] + int(0.5e9)
    fit = ImuFit(imu, [(tk, T, 0.002, 0.002) for tk, T in poses], t)
    assert np.allclose(fit.b_g, b_g, atol=1e-4) and np.allclose(fit.x[6:], b_a, atol=2e-3)
    dp, dr = _pose_error(fit.at(t), _accelerating_pose(t * 1e-9))
    assert dp < 2e-4 and dr < 1e-4, (dp, dr)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_imu_fit_extrapolates_better_than_the_imu_from_the_last_two_poses(seed):
    """Poses 2 mm / 0.1 deg noisy over 1 s, an IMU with the simulator's scale of biases: the
    fit's position 0.5 and 1 s after the last pose is within 2 / 4.5 cm and at least 1.5x nearer
    than the IMU extrapolated from the last two poses (the old prediction beyond a bridge)."""
    from fusion.qr.predict import ImuBridge, ImuFit

    rng = np.random.default_rng(seed)
    b_g, b_a = rng.normal(0.0, 0.002, 3), rng.normal(0.0, 0.05, 3)
    imu = ImuBridge(_imu_of(_accelerating_pose, 3.0, accel_bias=b_a, gyro_bias=b_g))
    poses = _noisy_poses(_accelerating_pose, np.arange(0.5, 1.5 + 1e-9, 1 / 30), rng, 0.002, 0.002)
    window = [(t, T, 0.002, 0.002) for t, T in poses]
    (t0, T0), (t1, T1) = poses[-4], poses[-1]
    v1 = imu.bridge(t0, T0, t1, T1, t1)[2]
    for ahead_s, limit_m in ((0.5, 0.02), (1.0, 0.045)):
        t = t1 + int(ahead_s * 1e9)
        truth = _accelerating_pose(t * 1e-9)
        dp, dr = _pose_error(ImuFit(imu, window, t).at(t), truth)
        old_dp = _pose_error(imu.extrapolate(t1, T1, v1, t), truth)[0]
        assert dp < limit_m and dr < np.radians(0.4), (ahead_s, dp, np.degrees(dr))
        assert old_dp > 1.5 * dp, (ahead_s, dp, old_dp)


def test_imu_fit_leaves_out_a_pose_far_off_the_others():
    from fusion.qr.predict import FIT_MIN_POSES, ImuBridge, ImuFit

    rng = np.random.default_rng(3)
    imu = ImuBridge(_imu_of(_accelerating_pose, 3.0))
    poses = _noisy_poses(_accelerating_pose, np.linspace(0.5, 1.0, 12), rng, 0.002, 0.002)
    poses[5][1][:3, 3] += [0.0, 0.3, 0.0]  # one pose 30 cm off
    t = int(1.4e9)
    window = [(tk, T, 0.002, 0.002) for tk, T in poses]
    fit = ImuFit(imu, window, t)
    assert fit.poses_used == len(poses) - 1 >= FIT_MIN_POSES
    clean = ImuFit(imu, window[:5] + window[6:], t)  # the same fit without it
    assert np.allclose(fit.at(t), clean.at(t), atol=1e-9)


def test_pose_predictor_uses_the_fit_beyond_the_extrapolation_and_weak_poses_in_it(monkeypatch):
    """Beyond MAX_EXTRAPOLATION_S from the last pose and up to FIT_MAX_EXTRAPOLATION_S: the fit
    (none without it); poses too uncertain to predict from alone (add_weak) carry it on."""
    from fusion.qr import predict
    from fusion.qr.predict import FIT_MAX_EXTRAPOLATION_S, MAX_EXTRAPOLATION_S, ImuBridge, PosePredictor

    rng = np.random.default_rng(4)
    imu = ImuBridge(_imu_of(_accelerating_pose, 3.0))
    poses = _noisy_poses(_accelerating_pose, np.arange(0.2, 0.7 + 1e-9, 1 / 30), rng, 0.002, 0.002)
    stamps = np.array([t for t, _ in poses])
    pred = PosePredictor(stamps, np.array([T for _, T in poses]), imu)
    t_far = int(stamps[-1] + 0.5 * (MAX_EXTRAPOLATION_S + FIT_MAX_EXTRAPOLATION_S) * 1e9)
    T, horizon = pred.predict(t_far)
    assert pred.last_kind == "fit" and pred.fits == 1
    assert horizon == pytest.approx((t_far - stamps[-1]) * 1e-9)
    assert _pose_error(T, _accelerating_pose(t_far * 1e-9))[0] < 0.03
    assert pred.predict(int(stamps[-1] + (FIT_MAX_EXTRAPOLATION_S + 0.05) * 1e9)) is None
    monkeypatch.setattr(predict, "USE_FIT", False)
    assert pred.predict(t_far) is None
    monkeypatch.setattr(predict, "USE_FIT", True)
    # weak poses (5 mm noise) every 1/30 s after the first pass's: predicted 1.5 s further on
    for t_w, T_w in _noisy_poses(_accelerating_pose, np.arange(0.75, 2.0, 1 / 30), rng, 0.005, 0.004):
        pred.add_weak(t_w, T_w, 0.005, 0.004)
    T, horizon = pred.predict(int(2.1e9))
    assert pred.last_kind == "fit" and horizon < 0.15  # from the last weak pose
    assert _pose_error(T, _accelerating_pose(2.1))[0] < 0.01


def test_refinement_only_takes_off_the_disagreement_the_tracker_added():
    from fusion.qr.predict import _refinement_only
    from fusion.qr.track import TRACK_AGREEMENT_SIGMA_PX
    from fusion.types import QRDetection

    pred = np.array([[100.0, 100.0], [142.0, 100.0], [142.0, 142.0], [100.0, 142.0]])
    corners = pred + [2.0, -1.0]
    base = np.diag(np.linspace(0.01, 0.08, 8))
    excess = 2.5 - TRACK_AGREEMENT_SIGMA_PX**2  # |e|^2 / 8 = 4 x 5 / 8 px^2
    d = QRDetection("cam0", 0, "p", corners, pred, 2.2, base + excess * np.eye(8), tracked=True)
    out = _refinement_only(d)
    assert np.allclose(out.corner_cov_px2, base)
    assert out.corner_sigma_px == pytest.approx(np.sqrt(np.mean(np.diag(base))))
    near = QRDetection("cam0", 0, "p", pred + 0.1, pred, 0.2, base, tracked=True)  # within 0.5 px
    assert np.allclose(_refinement_only(near).corner_cov_px2, base)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pose_predictor_bridges_a_gap_with_the_fit_over_both_sides(seed, monkeypatch):
    """First-pass poses (2 mm / 0.1 deg noisy) over 0.5 s on both sides of a 1 s gap, the last
    one before it 2 cm off (a single small code): ImuBridge, pinned at that end, is pulled off
    in the gap; the fit over both sides' poses (_predict_bridge_fit) leaves the outlier out and
    is nearer (kind "bridge_fit": the tight pose gate, no locator), and the bridge itself with
    USE_BRIDGE_FIT off."""
    from fusion.qr import predict
    from fusion.qr.predict import ImuBridge, PosePredictor

    rng = np.random.default_rng(seed)
    b_g, b_a = rng.normal(0.0, 0.002, 3), rng.normal(0.0, 0.05, 3)
    imu = ImuBridge(_imu_of(_accelerating_pose, 3.0, accel_bias=b_a, gyro_bias=b_g))
    times = np.concatenate([np.arange(0.2, 0.7 + 1e-9, 1 / 30), np.arange(1.7, 2.2 + 1e-9, 1 / 30)])
    poses = _noisy_poses(_accelerating_pose, times, rng, 0.002, 0.002)
    end = int(np.argmax(times > 1.0)) - 1  # the last pose before the gap
    poses[end][1][:3, 3] += [0.02, 0.0, 0.0]
    stamps = np.array([t for t, _ in poses])
    pred = PosePredictor(stamps, np.array([T for _, T in poses]), imu)
    t = int(1.2e9)
    truth = _accelerating_pose(1.2)
    T, horizon = pred.predict(t)
    assert pred.last_kind == "bridge_fit" and pred.bridge_fits == 1 and pred.fits == 0
    assert horizon == pytest.approx(1.2 - times[end])
    monkeypatch.setattr(predict, "USE_BRIDGE_FIT", False)
    T_bridge, horizon_bridge = pred.predict(t)
    assert pred.last_kind == "bridge" and pred.bridge_fits == 1 and horizon_bridge == horizon
    dp, dr = _pose_error(T, truth)
    dp_bridge = _pose_error(T_bridge, truth)[0]
    assert dp < 0.005 and dr < np.radians(0.2), (dp, np.degrees(dr))
    assert dp_bridge > 2.0 * dp, (dp, dp_bridge)


def test_tracker_starts_at_the_prediction_without_the_locator(monkeypatch):
    """A 10 px-blurred code predicted 0.3 px off, the locator answering with the finder's
    2-module alias: with locate=False it is not asked, refinement starts at the prediction and
    the corners are the code's; with it, the alias is the first start."""
    from fusion.qr import track

    ((img, ts, truth),) = _frames(1, blur_from=0)
    module = np.linalg.norm(truth[1] - truth[0]) / CODE.modules
    calls = []

    def alias(image, corners_px, modules, max_shift_px):
        calls.append(max_shift_px)
        return np.array([2.0 * module, 0.0]), 0.9

    monkeypatch.setattr(track, "locate_symbol", alias)
    pred = {CODE.payload: (truth + 0.3, 6.0, CODE.modules)}
    out = CodeTracker(CAMERA).step(img, "cam0", ts, [], [], pred, own_motion=False, locate=False)
    assert calls == [] and len(out) == 1
    assert np.max(np.linalg.norm(out[0].corners_px - truth, axis=1)) < 1.0
    tracker = CodeTracker(CAMERA)
    tracker.step(img, "cam0", ts, [], [], pred, own_motion=False)
    assert len(calls) == 1
