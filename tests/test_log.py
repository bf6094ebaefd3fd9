"""Flight-log reader / writer: round trip and every documented bad-log case."""
import shutil

import cv2
import numpy as np
import pytest

from fusion.camera import CameraModel
from fusion.conventions import R_BODY_FLOORCAM
from fusion.errors import LogError
from fusion.geometry import make_T, rot_z
from fusion.log import (
    FlightLogWriter,
    GroundTruth,
    ImuData,
    ImuNoise,
    VelocityData,
    read_flight,
)
from fusion.log.files import read_loads_csv, read_tum, write_loads_csv, write_tum
from fusion.types import LoadEstimate, LoadMap, Trajectory
from fusion.world import World


def write_small_log(root, n_frames=5, n_imu=50, seed=0):
    rng = np.random.default_rng(seed)
    cam = CameraModel(64, 48, 60.0, 60.0, 32.0, 24.0, np.array([-0.1, 0.01, 0, 0]),
                      make_T(R_BODY_FLOORCAM, [0, 0, -0.02]), rate_hz=10)
    t_cam = (np.arange(n_frames) * 1e8).astype(np.int64) + 1_000_000_000
    t_imu = (np.arange(n_imu) * 5e6).astype(np.int64) + 1_000_000_000
    # a plausible resting IMU (check_log flags units by magnitude and noise)
    imu = ImuData(t_imu, rng.normal(scale=1.4e-3, size=(n_imu, 3)),
                  np.array([0, 0, 9.81]) + rng.normal(scale=0.03, size=(n_imu, 3)),
                  ImuNoise(1e-4, 2e-5, 2e-3, 3e-3), np.eye(4), 200.0)
    q = rng.normal(size=(n_imu, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    gt = GroundTruth(t_imu, rng.normal(size=(n_imu, 3)), q, rng.normal(size=(n_imu, 3)),
                     rng.normal(size=(n_imu, 3)), rng.normal(size=(n_imu, 3)))
    vel = VelocityData(t_cam, rng.normal(size=(n_frames, 3)), 0.03)
    images = [rng.integers(0, 255, size=(48, 64), dtype=np.uint8) for _ in t_cam]
    with FlightLogWriter(root) as w:
        w.write_world(World(0.2, 1.0, 0.15, (0, 10), (0, 5)))
        w.add_camera("cam0", cam)
        w.add_camera("cam1", cam)
        for t, img in zip(t_cam, images):
            w.write_frame("cam0", t, img)
            w.write_frame("cam1", t, img)
        w.write_imu(imu)
        w.write_velocity(vel)
        w.write_groundtruth(gt)
        w.write_loads_groundtruth({"A-1": np.array([1.0, 2.0, 3.0]), "B,2": np.array([4, 5, 6.0])})
        w.write_blackouts([(1_100_000_000, 1_200_000_000, "shadow")])
    return dict(cam=cam, t_cam=t_cam, imu=imu, gt=gt, vel=vel, images=images)


def test_write_read_round_trip(tmp_path):
    root = tmp_path / "flight"
    ref = write_small_log(root)
    assert not (tmp_path / "flight.partial").exists()
    log = read_flight(root)
    assert np.array_equal(log.floor.timestamps_ns, ref["t_cam"])
    assert np.allclose(log.floor.camera.K, ref["cam"].K)
    assert np.allclose(log.floor.camera.T_body_cam, ref["cam"].T_body_cam)
    for frame, img in zip(log.floor.frames(), ref["images"]):
        assert np.array_equal(frame.image, img)
    assert np.array_equal(log.imu.timestamps_ns, ref["imu"].timestamps_ns)
    assert np.array_equal(log.imu.gyro_rad_s, ref["imu"].gyro_rad_s)
    assert np.array_equal(log.imu.accel_m_s2, ref["imu"].accel_m_s2)
    assert log.imu.noise == ref["imu"].noise
    assert np.array_equal(log.groundtruth.q_world_body_wxyz, ref["gt"].q_world_body_wxyz)
    assert np.array_equal(log.velocity.v_body_m_s, ref["vel"].v_body_m_s)
    assert log.velocity.noise_m_s == 0.03
    assert set(log.loads_groundtruth) == {"A-1", "B,2"}
    assert log.blackouts == [(1_100_000_000, 1_200_000_000, "shadow")]
    assert log.front is not None and log.world.bounds_x_m == (0.0, 10.0)


def test_writer_discards_on_error(tmp_path):
    root = tmp_path / "f"
    with pytest.raises(RuntimeError):
        with FlightLogWriter(root) as w:
            w.write_world(World())
            raise RuntimeError("interrupted")
    assert not root.exists() and not (tmp_path / "f.partial").exists()


@pytest.fixture
def log_dir(tmp_path):
    root = tmp_path / "flight"
    write_small_log(root)
    return root


def edit_line(path, lineno, new):
    lines = path.read_text().splitlines()
    lines[lineno - 1] = new
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("case, match", [
    ("cam_duplicate", r"cam0/data.csv:3: duplicate timestamp"),
    ("cam_backwards", r"cam0/data.csv:3: non-monotonic timestamp"),
    ("cam_outside", r"cam0/data.csv:2: file name .* points outside"),
    ("cam_short_row", r"cam0/data.csv:4: expected 2 fields, found 1"),
    ("cam_bad_ts", r"cam0/data.csv:2: timestamp .* is not an integer"),
    ("imu_nan", r"imu0/data.csv:5: NaN or infinite value"),
    ("imu_short", r"imu0/data.csv:6: expected 7 fields, found 4"),
    ("imu_text", r"imu0/data.csv:7: a value is not a number"),
    ("imu_missing_key", r"imu0/sensor.yaml: missing key 'gyroscope_noise_density'"),
    ("cam_missing_key", r"cam0/sensor.yaml: missing key 'intrinsics'"),
    ("gt_short", r"state_groundtruth_estimate0/data.csv:3: expected 17 fields"),
    ("no_world", r"world.yaml: file not found"),
    ("no_cam0", r"floor camera folder is missing"),
    ("loads_dup", r"loads_groundtruth.csv:3: duplicate load id"),
])
def test_bad_logs_name_file_and_line(log_dir, case, match):
    mav = log_dir / "mav0"
    cam_csv = mav / "cam0" / "data.csv"
    imu_csv = mav / "imu0" / "data.csv"
    cam_lines = cam_csv.read_text().splitlines()
    if case == "cam_duplicate":
        edit_line(cam_csv, 3, cam_lines[1])
    elif case == "cam_backwards":
        edit_line(cam_csv, 3, "999," + cam_lines[2].split(",")[1])
    elif case == "cam_outside":
        edit_line(cam_csv, 2, cam_lines[1].split(",")[0] + ",../../../world.yaml")
    elif case == "cam_short_row":
        edit_line(cam_csv, 4, cam_lines[3].split(",")[0])
    elif case == "cam_bad_ts":
        edit_line(cam_csv, 2, "1e9," + cam_lines[1].split(",")[1])
    elif case == "imu_nan":
        parts = imu_csv.read_text().splitlines()[4].split(",")
        edit_line(imu_csv, 5, ",".join(parts[:3] + ["nan"] + parts[4:]))
    elif case == "imu_short":
        edit_line(imu_csv, 6, ",".join(imu_csv.read_text().splitlines()[5].split(",")[:4]))
    elif case == "imu_text":
        parts = imu_csv.read_text().splitlines()[6].split(",")
        edit_line(imu_csv, 7, ",".join(parts[:6] + ["abc"]))
    elif case == "imu_missing_key":
        y = mav / "imu0" / "sensor.yaml"
        y.write_text("\n".join(l for l in y.read_text().splitlines()
                               if not l.startswith("gyroscope_noise_density")))
    elif case == "cam_missing_key":
        y = mav / "cam0" / "sensor.yaml"
        y.write_text("\n".join(l for l in y.read_text().splitlines() if not l.startswith("intrinsics")))
    elif case == "gt_short":
        p = mav / "state_groundtruth_estimate0" / "data.csv"
        edit_line(p, 3, "1,2,3")
    elif case == "no_world":
        (log_dir / "world.yaml").unlink()
    elif case == "no_cam0":
        shutil.rmtree(mav / "cam0")
    elif case == "loads_dup":
        p = log_dir / "loads_groundtruth.csv"
        lines = p.read_text().splitlines()
        edit_line(p, 3, lines[1])
    with pytest.raises(LogError, match=match):
        read_flight(log_dir)


def test_bad_frames_are_skipped_and_counted(log_dir):
    data = log_dir / "mav0" / "cam0" / "data"
    files = sorted(data.iterdir())
    files[1].write_bytes(b"\x89PNG\r\n\x1a\n corrupt")
    files[2].unlink()
    cv2.imwrite(str(files[3]), np.zeros((10, 10), np.uint8))
    log = read_flight(log_dir)
    frames = list(log.floor.frames())
    assert [f.image is None for f in frames] == [False, True, True, True, False]
    assert len(log.floor.skipped) == 3
    assert "data.csv:3: image" in log.floor.skipped[0] and "unreadable" in log.floor.skipped[0]
    assert "missing" in log.floor.skipped[1]
    assert "10x10" in log.floor.skipped[2]


def test_tum_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    T = np.stack([make_T(rot_z(a), rng.normal(size=3)) for a in rng.uniform(-3, 3, 10)])
    ts = np.arange(10, dtype=np.int64) * 33_333_333 + 1_234_567_890_123
    write_tum(tmp_path / "t.tum", Trajectory("x", ts, T))
    back = read_tum(tmp_path / "t.tum")
    assert np.array_equal(back.timestamps_ns, ts)
    assert np.allclose(back.T_world_body, T, atol=1e-8)
    (tmp_path / "bad.tum").write_text("1.0 2 3\n")
    with pytest.raises(LogError, match="bad.tum:1"):
        read_tum(tmp_path / "bad.tum")


def test_loads_csv_round_trip(tmp_path):
    m = LoadMap("pnp", [LoadEstimate("a,b", np.array([1.0, 2, 3]), np.diag([1e-4, 4e-4, 9e-4]), 7),
                        LoadEstimate("c", np.array([4.0, 5, 6]), None, 1)])
    write_loads_csv(tmp_path / "l.csv", m)
    back = read_loads_csv(tmp_path / "l.csv").by_id()
    assert np.allclose(back["a,b"].p_world, [1, 2, 3]) and back["a,b"].n_obs == 7
    assert np.allclose(np.sqrt(np.diag(back["a,b"].cov_world)), [0.01, 0.02, 0.03])
    assert back["c"].cov_world is None
