"""Video logs: lossless round trip, frame times (CSV, constant rate, ULog capture topic), PX4
ULog IMU, and the refusals (variable frame rate without times, no sensor_combined)."""

import shutil
import struct
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import yaml

from fusion.cli import build_parser
from fusion.errors import LogError
from fusion.log import LogOptions, euroc, open_flight
from fusion.log.inspect import inspect_log
from fusion.log.ulog import T_FLU_FRD
from fusion.log.video import write_video_flight

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"
N_FRAMES = 6


def short_flight(n_frames=N_FRAMES):
    f = euroc.read_flight(SAMPLE)
    f.cameras = {
        name: euroc.CameraStream(
            name, s.camera, s.timestamps_ns[:n_frames], s.paths[:n_frames], s.csv_lines[:n_frames]
        )
        for name, s in f.cameras.items()
    }
    return f


@pytest.fixture(scope="module")
def video_dir(tmp_path_factory):
    return write_video_flight(short_flight(), tmp_path_factory.mktemp("v") / "flight")


def test_ffv1_round_trip_is_pixel_exact(video_dir):
    ref = short_flight()
    got = open_flight(video_dir)
    assert sorted(got.cameras) == ["cam0", "cam1"]
    for name, s in ref.cameras.items():
        g = got.cameras[name]
        np.testing.assert_array_equal(g.timestamps_ns, s.timestamps_ns)
        assert g.camera.to_sensor_yaml()["intrinsics"] == s.camera.to_sensor_yaml()["intrinsics"]
        np.testing.assert_allclose(g.camera.T_body_cam, s.camera.T_body_cam, atol=1e-15)
        for i in (0, 4, 2, 3, N_FRAMES - 1):  # in and out of order
            np.testing.assert_array_equal(g.load_image(i), s.load_image(i))
    np.testing.assert_array_equal(got.imu.accel_m_s2, ref.imu.accel_m_s2)
    assert got.imu.noise == ref.imu.noise and got.world == ref.world
    rep = inspect_log(video_dir)
    assert rep.roles["cam0"] == "cam0" and "accel OK" in rep.imu_units


def _copy_without_times(video_dir, tmp_path):
    d = tmp_path / "v"
    shutil.copytree(video_dir, d)
    (d / "cam0.csv").unlink()
    (d / "cam1.mkv").unlink()
    (d / "cam1.csv").unlink()
    return d


def test_constant_rate_needs_a_start_time(video_dir, tmp_path):
    d = _copy_without_times(video_dir, tmp_path)
    with pytest.raises(LogError, match=r"cam0.mkv: no frame times file .*--video-start-ns"):
        open_flight(d)
    flight = open_flight(d, LogOptions(video_start_ns=5_000_000_000))
    # the container's rate (10 Hz, as written) from the given start
    np.testing.assert_array_equal(
        flight.floor.timestamps_ns, 5_000_000_000 + np.arange(N_FRAMES) * 100_000_000
    )
    flight = open_flight(d, LogOptions(video_start_ns=0, video_fps=20.0))
    assert flight.floor.timestamps_ns[1] == 50_000_000
    # a rate or start that is no rate or time: an error naming the video, not nonsense stamps
    for bad in (
        LogOptions(video_start_ns=0, video_fps=float("nan")),
        LogOptions(video_start_ns=0, video_fps=-30.0),
        LogOptions(video_start_ns=0, video_fps=0.0),
        LogOptions(video_start_ns=-5),
    ):
        with pytest.raises(LogError, match=r"cam0.mkv: video_(fps|start_ns) "):
            open_flight(d, bad)


@pytest.mark.parametrize(
    "flag, value",
    [
        ("--video-fps", "nan"),
        ("--video-fps", "-30"),
        ("--video-fps", "0"),
        ("--video-fps", "inf"),
        ("--video-start-ns", "-5"),
        ("--video-start-ns", "1_000"),
        ("--video-start-ns", "99999999999999999999"),
    ],
)
def test_video_rate_and_start_flags_refuse_nonsense(flag, value, capsys):
    """argparse, like every other numeric flag: exit 2, one line naming the flag."""
    with pytest.raises(SystemExit) as e:
        build_parser().parse_args(["inspect", "v.mkv", flag, value])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert flag in err and "Traceback" not in err
    args = build_parser().parse_args(["inspect", "v.mkv", "--video-fps", "29.97", "--video-start-ns", "0"])
    assert (args.video_fps, args.video_start_ns) == (29.97, 0)


def test_frame_times_shorter_than_video_use_the_first_frames(video_dir, tmp_path, caplog):
    d = tmp_path / "v"
    shutil.copytree(video_dir, d)
    lines = (d / "cam0.csv").read_text().splitlines()
    (d / "cam0.csv").write_text("\n".join(lines[:4]) + "\n")  # header + 3 times
    flight = open_flight(d)
    assert len(flight.floor) == 3 and "6 frames but 3 times" in caplog.text
    assert [(w.name, w.count) for w in flight.warnings if w.name == "frame_times_mismatch"] == [
        ("frame_times_mismatch", 3)
    ]
    (d / "cam0.csv").write_text(lines[0] + "\n" + lines[2] + "\n" + lines[1] + "\n")
    with pytest.raises(LogError, match=r"cam0.csv:3: non-monotonic timestamp"):
        open_flight(d)


def test_missing_imu_noise_calibration_is_a_counted_warning(video_dir, tmp_path):
    """Without imu.yaml the IMU noise is the defaults', and the run's warnings say so."""
    d = tmp_path / "v"
    shutil.copytree(video_dir, d)
    assert open_flight(d).imu.noise == short_flight().imu.noise
    assert not [w for w in open_flight(d).warnings if w.name == "imu_noise_default"]
    (d / "imu.yaml").unlink()
    flight = open_flight(d)
    assert [(w.name, w.count) for w in flight.warnings if w.name == "imu_noise_default"] == [
        ("imu_noise_default", 1)
    ]


def test_a_videos_plausibility_warnings_name_its_files(video_dir, tmp_path):
    """euroc.check_log's warnings about a video log name the file the stream came from (here
    imu.csv, clipped), not `<folder>/mav0/imu0/data.csv` as if it were an EuRoC folder."""
    d = tmp_path / "v"
    shutil.copytree(video_dir, d)
    assert not open_flight(d).warnings
    header, *rows = (d / "imu.csv").read_text().splitlines()
    values = np.array([[float(v) for v in r.split(",")[1:]] for r in rows])
    top = np.sort(values[:, 5])[-12]
    clipped = [r.rsplit(",", 1)[0] + f",{float(min(v, top))!r}" for r, v in zip(rows, values[:, 5])]
    (d / "imu.csv").write_text("\n".join([header, *clipped]) + "\n")
    (w,) = [w for w in open_flight(d).warnings if w.name == "imu_saturated"]
    assert w.count == 12 and w.message.startswith(f"{d / 'imu.csv'}: 12 sample value(s)")
    assert "mav0" not in w.message


def test_a_video_imu_slower_than_its_imu_yaml_says_is_a_rate_mismatch(video_dir, tmp_path):
    """imu.yaml's `update_rate` is checked against imu.csv's stamps as an EuRoC folder's
    sensor.yaml `rate_hz` is: `rate_mismatch` naming imu.csv and imu.yaml (it never fired for
    a video log: the check looked for `<folder>/mav0/imu0/sensor.yaml`)."""
    d = tmp_path / "v"
    shutil.copytree(video_dir, d)
    text = (d / "imu.yaml").read_text()
    assert "update_rate: 200.0" in text and not open_flight(d).warnings
    (d / "imu.yaml").write_text(text.replace("update_rate: 200.0", "update_rate: 400.0"))
    (w,) = [w for w in open_flight(d).warnings if w.name == "rate_mismatch"]
    assert w.count == 1
    said = f"samples every 5 ms (200 Hz) but {d / 'imu.yaml'} says update_rate 400"
    assert w.message == f"{d / 'imu.csv'}: {said}"


def _vfr_video(path, images, pts):
    import av

    with av.open(str(path), mode="w") as c:
        vs = c.add_stream("ffv1", rate=30)
        vs.width, vs.height, vs.pix_fmt = images[0].shape[1], images[0].shape[0], "gray"
        vs.codec_context.time_base = Fraction(1, 30)
        for img, p in zip(images, pts):
            f = av.VideoFrame.from_ndarray(img, format="gray")
            f.pts = p
            f.time_base = Fraction(1, 30)
            for pkt in vs.encode(f):
                c.mux(pkt)
        for pkt in vs.encode():
            c.mux(pkt)


def test_variable_frame_rate_without_times_is_refused(video_dir, tmp_path):
    d = _copy_without_times(video_dir, tmp_path)
    rng = np.random.default_rng(1)
    imgs = [rng.integers(0, 255, (480, 640), dtype=np.uint8) for _ in range(5)]
    _vfr_video(d / "cam0.mkv", imgs, [0, 1, 3, 4, 8])
    with pytest.raises(LogError, match=r"cam0.mkv: variable frame rate .*--frame-times"):
        open_flight(d, LogOptions(video_start_ns=0))
    # with a frame times file it reads, frames in order
    (d / "cam0.csv").write_text("#timestamp [ns]\n" + "".join(f"{k * 1000}\n" for k in range(5)))
    flight = open_flight(d)
    np.testing.assert_array_equal(flight.floor.load_image(3), imgs[3])
    np.testing.assert_array_equal(flight.floor.load_image(1), imgs[1])


def test_truncated_video_reads_up_to_the_damage(video_dir, tmp_path):
    d = tmp_path / "v"
    shutil.copytree(video_dir, d)
    data = (d / "cam0.mkv").read_bytes()
    (d / "cam0.mkv").write_bytes(data[: int(len(data) * 0.6)])
    flight = open_flight(d)
    n = len(flight.floor)
    assert 0 < n < N_FRAMES
    ref = short_flight()
    for i in range(n):
        img = flight.floor.load_image(i)
        if img is not None:  # the last, cut frame may be reported unreadable
            np.testing.assert_array_equal(img, ref.floor.load_image(i))
    assert len(flight.floor.skipped) <= 1
    if n < N_FRAMES - 1:  # demuxing stopped at the damage: a named warning in the log's list
        assert [w.name for w in flight.warnings if w.name == "video_truncated"] == ["video_truncated"]
    assert not [w for w in open_flight(video_dir).warnings if w.name == "video_truncated"]


def test_cut_mp4_is_refused_with_the_reason(video_dir, tmp_path):
    d = tmp_path / "v"
    shutil.copytree(video_dir, d)
    (d / "cam0.mkv").unlink()
    (d / "cam0.mp4").write_bytes(b"\x00\x00\x00\x18ftypisom" + bytes(200))  # cut before moov
    with pytest.raises(LogError, match=r"cam0.mp4: not a readable video .*moov atom"):
        open_flight(d)


# ---------------------------------------------------------------------------- PX4 ULog

_CODES = {"uint64_t": "Q", "float": "f", "int32_t": "i", "uint32_t": "I"}
SENSOR_COMBINED = [
    ("uint64_t", "timestamp"),
    ("float[3]", "gyro_rad"),
    ("uint32_t", "gyro_integral_dt"),
    ("int32_t", "accelerometer_timestamp_relative"),
    ("float[3]", "accelerometer_m_s2"),
]
CAMERA_CAPTURE = [("uint64_t", "timestamp"), ("uint32_t", "seq")]


def write_ulog(path, topics):
    """A minimal ULog v1 file (PX4 docs "ULog File Format": header, B, F, A, D messages).
    topics: {name: (fields [(type, name)], rows [tuple])}."""
    out = bytearray(b"ULog\x01\x12\x35\x01" + struct.pack("<Q", 0))

    def msg(kind, payload):
        out.extend(struct.pack("<HB", len(payload), ord(kind)) + payload)

    msg("B", bytes(40))
    for name, (fields, _) in topics.items():
        msg("F", (name + ":" + "".join(f"{t} {n};" for t, n in fields)).encode())
    for k, name in enumerate(topics):
        msg("A", struct.pack("<BH", 0, k) + name.encode())
    for k, (fields, rows) in enumerate(topics.values()):
        fmt = "<" + "".join(
            _CODES[t.split("[")[0]] * (int(t.split("[")[1][:-1]) if "[" in t else 1) for t, _ in fields
        )
        for r in rows:
            msg("D", struct.pack("<H", k) + struct.pack(fmt, *r))
    Path(path).write_bytes(bytes(out))


def test_ulog_imu_and_capture_times(video_dir, tmp_path):
    d = tmp_path / "v"
    shutil.copytree(video_dir, d)
    for f in ("imu.csv", "cam0.csv", "cam1.mkv", "cam1.csv"):
        (d / f).unlink()
    # FRD samples: gravity reads -9.81 on z (specific force points up = -z in FRD)
    rows = [(1_000_000 + 5000 * k, 0.1, 0.2, 0.3, 5000, 0, 0.5, 0.0, -9.81) for k in range(400)]
    capture = [(1_000_000 + 100_000 * k + 7, k) for k in range(N_FRAMES)]
    write_ulog(
        d / "flight.ulg",
        {"sensor_combined": (SENSOR_COMBINED, rows), "camera_capture": (CAMERA_CAPTURE, capture)},
    )
    flight = open_flight(d)
    imu = flight.imu
    assert len(imu.timestamps_ns) == 400 and imu.timestamps_ns[1] - imu.timestamps_ns[0] == 5_000_000
    np.testing.assert_allclose(imu.gyro_rad_s[0], [0.1, 0.2, 0.3], rtol=1e-6)
    np.testing.assert_array_equal(imu.T_body_imu, T_FLU_FRD)
    # in the FLU body frame the specific force is +z up
    a_body = imu.T_body_imu[:3, :3] @ imu.accel_m_s2[0]
    np.testing.assert_allclose(a_body, [0.5, 0.0, 9.81], rtol=1e-6)
    np.testing.assert_array_equal(
        flight.floor.timestamps_ns, [(1_000_000 + 100_000 * k + 7) * 1000 for k in range(N_FRAMES)]
    )
    # the camchain was written for an identity T_body_imu: composed with FRD now
    np.testing.assert_allclose(
        flight.floor.camera.T_body_cam, T_FLU_FRD @ short_flight().floor.camera.T_body_cam, atol=1e-12
    )

    assert not [w for w in flight.warnings if w.name.startswith("stamps_")]
    # a duplicated and a swapped sample: sorted, the duplicate dropped, both named and counted
    # (they were a log line only; a bag's IMU topic names them the same way)
    bad = rows[:10] + [rows[9]] + [rows[11], rows[10]] + rows[12:]
    write_ulog(
        d / "flight.ulg",
        {"sensor_combined": (SENSOR_COMBINED, bad), "camera_capture": (CAMERA_CAPTURE, capture)},
    )
    flight = open_flight(d)
    np.testing.assert_array_equal(flight.imu.timestamps_ns, imu.timestamps_ns)
    named = {w.name: w.count for w in flight.warnings}
    assert named.get("stamps_out_of_order") == 1 and named.get("stamps_duplicate") == 1

    # `fusion inspect` says so too, as the run does: its streams are the sorted ones (no
    # stamp out of order to count), so the warnings were its only trace, and it dropped them
    problems = inspect_log(d).problems
    assert any(p.startswith("[stamps_out_of_order] x1: ") and "sensor_combined" in p for p in problems)
    assert any(p.startswith("[stamps_duplicate] x1: ") for p in problems)

    # a re-sent capture message: its repeated time dropped and counted, the frames keep theirs
    # (it had failed every back end with "sample 50 is duplicated", naming no file)
    resent = capture[:5] + [capture[4]] + capture[5:]
    write_ulog(
        d / "flight.ulg",
        {"sensor_combined": (SENSOR_COMBINED, rows), "camera_capture": (CAMERA_CAPTURE, resent)},
    )
    flight = open_flight(d)
    np.testing.assert_array_equal(
        flight.floor.timestamps_ns, [(1_000_000 + 100_000 * k + 7) * 1000 for k in range(N_FRAMES)]
    )
    (dup,) = [w for w in flight.warnings if w.name == "stamps_duplicate"]
    assert dup.count == 1 and "camera_capture" in dup.message

    write_ulog(d / "flight.ulg", {"camera_capture": (CAMERA_CAPTURE, capture)})
    with pytest.raises(
        LogError,
        match=r"flight.ulg: no 'sensor_combined' topic; the ULog holds "
        r"camera_capture",
    ):
        open_flight(d)


@pytest.mark.parametrize("noise, words", [("fast", "expected a number"), (-0.05, "positive")])
def test_a_video_logs_velocity_noise_is_checked_when_read(video_dir, tmp_path, noise, words):
    """velocity.yaml's `noise_m_s: fast` ended in a traceback; `-0.05` passed the reader and
    failed every back end without naming the file (second audit)."""
    d = tmp_path / "v"
    shutil.copytree(video_dir, d)
    if not (d / "velocity.csv").exists():
        pytest.skip("the short flight has no velocity")
    (d / "velocity.yaml").write_text(yaml.safe_dump({"noise_m_s": noise, "frame": "body"}))
    with pytest.raises(LogError, match=rf"velocity.yaml: noise_m_s: .*{words}"):
        open_flight(d)
