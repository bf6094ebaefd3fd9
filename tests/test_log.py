"""Flight-log reader / writer: round trip and every documented bad-log case."""

import re
import shutil

import cv2
import numpy as np
import pytest

from fusion.camera import CameraModel
from fusion.conventions import R_BODY_FLOORCAM
from fusion.errors import LogError, WorldError
from fusion.fileio import load_yaml
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


def write_small_log(root, n_frames=5, n_imu=81, seed=0):
    rng = np.random.default_rng(seed)
    cam = CameraModel(
        64,
        48,
        60.0,
        60.0,
        32.0,
        24.0,
        np.array([-0.1, 0.01, 0, 0]),
        make_T(R_BODY_FLOORCAM, [0, 0, -0.02]),
        rate_hz=10,
    )
    t_cam = (np.arange(n_frames) * 1e8).astype(np.int64) + 1_000_000_000
    t_imu = (np.arange(n_imu) * 5e6).astype(np.int64) + 1_000_000_000  # the frames' 1.0-1.4 s
    # a plausible resting IMU (check_log flags units by magnitude and noise)
    imu = ImuData(
        t_imu,
        rng.normal(scale=1.4e-3, size=(n_imu, 3)),
        np.array([0, 0, 9.81]) + rng.normal(scale=0.03, size=(n_imu, 3)),
        ImuNoise(1e-4, 2e-5, 2e-3, 3e-3),
        np.eye(4),
        200.0,
    )
    q = rng.normal(size=(n_imu, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[:, :1])
    gt = GroundTruth(
        t_imu,
        rng.normal(size=(n_imu, 3)),
        q,
        rng.normal(size=(n_imu, 3)),
        rng.normal(size=(n_imu, 3)),
        rng.normal(size=(n_imu, 3)),
    )
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


def test_csv_and_yaml_with_a_byte_order_mark_read_as_without(log_dir):
    """Spreadsheet programs save UTF-8 with a BOM: it is skipped, not read as the header's first
    character (which made the header a data row with a bad timestamp)."""
    before = read_flight(log_dir)
    mav = log_dir / "mav0"
    for path in (mav / "cam0" / "data.csv", mav / "imu0" / "data.csv", mav / "cam0" / "sensor.yaml"):
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
    after = read_flight(log_dir)
    assert np.array_equal(after.floor.timestamps_ns, before.floor.timestamps_ns)
    assert np.array_equal(after.imu.gyro_rad_s, before.imu.gyro_rad_s)
    assert after.floor.camera.fu == before.floor.camera.fu


def edit_line(path, lineno, new):
    lines = path.read_text().splitlines()
    lines[lineno - 1] = new
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize(
    "case, match",
    [
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
    ],
)
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
        y.write_text(
            "\n".join(l for l in y.read_text().splitlines() if not l.startswith("gyroscope_noise_density"))
        )
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


def test_12_bit_images_in_16_bit_pngs_are_read_at_full_contrast(log_dir):
    """Machine-vision cameras write Mono12 (0-4095) in 16-bit PNGs: OpenCV's 8-bit read kept
    the high byte, a near-black image (0-15), and the run said only "check focus and exposure"
    (thirty-first session's audit).  A 16-bit image is stretched to its brightest pixel, as the
    bag reader does with mono16; full-range 16-bit reads as the 8-bit original."""
    files = sorted((log_dir / "mav0" / "cam0" / "data").iterdir())
    before = [f.image for f in read_flight(log_dir).floor.frames()]
    cv2.imwrite(str(files[1]), before[1].astype(np.uint16) * 16)  # 12 bits
    cv2.imwrite(str(files[2]), before[2].astype(np.uint16) * 257)  # full 16-bit range
    assert cv2.imread(str(files[1]), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    after = [f.image for f in read_flight(log_dir).floor.frames()]
    for k in (1, 2):
        assert after[k].dtype == np.uint8
        expected = np.round(before[k] * (255.0 / before[k].max())).astype(np.uint8)
        np.testing.assert_array_equal(after[k], expected)
    np.testing.assert_array_equal(after[0], before[0])


def test_symlink_loops_are_a_skipped_frame_or_an_error_naming_them(log_dir):
    """A symbolic link loop had raised RuntimeError ("Symlink loop", Python 3.11; OSError on 3.13)
    from Path.resolve(): an image that is one is skipped and counted like any unreadable image;
    a camera's data folder or a stream folder that is one is an error naming it."""
    mav = log_dir / "mav0"
    image = sorted((mav / "cam0" / "data").iterdir())[2]
    image.unlink()
    image.symlink_to(image.name)  # a -> a
    log = read_flight(log_dir)
    frames = list(log.floor.frames())
    assert [f.image is None for f in frames] == [False, False, True, False, False]
    (skipped,) = log.floor.skipped
    assert f"data.csv:4: image {image.name}" in skipped and "symbolic links" in skipped
    shutil.rmtree(mav / "cam1" / "data")
    (mav / "cam1" / "data").symlink_to("data")
    with pytest.raises(LogError) as e:
        read_flight(log_dir)
    assert str(e.value) == f"{mav / 'cam1' / 'data'}: cannot be opened (a symbolic link loop)"
    shutil.rmtree(mav / "cam1")
    (mav / "cam1").symlink_to("cam1")  # had read as a log without a front camera, silently
    with pytest.raises(LogError, match=r"mav0/cam1: is a symbolic link loop; expected the stream's folder"):
        read_flight(log_dir)
    (mav / "cam1").unlink()
    (mav / "cam1").write_text("")
    with pytest.raises(LogError, match=r"mav0/cam1: is not a folder"):
        read_flight(log_dir)


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_truncated_images_are_skipped_without_the_codec_printing(log_dir, ext, capfd):
    """A PNG cut short (no IEND) or a JPEG without its end marker is skipped and counted before
    the codec sees it: libpng printed `libpng error: Read Error` on stderr, libjpeg decoded the
    missing rows as grey."""
    data = log_dir / "mav0" / "cam0" / "data"
    files = sorted(data.iterdir())
    img = cv2.imread(str(files[1]), cv2.IMREAD_GRAYSCALE)
    ok, buf = cv2.imencode(ext, img)
    assert ok
    files[1].write_bytes(buf.tobytes()[: len(buf) * 2 // 3])
    capfd.readouterr()
    frames = list(read_flight(log_dir).floor.frames())
    assert [f.image is None for f in frames] == [False, True, False, False, False]
    assert "libpng" not in capfd.readouterr().err
    log = read_flight(log_dir)
    list(log.floor.frames())
    assert len(log.floor.skipped) == 1 and "data.csv:3: image" in log.floor.skipped[0]
    assert "truncated" in log.floor.skipped[0]


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
    m = LoadMap(
        "pnp",
        [
            LoadEstimate("a,b", np.array([1.0, 2, 3]), np.diag([1e-4, 4e-4, 9e-4]), 7),
            LoadEstimate("c", np.array([4.0, 5, 6]), None, 1),
        ],
    )
    write_loads_csv(tmp_path / "l.csv", m)
    back = read_loads_csv(tmp_path / "l.csv").by_id()
    assert np.allclose(back["a,b"].p_world, [1, 2, 3]) and back["a,b"].n_obs == 7
    assert np.allclose(np.sqrt(np.diag(back["a,b"].cov_world)), [0.01, 0.02, 0.03])
    assert back["c"].cov_world is None


# ---------------------------------------------------------------- trust: hostile and mistaken inputs


def _set_yaml_line(path, key, text):
    """Replace the line `key: ...` of a flat YAML file (or append it)."""
    lines = [l for l in path.read_text().splitlines() if not l.startswith(f"{key}:")]
    path.write_text("\n".join(lines + [f"{key}: {text}"]) + "\n")


def _rewrite_csv(path, fn):
    """Apply fn(t_ns (N,), values (N, M)) -> (t, values) to a numeric EuRoC CSV."""
    lines = path.read_text().splitlines()
    rows = np.array([[float(v) for v in l.split(",")] for l in lines[1:]])
    t = np.array([int(l.split(",")[0]) for l in lines[1:]], dtype=object)
    t2, vals = fn(t, rows[:, 1:])
    path.write_text(
        "\n".join([lines[0]] + [",".join([str(a)] + [repr(float(x)) for x in v]) for a, v in zip(t2, vals)])
        + "\n"
    )


def test_an_exponent_without_a_decimal_point_is_a_number(log_dir):
    """YAML 1.2 (yaml-cpp, ROS, Kalibr's tools) reads `2e-4` as a number; PyYAML's 1.1 resolver
    read it as a string and the noise density was refused.  A quoted one stays a string."""
    imu_yaml = log_dir / "mav0" / "imu0" / "sensor.yaml"
    _set_yaml_line(imu_yaml, "gyroscope_noise_density", "2e-4")
    _set_yaml_line(imu_yaml, "accelerometer_noise_density", "-3E-3")
    with pytest.raises(LogError, match="accelerometer_noise_density: must be positive"):
        read_flight(log_dir)
    _set_yaml_line(imu_yaml, "accelerometer_noise_density", "3E-3")
    noise = read_flight(log_dir).imu.noise
    assert (noise.gyroscope_noise_density, noise.accelerometer_noise_density) == (2e-4, 3e-3)
    _set_yaml_line(imu_yaml, "gyroscope_noise_density", "'2e-4'")
    with pytest.raises(LogError, match="gyroscope_noise_density: expected a number, got str"):
        read_flight(log_dir)


@pytest.mark.parametrize(
    "case, match",
    [
        ("ts_overflow", r"cam0/data.csv:3: timestamp 99999999999999999999 is too large"),
        ("ts_plus", r"imu0/data.csv:4: timestamp '\+1010000000' is not an integer"),
        (
            "gt_zero_quat",
            r"state_groundtruth_estimate0/data.csv:4: quaternion q_RS_wxyz "
            r"\(0, 0, 0, 0\) is not a rotation",
        ),
        ("world_side_bool", r"world.yaml: floor_qr.side_m: expected a number, got bool True"),
        ("world_unit_text", r"world.yaml: floor_qr.payload_unit_m: expected a number, got str"),
        ("world_side_cm", r"world.yaml: floor_qr.side_m is 20 m: a QR code's side is 0.01-2 m; .* metres"),
        ("world_bounds_reversed", r"world.yaml: bounds_m.x is \[10, 0\]: the minimum must come first"),
        ("cam_rate_text", r"cam0/sensor.yaml: rate_hz: expected a number, got str 'fast'"),
        ("cam_resolution_bool", r"cam0/sensor.yaml: resolution\[0\]: expected a number, got bool"),
        ("imu_rate_text", r"imu0/sensor.yaml: rate_hz: expected a number, got str 'fast'"),
        ("imu_noise_bool", r"imu0/sensor.yaml: gyroscope_noise_density: expected a number, got bool"),
        ("vel_noise_text", r"vel0/sensor.yaml: noise_m_s: expected a number"),
        ("vel_world_frame", r"vel0/sensor.yaml: frame 'world': the velocity must be in the body frame"),
        (
            "imu_microseconds",
            r"imu0/data.csv: timestamps advance 5000 per sample .* rate_hz 200: "
            r"they look like microseconds",
        ),
        ("cam_milliseconds", r"cam0/data.csv: timestamps advance 100 per sample .* like milliseconds"),
        ("accel_in_g", r"imu0/data.csv: the accelerometer's median magnitude is 1, .* look like g"),
    ],
)
def test_mistaken_inputs_name_file_and_field(log_dir, case, match):
    mav = log_dir / "mav0"
    cam_csv, imu_csv = mav / "cam0" / "data.csv", mav / "imu0" / "data.csv"
    gt_csv = mav / "state_groundtruth_estimate0" / "data.csv"
    world = log_dir / "world.yaml"
    if case == "ts_overflow":
        edit_line(cam_csv, 3, "99999999999999999999," + cam_csv.read_text().splitlines()[2].split(",")[1])
    elif case == "ts_plus":
        line = imu_csv.read_text().splitlines()[3]
        edit_line(imu_csv, 4, "+" + line)
    elif case == "gt_zero_quat":
        parts = gt_csv.read_text().splitlines()[3].split(",")
        edit_line(gt_csv, 4, ",".join(parts[:4] + ["0", "0", "0", "0"] + parts[8:]))
    elif case == "world_side_bool":
        world.write_text(world.read_text().replace("side_m: 0.2,", "side_m: true,", 1))
    elif case == "world_side_cm":
        world.write_text(world.read_text().replace("side_m: 0.2,", "side_m: 20,", 1))
    elif case == "world_unit_text":
        world.write_text(world.read_text().replace("payload_unit_m: 1.0", "payload_unit_m: '1'"))
    elif case == "world_bounds_reversed":
        world.write_text(world.read_text().replace("x: [0.0, 10.0]", "x: [10, 0]"))
    elif case == "cam_rate_text":
        _set_yaml_line(mav / "cam0" / "sensor.yaml", "rate_hz", "fast")
    elif case == "cam_resolution_bool":
        _set_yaml_line(mav / "cam0" / "sensor.yaml", "resolution", "[true, 48]")
    elif case == "imu_rate_text":
        _set_yaml_line(mav / "imu0" / "sensor.yaml", "rate_hz", "fast")
    elif case == "imu_noise_bool":
        _set_yaml_line(mav / "imu0" / "sensor.yaml", "gyroscope_noise_density", "yes")
    elif case == "vel_noise_text":
        (mav / "vel0" / "sensor.yaml").write_text("sensor_type: velocity\nnoise_m_s: small\n")
    elif case == "vel_world_frame":  # it was never read: fused as body-frame (third audit)
        (mav / "vel0" / "sensor.yaml").write_text("sensor_type: velocity\nframe: world\nnoise_m_s: 0.05\n")
    elif case == "imu_microseconds":
        _rewrite_csv(imu_csv, lambda t, v: ([x // 1000 for x in t], v))
    elif case == "cam_milliseconds":
        lines = cam_csv.read_text().splitlines()
        cam_csv.write_text(
            "\n".join(
                [lines[0]] + [f"{int(l.split(',')[0]) // 1_000_000},{l.split(',')[1]}" for l in lines[1:]]
            )
            + "\n"
        )
    elif case == "accel_in_g":
        _rewrite_csv(imu_csv, lambda t, v: (t, np.c_[v[:, :3], v[:, 3:] / 9.81]))
    with pytest.raises(LogError, match=match):
        read_flight(log_dir)


def _warning_names(log):
    return {w.name: w for w in log.warnings}


def test_duplicate_yaml_keys_are_an_error_naming_file_and_line(log_dir):
    """A new calibration pasted below the old one: PyYAML had kept the last, silently."""
    sensor = log_dir / "mav0" / "cam0" / "sensor.yaml"
    lines = sensor.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("intrinsics:")) + 1
    sensor.write_text("\n".join(lines) + "\nintrinsics: [600.0, 600.0, 320.0, 240.0]\n")
    with pytest.raises(LogError) as e:
        read_flight(log_dir)
    assert str(e.value) == (
        f"{sensor}:{len(lines) + 1}: not valid YAML (key 'intrinsics' given twice (first on line {first}): "
        "which one holds?)"
    )
    world = log_dir / "world.yaml"
    world.write_text(world.read_text() + "floor_qr: {side_m: 0.3}\n")
    with pytest.raises(WorldError, match=r"world.yaml:\d+: not valid YAML \(key 'floor_qr' given twice"):
        World.load(world)
    # YAML merge keys may be overridden, as they intend
    merged = log_dir / "merged.yaml"
    merged.write_text("base: &b {side_m: 0.2}\nfloor_qr:\n  <<: *b\n  side_m: 0.25\n")
    assert load_yaml(merged)["floor_qr"] == {"side_m": 0.25}


@pytest.mark.parametrize(
    "text, match",
    [
        ("load_qr: {side_mm: 100}", r"unknown key load_qr.side_mm \(known load_qr: side_m, side_sigma_m\)"),
        (
            "floor_qr: {side_m: 0.2, payload_units_m: 0.5}",
            r"unknown key floor_qr.payload_units_m \(known floor_qr: side_m, payload_unit_m, ",
        ),
        (
            "floor_qr: {side_m: 0.2}\nbounds: {x: [0, 1], y: [0, 1]}",
            r"unknown key bounds \(known keys: floor_qr",
        ),
    ],
)
def test_unknown_world_yaml_keys_are_an_error(tmp_path, text, match):
    """A misspelt optional key had been ignored and its default used (a 10 cm label mapped as
    the 15 cm default: every load 1.5x too far along its rays, health ok)."""
    path = tmp_path / "world.yaml"
    path.write_text(("floor_qr: {side_m: 0.2}\n" if not text.startswith("floor_qr") else "") + text + "\n")
    with pytest.raises(WorldError, match=f"^{re.escape(str(path))}: {match}"):
        World.load(path)


def test_sensor_yaml_keys_of_kalibr_or_misspelt_are_errors_others_counted(log_dir):
    """Kalibr's `line_delay` (ours: line_delay_s) had silently meant a global shutter, a typo
    the default; a key other tools write (Kalibr's `rostopic`) is read past and counted."""
    sensor = log_dir / "mav0" / "cam0" / "sensor.yaml"
    text = sensor.read_text()
    for extra, match in (
        (
            "line_delay: 2.0e-05",
            r"cam0/sensor.yaml: key 'line_delay' is Kalibr's; a sensor.yaml says line_delay_s",
        ),
        ("distortion_coeffs: [0.1, 0, 0, 0]", r"key 'distortion_coeffs' is Kalibr's"),
        (
            "intrinsic_sigma: [1, 1, 1, 1]",
            r"unknown key 'intrinsic_sigma' \(did you mean 'intrinsics_sigma'\? known: ",
        ),
    ):
        sensor.write_text(text + extra + "\n")
        with pytest.raises(LogError, match=match):
            read_flight(log_dir)
    sensor.write_text(text + "rostopic: /cam0/image_raw\ncam_overlaps: [1]\n")
    imu_sensor = log_dir / "mav0" / "imu0" / "sensor.yaml"
    imu_text = imu_sensor.read_text()
    imu_sensor.write_text(imu_text + "gyroscope_noise_densty: 0.1\n")
    with pytest.raises(
        LogError, match=r"imu0/sensor.yaml: unknown key 'gyroscope_noise_densty' \(did you mean"
    ):
        read_flight(log_dir)
    imu_sensor.write_text(imu_text)
    (w,) = read_flight(log_dir).warnings
    assert (w.name, w.count) == ("sensor_yaml_unknown_keys", 2)
    assert w.message.startswith(f"{sensor}: key(s) rostopic, cam_overlaps not read (known: sensor_type, ")


def test_clean_log_has_no_warnings(log_dir):
    assert read_flight(log_dir).warnings == []


def test_one_row_ground_truth_is_a_named_warning_and_no_ground_truth(log_dir):
    """Ground truth is optional: one sample (nothing to interpolate) is dropped and warned,
    naming the file, at read time; the run had failed after finishing, naming no file."""
    gt_csv = log_dir / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    gt_csv.write_text("".join(gt_csv.read_text().splitlines(keepends=True)[:2]))
    log = read_flight(log_dir)
    assert log.groundtruth is None
    (w,) = log.warnings
    assert (w.name, w.count) == ("groundtruth_too_short", 1)
    assert (
        w.message
        == f"{gt_csv}: ground truth has 1 sample (2 or more needed): evaluation against ground truth skipped"
    )


@pytest.mark.parametrize(
    "case, name, match",
    [
        (
            "gyro_deg_s",
            "gyroscope_units",
            r"imu0/data.csv: white noise .*x the stated "
            r"gyroscope_noise_density: the gyro looks like deg/s",
        ),
        (
            "imu_10hz",
            "rate_mismatch",
            r"imu0: samples every 100 ms \(10 Hz\) but sensor.yaml says "
            r"rate_hz 200",
        ),
        ("imu_offset", "clock_offset", r"imu0 \(1001-1001.4 s\) does not overlap cam0"),
        ("gt_offset", "clock_offset", r"groundtruth \(1.6-2 s\) does not overlap cam0 \(1-1.4 s\)"),
        ("tbs_mm", "T_BS_translation", r"cam1/sensor.yaml: T_BS puts cam1 20 m from the body origin"),
        (
            "gt_quat_scaled",
            "groundtruth_quaternion_not_unit",
            r"81 quaternion\(s\) not of unit norm "
            r"\(first: line 2, norm 2\)",
        ),
        (
            "imu_gap",
            "imu_gaps",
            r"imu0/data.csv: 1 gap\(s\) over 50 ms between samples, 0.105 s in all; the longest "
            r"0.105 s after timestamp \d+ \(0.\d\d s into the IMU\): bridged by a random walk",
        ),
        (
            "imu_late",
            "imu_coverage",
            r"imu0/data.csv: the IMU \(1.2-1.4 s\) starts 0.2 s after the cameras' first frame "
            r"\(1-1.4 s\): 4 frame\(s\) outside it, where the fused poses rest on the cameras alone",
        ),
        (
            "imu_short",
            "imu_coverage",
            r"the IMU \(1.2-1.3 s\) starts 0.2 s after the cameras' first frame and ends 0.1 s "
            r"before their last \(1-1.4 s\): 6 frame",
        ),
        (
            "imu_frd",
            "imu_gravity_axis",
            r"imu0/data.csv: the median specific force is \([-+]0.00, [-+]0.00, -9.8\d\) m s\^-2 in the body "
            r"frame, 180 deg from its up axis",
        ),
        (
            "accel_clipped",
            "imu_saturated",
            r"imu0/data.csv: 10 sample value\(s\) sit at an axis' "
            r"extreme",
        ),
    ],
)
def test_unit_and_clock_mistakes_are_named_warnings(log_dir, case, name, match):
    _spoil(log_dir, case)
    log = read_flight(log_dir)
    found = _warning_names(log)
    assert name in found, log.warnings
    assert found[name].count >= 1
    import re

    assert re.search(match, found[name].message), found[name].message
    if case == "gt_quat_scaled":
        assert np.allclose(np.linalg.norm(log.groundtruth.q_world_body_wxyz, axis=1), 1.0)


def _spoil(log_dir, case):
    """One of the mistakes of test_unit_and_clock_mistakes_are_named_warnings, made in the log."""
    mav = log_dir / "mav0"
    imu_csv = mav / "imu0" / "data.csv"
    gt_csv = mav / "state_groundtruth_estimate0" / "data.csv"
    if case == "gyro_deg_s":
        _rewrite_csv(imu_csv, lambda t, v: (t, np.c_[np.degrees(v[:, :3]), v[:, 3:]]))
    elif case == "imu_10hz":
        _rewrite_csv(imu_csv, lambda t, v: (t[::20], v[::20]))
        lines = imu_csv.read_text().splitlines()  # keep the flight's span: 0.1 s steps
        imu_csv.write_text(
            "\n".join(
                [lines[0]]
                + [
                    f"{1_000_000_000 + 100_000_000 * i}," + l.split(",", 1)[1]
                    for i, l in enumerate(lines[1:])
                ]
            )
            + "\n"
        )
    elif case == "imu_offset":
        _rewrite_csv(imu_csv, lambda t, v: ([x + 1000 * 10**9 for x in t], v))
    elif case == "gt_offset":
        _rewrite_csv(gt_csv, lambda t, v: ([x + 600_000_000 for x in t], v))
    elif case == "tbs_mm":
        cam = CameraModel.load(mav / "cam1" / "sensor.yaml")
        cam.T_body_cam[:3, 3] *= 1000.0
        cam.save(mav / "cam1" / "sensor.yaml")
    elif case == "gt_quat_scaled":
        _rewrite_csv(gt_csv, lambda t, v: (t, np.c_[v[:, :3], 2 * v[:, 3:7], v[:, 7:]]))
    elif case == "imu_gap":
        _rewrite_csv(imu_csv, lambda t, v: (list(t[:20]) + list(t[40:]), np.r_[v[:20], v[40:]]))
    elif case == "imu_late":  # had no warning: imu_gaps looks between samples only
        _rewrite_csv(imu_csv, lambda t, v: (t[40:], v[40:]))
    elif case == "imu_short":
        _rewrite_csv(imu_csv, lambda t, v: (t[40:61], v[40:61]))
    elif case == "imu_frd":  # an FRD IMU (PX4) logged as FLU: y and z negated, T_BS identity
        _rewrite_csv(imu_csv, lambda t, v: (t, v * np.array([1, -1, -1, 1, -1, -1])))
    elif case == "accel_clipped":
        _rewrite_csv(imu_csv, lambda t, v: (t, np.c_[v[:, :5], np.minimum(v[:, 5], np.sort(v[:, 5])[-10])]))


def test_inspect_shows_the_readers_named_warnings(log_dir):
    """`fusion inspect` of an EuRoC folder lists the reader's named warnings as problems, as a
    run's summary does: it dropped them, so a log the run warns about looked clean."""
    from fusion.log.inspect import inspect_log

    assert not inspect_log(log_dir).problems
    gt_csv = log_dir / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    _rewrite_csv(gt_csv, lambda t, v: (t, np.c_[v[:, :3], 2 * v[:, 3:7], v[:, 7:]]))
    (problem,) = inspect_log(log_dir).problems
    assert problem.startswith("[groundtruth_quaternion_not_unit] x81: ") and str(gt_csv) in problem


@pytest.mark.parametrize("case, name", [("imu_10hz", "rate_mismatch"), ("accel_clipped", "imu_saturated")])
def test_inspect_shows_the_runs_plausibility_warnings(log_dir, case, name, capsys):
    """`fusion inspect` of an EuRoC folder lists the run's plausibility warnings about the log's
    data (euroc.check_log, as the reader gives them to the run), with the run's names and counts
    (a bag's: test_rosbag.test_inspect_shows_the_plausibility_warnings_a_run_gives_for_a_bag)."""
    from fusion.cli import main
    from fusion.log.inspect import inspect_log

    _spoil(log_dir, case)
    run = read_flight(log_dir).warnings
    assert name in {w.name for w in run}
    assert inspect_log(log_dir).problems == [str(w) for w in run]
    assert main(["inspect", str(log_dir)]) == 0
    out = capsys.readouterr().out
    assert all(f"problem: {w}" in out for w in run)


def test_image_header_is_checked_before_decoding(log_dir, monkeypatch):
    """A PNG whose header claims 100000x100000 px is skipped and counted like any bad image,
    without being decoded (OpenCV would raise on it)."""
    import struct
    import zlib

    files = sorted((log_dir / "mav0" / "cam0" / "data").iterdir())
    ok, buf = cv2.imencode(".png", np.zeros((48, 64), np.uint8))
    b = bytearray(buf.tobytes())
    b[16:24] = struct.pack(">II", 100_000, 100_000)
    b[29:33] = struct.pack(">I", zlib.crc32(bytes(b[12:29])) & 0xFFFFFFFF)
    files[2].write_bytes(bytes(b))
    from fusion.log import euroc

    log = read_flight(log_dir)
    decoded = []
    real = euroc.decode_image_bytes
    monkeypatch.setattr(euroc, "decode_image_bytes", lambda *a: decoded.append(1) or real(*a))
    frames = list(log.floor.frames())
    assert [f.image is None for f in frames] == [False, False, True, False, False]
    assert len(decoded) == 4
    assert "data.csv:4: image" in log.floor.skipped[0]
    assert "100000x100000 (header), sensor.yaml says 64x48" in log.floor.skipped[0]


def test_image_size_from_header_png_and_jpeg():
    from fusion.log.euroc import image_size_from_header

    img = np.zeros((37, 53), np.uint8)
    for ext in (".png", ".jpg"):
        ok, buf = cv2.imencode(ext, img)
        assert image_size_from_header(buf.tobytes()) == (53, 37)
    assert image_size_from_header(b"GIF89a....") is None


def test_load_ids_round_trip_spreadsheet_safe(tmp_path):
    from fusion.fileio import csv_safe, csv_unsafe

    assert csv_safe("\rx") == "'\rx" and csv_unsafe(csv_safe("\rx")) == "\rx"
    ids = ["=cmd|' /C calc'!A0", "+1", "-2", "@SUM(A1)", "\tx", "'quoted", "plain"]
    m = LoadMap("pnp", [LoadEstimate(i, np.array([1.0, 2, 3]), None, 1) for i in ids])
    write_loads_csv(tmp_path / "l.csv", m)
    import csv

    with open(tmp_path / "l.csv", newline="") as f:
        first = [row[0] for row in csv.reader(f)][1:]
    for cell in first:
        assert not cell.startswith(("=", "+", "-", "@", "\t", "\r"))
    assert "'=cmd|' /C calc'!A0" in first and "plain" in first and "''quoted" in first
    assert set(read_loads_csv(tmp_path / "l.csv").by_id()) == set(ids)
    root = tmp_path / "flight"
    with FlightLogWriter(root) as w:
        w.write_world(World())
        w.add_camera("cam0", CameraModel(64, 48, 60.0, 60.0, 32.0, 24.0))
        w.write_loads_groundtruth({i: np.array([1.0, 2, 3]) for i in ids})
    text = (root / "loads_groundtruth.csv").read_text()
    assert "\n=" not in text and "\n'=cmd" in text
