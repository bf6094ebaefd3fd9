"""ROS bags: round trip (EuRoC -> bag -> FlightLog) with the same frames, detections and
estimates; image encodings; roles by type and overrides; stamps; bad bags end in one line."""

import shutil
from pathlib import Path

import cv2
import numpy as np
import yaml
import pytest

from fusion.cli import main
from fusion.errors import LogError
from fusion.log import LogOptions, StampSource, euroc, open_flight
from fusion.log.convert import export_flight, import_flight
from fusion.log.inspect import inspect_log
from fusion.log.kalibr import write_camchain
from fusion.log.rosbag import BAYER_TO_GRAY, COMPRESSED, IMAGE, IMU, _header, decode_image, typestore_for

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"


@pytest.fixture(scope="module")
def sample():
    return short_flight()


def short_flight(n_frames=8):
    """The sample flight with its first frames only (IMU, velocity, ground truth whole)."""
    f = euroc.read_flight(SAMPLE)
    f.cameras = {
        name: euroc.CameraStream(
            name, s.camera, s.timestamps_ns[:n_frames], s.paths[:n_frames], s.csv_lines[:n_frames]
        )
        for name, s in f.cameras.items()
    }
    return f


@pytest.fixture(scope="module")
def bags(tmp_path_factory, sample):
    d = tmp_path_factory.mktemp("bags")
    return {
        "mcap": export_flight(sample, d / "f.mcap"),
        "bag": export_flight(sample, d / "f.bag"),
        "png": export_flight(sample, d / "png.mcap", image_format="png"),
        "jpeg": export_flight(sample, d / "jpeg.bag", image_format="jpeg"),
    }


def _same_flight(a, b, lossless=True):
    assert sorted(a.cameras) == sorted(b.cameras)
    for name in a.cameras:
        sa, sb = a.cameras[name], b.cameras[name]
        np.testing.assert_array_equal(sa.timestamps_ns, sb.timestamps_ns)
        assert sa.camera.to_sensor_yaml() == sb.camera.to_sensor_yaml()
        # out of order on purpose: exercises the seek path as well as the sequential one
        for i in (0, 6, 3, 4, len(sa) - 1):
            ia, ib = sa.load_image(i), sb.load_image(i)
            if lossless:
                np.testing.assert_array_equal(ia, ib)
            else:
                assert np.abs(ia.astype(int) - ib).mean() < 3.0
    np.testing.assert_array_equal(a.imu.timestamps_ns, b.imu.timestamps_ns)
    np.testing.assert_array_equal(a.imu.gyro_rad_s, b.imu.gyro_rad_s)
    np.testing.assert_array_equal(a.imu.accel_m_s2, b.imu.accel_m_s2)
    assert a.imu.noise == b.imu.noise
    np.testing.assert_array_equal(a.velocity.v_body_m_s, b.velocity.v_body_m_s)
    assert a.velocity.noise_m_s == b.velocity.noise_m_s
    assert a.world == b.world and a.blackouts == b.blackouts
    assert a.loads_groundtruth.keys() == b.loads_groundtruth.keys()
    np.testing.assert_allclose(a.groundtruth.p_world, b.groundtruth.p_world, atol=0)
    np.testing.assert_allclose(a.groundtruth.v_world, b.groundtruth.v_world, atol=1e-12)


@pytest.mark.parametrize("kind", ["mcap", "bag", "png"])
def test_bag_round_trip_is_lossless(sample, bags, kind):
    _same_flight(sample, open_flight(bags[kind]))


def test_jpeg_bag_is_close(sample, bags):
    _same_flight(sample, open_flight(bags["jpeg"]), lossless=False)


def test_import_gives_back_the_euroc_folder(sample, bags, tmp_path):
    out = import_flight(bags["bag"], tmp_path / "imported")
    _same_flight(sample, euroc.read_flight(out))


# ---------------------------------------------------------------------------- hand-made bags


def _write_bag(
    path,
    images=(),
    imu=True,
    camera_info=False,
    ros1=None,
    stamps=None,
    log_times=None,
    encoding="mono8",
    topic="/cam/image_raw",
    groundtruth_stamps=None,
    imu_samples=None,
):
    """A small bag: `images` (list of uint8 arrays) on `topic` with header `stamps` and receive
    `log_times`, an IMU at 100 Hz (30 samples: constant, or `imu_samples` rows gyro xyz, accel
    xyz), optionally a CameraInfo, and with `groundtruth_stamps` our /fusion/groundtruth
    Odometry with those header stamps, received 1 ms apart in list order."""
    from rosbags.rosbag1 import Writer as W1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as W2

    from fusion.log.rosbag import CAMERA_INFO, camera_info_msg

    ros1 = path.suffix == ".bag" if ros1 is None else ros1
    ts = typestore_for(ros1)
    ser = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    n = len(images)
    stamps = list(stamps) if stamps is not None else [1_000_000_000 + k * 100_000_000 for k in range(n)]
    log_times = list(log_times) if log_times is not None else stamps
    target = path if ros1 else path.with_name(path.stem + "_dir")
    w = W1(target) if ros1 else W2(target, version=9, storage_plugin=StoragePlugin.MCAP)
    queue = []  # (receive time, order, connection, bytes)

    class TimeOrdered:  # write in receive-time order, as recorded
        def __init__(self, writer):
            self.w = writer

        def add_connection(self, *a, **k):
            return self.w.add_connection(*a, **k)

        def write(self, con, t, data):
            queue.append((t, len(queue), con, data))

    real, w = w, TimeOrdered(w)
    with real:
        if n:
            c = w.add_connection(topic, IMAGE, typestore=ts)
            for img, t, tl in zip(images, stamps, log_times):
                ch = 1 if img.ndim == 2 else img.shape[2]
                msg = ts.types[IMAGE](
                    header=_header(ts, t, "cam", ros1),
                    height=img.shape[0],
                    width=img.shape[1],
                    encoding=encoding,
                    is_bigendian=0,
                    step=img.shape[1] * ch * img.itemsize,
                    data=np.frombuffer(img.tobytes(), np.uint8),
                )
                w.write(c, tl, ser(msg, IMAGE))
        if camera_info:
            from fusion.camera import CameraModel

            ci = w.add_connection(topic.rsplit("/", 1)[0] + "/camera_info", CAMERA_INFO, typestore=ts)
            cam = CameraModel(images[0].shape[1], images[0].shape[0], 50.0, 50.0, 16.0, 12.0)
            w.write(ci, stamps[0], ser(camera_info_msg(cam, stamps[0], "cam", ros1, ts), CAMERA_INFO))
        if imu:
            ci = w.add_connection("/imu", IMU, typestore=ts)
            V = ts.types["geometry_msgs/msg/Vector3"]
            samples = np.tile([0.01, 0, 0, 0, 0, 9.81], (30, 1)) if imu_samples is None else imu_samples
            for k, (wx, wy, wz, ax, ay, az) in enumerate(np.asarray(samples, dtype=float)):
                t = 1_000_000_000 + k * 10_000_000
                m = ts.types[IMU](
                    header=_header(ts, t, "imu", ros1),
                    orientation=ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.zeros(9),
                    angular_velocity=V(x=wx, y=wy, z=wz),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=V(x=ax, y=ay, z=az),
                    linear_acceleration_covariance=np.zeros(9),
                )
                w.write(ci, t, ser(m, IMU))
        if groundtruth_stamps is not None:
            from fusion.log.rosbag import GROUNDTRUTH_TOPIC, ODOMETRY

            cg = w.add_connection(GROUNDTRUTH_TOPIC, ODOMETRY, typestore=ts)
            T = ts.types
            zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
            for k, t in enumerate(groundtruth_stamps):
                pose = T["geometry_msgs/msg/PoseWithCovariance"](
                    pose=T["geometry_msgs/msg/Pose"](
                        position=T["geometry_msgs/msg/Point"](x=float(k), y=0.0, z=1.0),
                        orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                    ),
                    covariance=np.zeros(36),
                )
                twist = T["geometry_msgs/msg/TwistWithCovariance"](
                    twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero), covariance=np.zeros(36)
                )
                m = T[ODOMETRY](
                    header=_header(ts, t, "world", ros1), child_frame_id="body", pose=pose, twist=twist
                )
                w.write(cg, 1_000_000_000 + k * 1_000_000, ser(m, ODOMETRY))
        for t, _, con, data in sorted(queue, key=lambda q: q[:2]):
            real.write(con, t, data)
    if not ros1:  # one .mcap file, as `ros2 bag` can read
        (target / f"{target.name}.mcap").replace(path)
        shutil.rmtree(target)
    return path


@pytest.fixture
def world_and_calib(tmp_path, sample):
    """world.yaml beside the bags and a Kalibr camchain for a 32x24 camera on /cam/image_raw."""
    sample.world.save(tmp_path / "world.yaml")
    from fusion.camera import CameraModel

    cam = CameraModel(32, 24, 50.0, 50.0, 16.0, 12.0)
    calib = tmp_path / "camchain-imucam.yaml"
    write_camchain(calib, {"cam0": cam}, {"cam0": "/cam/image_raw"}, timeshift_ns={"cam0": 2_000_000})
    return calib


def _images(n, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 255, size=(24, 32), dtype=np.uint8) for _ in range(n)]


def _resting_imu(clipped=0, seed=1, n=200):
    """_write_bag's IMU samples (n: 2 s at 100 Hz, over the frames of up to 20 images at 10 Hz:
    an IMU stopping before the frames is the warning imu_coverage) of a plausible IMU at rest
    (the constant default reads as clipped to euroc.check_log): white noise as the default
    ImuNoise states it at 100 Hz, gravity on z; with `clipped`, that many accelerometer z
    readings sit at the axis' largest value."""
    rng = np.random.default_rng(seed)
    s = np.c_[rng.normal(scale=1.7e-3, size=(n, 3)), [0, 0, 9.81] + rng.normal(scale=0.02, size=(n, 3))]
    if clipped:
        s[:, 5] = np.minimum(s[:, 5], np.sort(s[:, 5])[-clipped])
    return s


def test_import_passes_on_what_the_reader_warned(tmp_path, world_and_calib, capsys):
    """`fusion import` of a bag with unordered and duplicate stamps: the EuRoC copy is sorted
    and no longer shows them, so the import says them (they were dropped: a later run on the
    copy cannot know)."""
    from fusion.cli import main

    stamps = [1_000_000_000, 1_200_000_000, 1_100_000_000, 1_300_000_000, 1_300_000_000]
    logt = [2_000_000_000 + k * 1000 for k in range(5)]  # received in this order
    bag = _write_bag(tmp_path / "u.bag", _images(5), stamps=stamps, log_times=logt)
    said: list = []
    import_flight(bag, tmp_path / "copy", LogOptions(calib=world_and_calib), warnings=said)
    assert {w.name for w in said} >= {"stamps_out_of_order", "stamps_duplicate"}
    assert main(["import", str(bag), str(tmp_path / "copy2"), "--calib", str(world_and_calib)]) == 0
    printed = capsys.readouterr().out
    assert "warning: [stamps_out_of_order] x1" in printed and "warning: [stamps_duplicate] x1" in printed


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_a_topic_without_header_stamps_falls_back_to_receive_time_with_a_named_warning(
    tmp_path, world_and_calib, suffix
):
    """A camera driver that leaves header.stamp empty: its frames take the bag's receive time,
    and the run says so by name (`bag_receive_time`, count: the topic's messages); it was a log
    line only, so `-q` and `fusion batch` never said that one topic is on the recorder's clock."""
    logt = [2_000_000_000 + k * 100_000_000 for k in range(4)]
    bag = _write_bag(tmp_path / f"z{suffix}", _images(4), stamps=[0] * 4, log_times=logt)
    flight = open_flight(bag, LogOptions(calib=world_and_calib))
    np.testing.assert_array_equal(flight.floor.timestamps_ns, np.array(logt) + 2_000_000)
    named = [w for w in flight.warnings if w.name == "bag_receive_time"]
    assert len(named) == 1 and named[0].count == 4 and "/cam/image_raw" in named[0].message
    # the IMU has its stamps: no warning for it
    assert "/imu" not in named[0].message


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_frames_with_an_unset_stamp_in_an_epoch_clock_are_dropped_and_counted(
    tmp_path, world_and_calib, suffix, caplog
):
    """A driver publishing header.stamp 0 before its clock is synchronised (second audit): its
    first frames sat at t = 0, 1.7e9 s before the rest, and the smoother split that span into
    11 million windows.  They are dropped and counted (`stamps_unset`); a clock that starts at
    0 keeps its frame at 0."""
    epoch = 1_700_000_000 * 10**9
    stamps = [0, 0] + [epoch + k * 100_000_000 for k in range(4)]
    bag = _write_bag(
        tmp_path / f"e{suffix}", _images(6), stamps=stamps, log_times=[epoch + k for k in range(6)]
    )
    flight = open_flight(bag, LogOptions(calib=world_and_calib))
    np.testing.assert_array_equal(flight.floor.timestamps_ns, np.array(stamps[2:]) + 2_000_000)
    np.testing.assert_array_equal(flight.floor.load_image(0), _images(6)[2])
    named = [w for w in flight.warnings if w.name == "stamps_unset"]
    assert len(named) == 1 and named[0].count == 2 and "/cam/image_raw" in named[0].message
    zero_based = [k * 100_000_000 for k in range(4)]
    bag = _write_bag(tmp_path / f"z0{suffix}", _images(4), stamps=zero_based, camera_info=True)
    caplog.clear()
    flight = open_flight(bag, LogOptions(calib=world_and_calib))
    assert len(flight.floor) == 4 and not [w for w in flight.warnings if w.name == "stamps_unset"]
    inspect_log(bag, LogOptions(calib=world_and_calib))
    # its one camera_info, stamped at the flight's t = 0, has its stamp (second audit: it was
    # said to have none, and read at the bag's receive time)
    assert "has no header stamps" not in caplog.text


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_out_of_order_and_duplicate_stamps_are_sorted_and_counted(tmp_path, world_and_calib, suffix):
    imgs = _images(5)
    stamps = [1_000_000_000, 1_200_000_000, 1_100_000_000, 1_300_000_000, 1_300_000_000]
    logt = [2_000_000_000 + k * 1000 for k in range(5)]
    bag = _write_bag(tmp_path / f"b{suffix}", imgs, stamps=stamps, log_times=logt)
    flight = open_flight(bag, LogOptions(calib=world_and_calib))
    cam = flight.floor
    # sorted, duplicate dropped, Kalibr timeshift (2 ms) added: t_imu = t_cam + shift
    np.testing.assert_array_equal(
        cam.timestamps_ns, np.array([1.0e9, 1.1e9, 1.2e9, 1.3e9]).astype(np.int64) + 2_000_000
    )
    assert flight.timeshift_ns == {"cam0": 2_000_000}  # the time-offset estimate's seed
    for i, k in enumerate([0, 2, 1, 3]):  # frame i is the bag's message k
        np.testing.assert_array_equal(cam.load_image(i), imgs[k])
    np.testing.assert_array_equal(list(f.image for f in cam.frames())[1], imgs[2])
    rep = inspect_log(bag, LogOptions(calib=world_and_calib))
    s = {x.name: x for x in rep.streams}["/cam/image_raw"]
    assert (s.n_out_of_order, s.n_duplicates, s.count, s.role) == (1, 1, 5, "floor camera")
    assert "accel OK" in rep.imu_units and rep.roles["imu0"] == "/imu"
    # receive time on request
    flight = open_flight(bag, LogOptions(calib=world_and_calib, stamps=StampSource.RECEIVE))
    np.testing.assert_array_equal(flight.floor.timestamps_ns, np.array(logt) + 2_000_000)


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_ground_truth_topic_out_of_order_is_a_named_counted_warning(tmp_path, world_and_calib, suffix):
    """The bag's ground truth is sorted like every other topic, and says so like them
    (`stamps_out_of_order` / `stamps_duplicate`, naming the topic): it was sorted silently, so a
    truth recorded out of order scored the flight with nobody told."""
    gt = [1_000_000_000, 1_200_000_000, 1_100_000_000, 1_300_000_000, 1_300_000_000]
    bag = _write_bag(tmp_path / f"g{suffix}", _images(3), groundtruth_stamps=gt)
    flight = open_flight(bag, LogOptions(calib=world_and_calib))
    np.testing.assert_array_equal(flight.groundtruth.timestamps_ns, sorted(set(gt)))
    np.testing.assert_array_equal(flight.groundtruth.p_world[:, 0], [0, 2, 1, 3])  # message k at x = k
    named = {w.name: w for w in flight.warnings if "/fusion/groundtruth" in w.message}
    assert named["stamps_out_of_order"].count == 1 and named["stamps_duplicate"].count == 1


def test_image_encodings_decode_to_gray():
    rng = np.random.default_rng(3)
    bgr = rng.integers(0, 255, size=(8, 10, 3), dtype=np.uint8)
    gray = cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)

    class Msg:
        def __init__(self, enc, data, step, big=0):
            self.encoding, self.height, self.width, self.step = enc, 8, 10, step
            self.data, self.is_bigendian = np.frombuffer(data, np.uint8), big

    np.testing.assert_array_equal(decode_image(Msg("bgr8", bgr.tobytes(), 30), IMAGE), gray)
    np.testing.assert_array_equal(decode_image(Msg("rgb8", bgr[..., ::-1].tobytes(), 30), IMAGE), gray)
    padded = np.zeros((8, 16), np.uint8)
    padded[:, :10] = gray
    np.testing.assert_array_equal(decode_image(Msg("mono8", padded.tobytes(), 16), IMAGE), gray)
    # rgb8 published under a mono8 label: three times the data step x height says (second
    # audit: read as grey stripes from its first third, every frame, no warning)
    with pytest.raises(ValueError, match="not step x height = 80"):
        decode_image(Msg("mono8", bgr.tobytes(), 10), IMAGE)
    with pytest.raises(ValueError, match="a row of at least 30"):
        decode_image(Msg("rgb8", bgr.tobytes()[:160], 20), IMAGE)
    img16 = gray.astype(np.uint16) * 257  # full 16-bit range -> the same 8 bits
    np.testing.assert_array_equal(
        decode_image(Msg("mono16", img16.tobytes(), 20), IMAGE),
        np.round(img16 * 255.0 / img16.max()).astype(np.uint8),
    )
    np.testing.assert_array_equal(
        decode_image(Msg("mono16", img16.astype(">u2").tobytes(), 20, big=1), IMAGE),
        decode_image(Msg("mono16", img16.tobytes(), 20), IMAGE),
    )
    # Bayer: mosaic a flat colour; demosaicing must give back its gray level (ROS names the
    # pattern from the top-left pixel: rggb = R at (0, 0))
    b, g, r = 40, 120, 200
    flat_gray = round(0.299 * r + 0.587 * g + 0.114 * b)
    place = {"r": r, "g": g, "b": b}
    for enc in BAYER_TO_GRAY:
        pat = enc.split("_")[1][:4]
        mosaic = np.zeros((8, 10), np.uint8)
        for (dy, dx), c in zip(((0, 0), (0, 1), (1, 0), (1, 1)), pat):
            mosaic[dy::2, dx::2] = place[c]
        out = decode_image(Msg(enc, mosaic.tobytes(), 10), IMAGE)
        assert abs(int(np.median(out[2:-2, 2:-2])) - flat_gray) <= 2, enc

    class Comp:
        format = "jpeg"
        data = np.frombuffer(cv2.imencode(".png", gray)[1].tobytes(), np.uint8)

    np.testing.assert_array_equal(decode_image(Comp, COMPRESSED), gray)  # png inside "jpeg"
    whole = Comp.data
    for fmt, enc in (("png", ".png"), ("jpeg", ".jpg")):
        # a cut frame is named before decoding: libpng printed its own stderr line per frame
        Comp.format, Comp.data = fmt, cv2.imencode(enc, gray)[1][:-20]
        with pytest.raises(ValueError, match=rf"CompressedImage \({fmt}\) is truncated \(no "):
            decode_image(Comp, COMPRESSED)
    Comp.format, Comp.data = "jpeg", whole
    Comp.format = "rgb8; compressedDepth"
    with pytest.raises(ValueError, match="compressedDepth"):
        decode_image(Comp, COMPRESSED)
    with pytest.raises(ValueError, match="'yuv422' is not supported"):
        decode_image(Msg("yuv422", bgr.tobytes(), 20), IMAGE)


def test_bad_bags_end_in_one_line(tmp_path, world_and_calib):
    opts = LogOptions(calib=world_and_calib)
    bag = _write_bag(tmp_path / "noimu.bag", _images(3), imu=False)
    with pytest.raises(LogError, match=r"noimu.bag: no IMU topic .* holds /cam/image_raw"):
        open_flight(bag, opts)
    bag = _write_bag(tmp_path / "nocam.mcap", [], imu=True)
    with pytest.raises(LogError, match=r"nocam.mcap: no camera topic .* holds /imu"):
        open_flight(bag, opts)
    bag = _write_bag(tmp_path / "enc.bag", [np.zeros((24, 64), np.uint8)], encoding="yuv422")
    with pytest.raises(
        LogError,
        match=r"enc.bag: topic /cam/image_raw message 0: image "
        r"encoding 'yuv422' is not supported",
    ):
        open_flight(bag, opts)
    bag = _write_bag(tmp_path / "ok.bag", _images(3))
    with pytest.raises(LogError, match=r"ok.bag: IMU topic /nope is not in the bag; it holds"):
        open_flight(bag, LogOptions(calib=world_and_calib, imu_topic="/nope"))
    with pytest.raises(LogError, match=r"floor topic /imu is sensor_msgs/msg/Imu"):
        open_flight(bag, LogOptions(calib=world_and_calib, floor_topic="/imu"))
    # CameraInfo alone says nothing of where the camera sits on the drone
    bag = _write_bag(tmp_path / "info.mcap", _images(3), camera_info=True)
    with pytest.raises(LogError, match=r"CameraInfo /cam/camera_info .*\(--calib\)"):
        open_flight(bag)
    # a ROS 1 bag cut before its first complete message
    good = _write_bag(tmp_path / "full.bag", _images(3))
    cut = tmp_path / "cut.bag"
    cut.write_bytes(good.read_bytes()[:200])
    with pytest.raises(
        LogError,
        match=r"cut.bag: truncated or unindexed ROS 1 bag with no "
        r"complete message",
    ):
        open_flight(cut, opts)


@pytest.mark.parametrize("fraction", [0.3, 0.8])
def test_truncated_ros1_bag_reads_up_to_the_damage(tmp_path, world_and_calib, monkeypatch, caplog, fraction):
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # the recovered copy goes here
    imgs = _images(20)
    good = _write_bag(tmp_path / "full.bag", imgs)
    cut = tmp_path / "cut.bag"
    cut.write_bytes(good.read_bytes()[: int(good.stat().st_size * fraction)])
    flight = open_flight(cut, LogOptions(calib=world_and_calib))
    n = len(flight.floor)
    assert 0 < n < 20 and "cut.bag: truncated or unindexed ROS 1 bag, cut after" in caplog.text
    assert flight.root == cut
    full = open_flight(good, LogOptions(calib=world_and_calib))
    np.testing.assert_array_equal(flight.floor.timestamps_ns, full.floor.timestamps_ns[:n])
    for i in (0, n - 1):
        np.testing.assert_array_equal(flight.floor.load_image(i), imgs[i])
    # the recovered copy is reused while the bag is unchanged
    copies = list((tmp_path / "fusion-recovered-bags").glob("cut-*.bag"))
    assert len(copies) == 1
    open_flight(cut, LogOptions(calib=world_and_calib))
    assert list((tmp_path / "fusion-recovered-bags").glob("cut-*.bag")) == copies


@pytest.mark.parametrize("fraction", [0.3, 0.6, 0.95])
def test_truncated_mcap_reads_up_to_the_damage(tmp_path, world_and_calib, monkeypatch, fraction):
    """A recording cut short has no MCAP footer (rosbags refuses it): the complete records are
    copied (those of the one uncompressed chunk the cut went through too), with a warning."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    imgs = _images(20)
    good = _write_bag(tmp_path / "full.mcap", imgs)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[: int(good.stat().st_size * fraction)])
    flight = open_flight(cut, LogOptions(calib=world_and_calib))
    n = len(flight.floor)
    assert 0 < n < 20 if fraction < 0.9 else 0 < n <= 20
    full = open_flight(good, LogOptions(calib=world_and_calib))
    np.testing.assert_array_equal(flight.floor.timestamps_ns, full.floor.timestamps_ns[:n])
    for i in (0, n - 1):
        np.testing.assert_array_equal(flight.floor.load_image(i), imgs[i])
    w = [x for x in flight.warnings if x.name == "bag_truncated"]
    assert len(w) == 1 and "cut.mcap: truncated MCAP file" in w[0].message
    assert not [x for x in full.warnings if x.name == "bag_truncated"]
    # cut before the first complete record: nothing to read, one line
    tiny = tmp_path / "tiny.mcap"
    tiny.write_bytes(good.read_bytes()[:40])
    with pytest.raises(LogError, match=r"tiny.mcap: truncated MCAP file with no complete message"):
        open_flight(tiny, LogOptions(calib=world_and_calib))


def test_truncated_mcap_keeps_its_complete_compressed_chunks(tmp_path):
    """zstd chunks (as `ros2 bag record` writes them): the chunks before the cut are read, the
    one the cut went through is lost."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin
    from rosbags.rosbag2 import Writer as W2

    from fusion.log.mcaprecover import recover_mcap

    ts = typestore_for(False)
    rng = np.random.default_rng(5)
    target = tmp_path / "z"
    w = W2(target, version=9, storage_plugin=StoragePlugin.MCAP)
    w.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
    stamps = [1_000_000_000 + k * 50_000_000 for k in range(40)]
    with w:
        c = w.add_connection("/cam/image_raw", IMAGE, typestore=ts)
        for t in stamps:  # 90 kB of noise each: about 12 messages per 1 MiB chunk
            img = rng.integers(0, 255, size=(300, 300), dtype=np.uint8)
            msg = ts.types[IMAGE](
                header=_header(ts, t, "cam", False),
                height=300,
                width=300,
                encoding="mono8",
                is_bigendian=0,
                step=300,
                data=img.reshape(-1),
            )
            w.write(c, t, ts.serialize_cdr(msg, IMAGE))
    good = target / "z.mcap"
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(good.read_bytes()[: int(good.stat().st_size * 0.7)])
    n_msg, n_chunks, note = recover_mcap(cut, tmp_path / "rec.mcap")
    assert n_msg == 0 and n_chunks >= 1 and "cut at byte" in note
    with AnyReader([tmp_path / "rec.mcap"], default_typestore=ts) as r:
        got = [t for _, t, _ in r.messages()]
    assert 0 < len(got) < 40 and len(got) % 12 == 0 and got == stamps[: len(got)]


@pytest.mark.parametrize(
    "suffix,said", [(".bag", "truncated or unindexed ROS 1 bag"), (".mcap", "truncated MCAP file")]
)
def test_inspect_says_a_bag_was_cut_short(tmp_path, world_and_calib, monkeypatch, capsys, suffix, said):
    """`fusion inspect` of a damaged bag shows the recovered copy's counts and says what was
    recovered (the note `fusion run` gives as `bag_truncated`): it showed the counts of a bag
    cut short as if they were the recording's."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    good = _write_bag(tmp_path / f"full{suffix}", _images(20), imu_samples=_resting_imu())
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(good.read_bytes()[: int(good.stat().st_size * 0.6)])
    rep = inspect_log(cut, LogOptions(calib=world_and_calib))
    assert rep.path == cut and any(f"cut{suffix}: {said}" in p for p in rep.problems)
    assert rep.roles["cam0"] == "/cam/image_raw"
    assert not inspect_log(good, LogOptions(calib=world_and_calib)).problems
    assert main(["inspect", str(cut), "--calib", str(world_and_calib)]) == 0
    assert f"problem: {cut}: {said}" in capsys.readouterr().out


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_inspect_shows_the_plausibility_warnings_a_run_gives_for_a_bag(
    tmp_path, world_and_calib, capsys, suffix
):
    """`fusion inspect` of a bag lists the run's plausibility warnings about its data
    (euroc.check_log; here `imu_saturated`: an accelerometer axis clipped), with the run's names
    and counts.  An EuRoC folder's were shown; a bag's only by the run, so a bag the run warns
    about looked clean.  A bag the run cannot read is said to be unchecked, and why."""
    opts = LogOptions(calib=world_and_calib)
    clean = _write_bag(tmp_path / f"clean{suffix}", _images(5), imu_samples=_resting_imu())
    assert not inspect_log(clean, opts).problems
    clipped = _write_bag(tmp_path / f"clipped{suffix}", _images(5), imu_samples=_resting_imu(clipped=12))
    (run,) = [w for w in open_flight(clipped, opts).warnings if w.name == "imu_saturated"]
    assert run.count == 12
    assert inspect_log(clipped, opts).problems == [str(run)]
    assert main(["inspect", str(clipped), "--calib", str(world_and_calib)]) == 0
    assert f"problem: {run}" in capsys.readouterr().out
    (unchecked,) = inspect_log(clipped, LogOptions()).problems  # no calibration for /cam/image_raw
    assert unchecked.startswith("plausibility not checked, the run could not read the log: ")
    assert "no calibration" in unchecked


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_inspect_reads_a_bags_messages_once(tmp_path, world_and_calib, monkeypatch, suffix):
    """`fusion inspect` of a bag passes over its messages once: the plausibility check builds the
    run's log from inspect's own pass (rosbag.BagPass) instead of reading the bag again (it read
    it twice, a long wait on a large bag); the warnings are the run's all the same."""
    from fusion.log import rosbag as rb

    opts = LogOptions(calib=world_and_calib)
    clipped = _write_bag(tmp_path / f"clipped{suffix}", _images(5), imu_samples=_resting_imu(clipped=12))
    (run,) = [w for w in open_flight(clipped, opts).warnings if w.name == "imu_saturated"]
    passes: list = []
    scan = rb.scan_bag

    def counted(bag, vectors=None, first_of=None, topics=None):
        if topics != {rb.METADATA_TOPIC}:  # the metadata topic's own small read aside
            passes.append(topics)
        return scan(bag, vectors, first_of, topics)

    monkeypatch.setattr(rb, "scan_bag", counted)
    assert inspect_log(clipped, opts).problems == [str(run)]
    assert passes == [None], passes  # one pass, over every topic


@pytest.mark.parametrize("suffix", [".bag", ".mcap"])
def test_a_bags_plausibility_warnings_name_the_bag_and_the_topic(tmp_path, world_and_calib, suffix):
    """euroc.check_log's warnings about a bag name the bag and the topic as the bag reader's own
    warnings do (`<bag>: topic /imu`), and a mount the camchain states names the camchain and
    the camera's key: they named `<bag>/mav0/imu0/data.csv` and `<bag>/mav0/cam0/sensor.yaml`,
    files that do not exist, as if the bag were an EuRoC folder."""
    from fusion.camera import CameraModel
    from fusion.geometry import make_T

    bag = _write_bag(tmp_path / f"clipped{suffix}", _images(5), imu_samples=_resting_imu(clipped=12))
    warnings = open_flight(bag, LogOptions(calib=world_and_calib)).warnings
    (w,) = [w for w in warnings if w.name == "imu_saturated"]
    assert w.count == 12
    assert w.message.startswith(f"{bag}: topic /imu: 12 sample value(s) sit at an axis' extreme")
    assert "mav0" not in w.message and "data.csv" not in w.message
    far = tmp_path / "far-camchain.yaml"  # the camera 1.5 m from the IMU: millimetres?
    cam = CameraModel(32, 24, 50.0, 50.0, 16.0, 12.0, T_body_cam=make_T(np.eye(3), [0, 0, 1.5]))
    write_camchain(far, {"cam0": cam}, {"cam0": "/cam/image_raw"})
    (w,) = [w for w in open_flight(bag, LogOptions(calib=far)).warnings if w.name == "T_BS_translation"]
    assert w.count == 1 and w.message.startswith(f"{far}: cam0: T_BS puts cam0 1.5 m from the body origin")
    assert "mav0" not in w.message


def test_a_bag_imu_slower_than_its_kalibr_imu_yaml_says_is_a_rate_mismatch(tmp_path, world_and_calib):
    """Kalibr's imu.yaml states the IMU's `update_rate`: a bag whose IMU runs at half of it gives
    `rate_mismatch` naming the yaml and the topic, as an EuRoC folder's sensor.yaml `rate_hz`
    does (the check looked for `<bag>/mav0/imu0/sensor.yaml` only, so it never fired for a bag).
    A rate 1000x off is the yaml's mistake, not the stamps' units (a bag's are sec + nsec): a
    warning too, not the refusal an EuRoC folder's CSV timestamps get."""
    from fusion.log.kalibr import write_imu_yaml

    bag = _write_bag(tmp_path / "slow.mcap", _images(5), imu_samples=_resting_imu())  # IMU 100 Hz
    imu_yaml = tmp_path / "imu.yaml"
    for stated, said in ((100.0, None), (200.0, "update_rate 200"), (0.1, "update_rate 0.1")):
        write_imu_yaml(imu_yaml, euroc.ImuNoise(), stated, "/imu")
        opts = LogOptions(calib=world_and_calib, imu_calib=imu_yaml)
        flight = open_flight(bag, opts)
        found = [w for w in flight.warnings if w.name == "rate_mismatch"]
        if said is None:
            assert not found, found
            continue
        (w,) = found
        assert w.count == 1
        assert w.message == f"{bag}: topic /imu: samples every 10 ms (100 Hz) but {imu_yaml} says {said}"
        assert f"[rate_mismatch] x1: {w.message}" in inspect_log(bag, opts).problems


def test_a_bag_read_with_an_euroc_calibration_folder_checks_its_imu_rate_hz(tmp_path, world_and_calib):
    """`--calib FOLDER` (an EuRoC folder's mav0/*/sensor.yaml as the calibration): its
    imu0/sensor.yaml `rate_hz` is a stated rate like Kalibr's update_rate, checked against the
    bag's IMU stamps (it was read for the noise and mount only)."""
    from fusion.camera import CameraModel

    bag = _write_bag(tmp_path / "slow.mcap", _images(5), imu_samples=_resting_imu())  # IMU 100 Hz
    mav = tmp_path / "calib" / "mav0"
    (mav / "cam0").mkdir(parents=True)
    (mav / "imu0").mkdir()
    CameraModel(32, 24, 50.0, 50.0, 16.0, 12.0).save(mav / "cam0" / "sensor.yaml")
    noise = {k: float(v) for k, v in vars(euroc.ImuNoise()).items()}
    for stated, expect in ((100.0, False), (200.0, True)):
        imu_yaml = mav / "imu0" / "sensor.yaml"
        imu_yaml.write_text(yaml.safe_dump({**noise, "rate_hz": stated}))
        flight = open_flight(bag, LogOptions(calib=tmp_path / "calib", world=tmp_path / "world.yaml"))
        found = [w for w in flight.warnings if w.name == "rate_mismatch"]
        if not expect:
            assert not found, found
            continue
        (w,) = found
        assert w.message == f"{bag}: topic /imu: samples every 10 ms (100 Hz) but {imu_yaml} says rate_hz 200"


def _as_sqlite3(mcap: Path, folder: Path) -> Path:
    """The ROS 2 bag `mcap` rewritten with sqlite3 storage into `folder` (metadata.yaml + .db3)."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as W2

    ts = typestore_for(False)
    with (
        AnyReader([mcap], default_typestore=ts) as r,
        W2(folder, version=8, storage_plugin=StoragePlugin.SQLITE3) as w,
    ):
        conns = {c.id: w.add_connection(c.topic, c.msgtype, typestore=ts) for c in r.connections}
        for c, t, raw in r.messages():
            w.write(conns[c.id], t, raw)
    return folder


def test_damaged_sqlite3_bags_read_what_is_there(tmp_path, world_and_calib, monkeypatch):
    """A .db3 cut short ("malformed" to SQLite) reads up to the damage; a folder whose recording
    never wrote metadata.yaml reads whole; both with a bag_truncated warning."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    imgs = _images(30)
    good = _as_sqlite3(_write_bag(tmp_path / "g.mcap", imgs), tmp_path / "good")
    opts = LogOptions(calib=world_and_calib)
    full = open_flight(good, opts)
    assert len(full.floor) == 30 and not [w for w in full.warnings if w.name == "bag_truncated"]

    def damage(f):
        return [w.message for w in f.warnings if w.name == "bag_truncated"]

    nometa = tmp_path / "nometa"
    shutil.copytree(good, nometa)
    (nometa / "metadata.yaml").unlink()
    flight = open_flight(nometa, opts)
    np.testing.assert_array_equal(flight.floor.timestamps_ns, full.floor.timestamps_ns)
    assert len(damage(flight)) == 1 and "no usable metadata.yaml" in damage(flight)[0]
    cut = tmp_path / "cut"
    shutil.copytree(good, cut)
    db = next(cut.glob("*.db3"))
    db.write_bytes(db.read_bytes()[: int(db.stat().st_size * 0.5)])
    flight = open_flight(cut, opts)
    n = len(flight.floor)
    assert 0 < n < 30
    np.testing.assert_array_equal(flight.floor.timestamps_ns, full.floor.timestamps_ns[:n])
    np.testing.assert_array_equal(flight.floor.load_image(n - 1), imgs[n - 1])
    (note,) = damage(flight)
    assert "stopped after" in note and "malformed" in note
    db.write_bytes(b"SQLite format 3\x00" + bytes(50))
    with pytest.raises(LogError, match=r"cut.*not an SQLite database"):
        open_flight(cut, opts)


def test_an_intact_bare_db3_file_is_not_called_truncated(tmp_path, world_and_calib, monkeypatch):
    """A .db3 file given alone (no metadata.yaml beside it: a .db3 has none of its own) and read
    whole is no damaged bag: it was a `bag_truncated` warning ("damaged ... no usable
    metadata.yaml") with nothing missing.  Cut short, it still is one."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    good = _as_sqlite3(_write_bag(tmp_path / "g.mcap", _images(30)), tmp_path / "good")
    opts = LogOptions(calib=world_and_calib)
    db = tmp_path / "bare.db3"  # beside world.yaml
    shutil.copy(next(good.glob("*.db3")), db)
    flight = open_flight(db, opts)
    assert len(flight.floor) == 30 and not [w for w in flight.warnings if w.name == "bag_truncated"]
    cut = tmp_path / "cut.db3"
    cut.write_bytes(db.read_bytes()[: int(db.stat().st_size * 0.5)])
    (note,) = [w.message for w in open_flight(cut, opts).warnings if w.name == "bag_truncated"]
    assert "stopped after" in note


def test_a_bare_db3_files_unknown_types_are_counted_not_called_damage(tmp_path, world_and_calib, monkeypatch):
    """A .db3 file given alone and read whole, with messages of a type the reader does not know:
    they are left out of the copy it reads, and that is what the warning says
    (`bag_unknown_types_left_out`, count: the messages, naming topic and type), in a run and in
    `fusion inspect`.  It was a `bag_truncated` "damaged ... bag" with nothing missing."""
    import sqlite3
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    good = _as_sqlite3(
        _write_bag(tmp_path / "g.mcap", _images(10), imu_samples=_resting_imu()), tmp_path / "good"
    )
    db = tmp_path / "bare.db3"  # beside world.yaml
    shutil.copy(next(good.glob("*.db3")), db)
    con = sqlite3.connect(db)
    with con:
        con.execute("INSERT INTO topics VALUES (9, '/thing', 'my_msgs/msg/Thing', 'cdr', '', '')")
        con.executemany(
            "INSERT INTO messages (topic_id, timestamp, data) VALUES (9, ?, x'00010000')",
            [(1_000_000_000 + k,) for k in range(4)],
        )
    con.close()
    opts = LogOptions(calib=world_and_calib)
    flight = open_flight(db, opts)
    assert len(flight.floor) == 10 and not [w for w in flight.warnings if w.name == "bag_truncated"]
    (w,) = [w for w in flight.warnings if w.name == "bag_unknown_types_left_out"]
    assert w.count == 4 and str(db) in w.message and "/thing (my_msgs/msg/Thing): 4" in w.message
    assert "damaged" not in w.message
    (problem,) = inspect_log(db, opts).problems
    assert problem.startswith("[bag_unknown_types_left_out] x4: ") and "damaged" not in problem


def test_bag_stamp_problems_are_named_counted_warnings(tmp_path, world_and_calib):
    stamps = [1_000_000_000, 1_200_000_000, 1_100_000_000, 1_300_000_000, 1_300_000_000]
    logt = [2_000_000_000 + k * 1000 for k in range(5)]  # recorded in this (header-unsorted) order
    bag = _write_bag(tmp_path / "b.mcap", _images(5), stamps=stamps, log_times=logt)
    flight = open_flight(bag, LogOptions(calib=world_and_calib))
    got = {(w.name, w.count) for w in flight.warnings}
    assert {("stamps_out_of_order", 1), ("stamps_duplicate", 1)} <= got
    assert not any(w.name == "bag_truncated" for w in flight.warnings)
    # a camchain without imu.yaml: the IMU noise is the defaults', said once
    assert ("imu_noise_default", 1) in got


def test_cli_inspect_import_export(tmp_path, bags, capsys):
    assert main(["inspect", str(bags["mcap"])]) == 0
    out = capsys.readouterr().out
    assert "/cam0/image_raw" in out and "floor camera" in out and "accel OK" in out
    assert main(["export", str(SAMPLE), str(tmp_path / "x.bag")]) == 0
    assert main(["inspect", str(tmp_path / "x.bag")]) == 0
    assert "/cam0/image_raw              sensor_msgs/msg/Image                 51" in capsys.readouterr().out
    assert main(["import", str(bags["png"]), str(tmp_path / "x")]) == 0
    assert euroc.read_flight(tmp_path / "x").floor.timestamps_ns.size == 8
    assert main(["inspect", str(tmp_path / "nothing.bag")]) == 1
    assert "nothing.bag: not found" in capsys.readouterr().err


def test_inspect_names_a_topic_recorded_with_two_message_types(tmp_path, capsys):
    """rosbags gives such a topic the msgtype None; `fusion inspect` used to end in a TypeError
    traceback formatting it.  Now the topic is listed as MIXED_MSGTYPES and the run ends normally."""
    from rosbags.rosbag1 import Writer

    from fusion.log.rosbag import MIXED_MSGTYPES

    ts = typestore_for(True)
    bag = tmp_path / "mixed.bag"
    with Writer(bag) as w:
        for k, (ty, value) in enumerate([("std_msgs/msg/String", "ok"), ("std_msgs/msg/Int32", 3)]):
            con = w.add_connection("/status", ty, typestore=ts)
            w.write(con, 1_000_000_000 + k * 100_000_000, ts.serialize_ros1(ts.types[ty](data=value), ty))
    rep = inspect_log(bag, LogOptions())
    assert [(s.name, s.msgtype, s.count) for s in rep.streams] == [("/status", MIXED_MSGTYPES, 2)]
    assert main(["inspect", str(bag)]) == 0
    out = capsys.readouterr().out
    assert f"/status                      {MIXED_MSGTYPES}" in out
    assert f"the bag holds /status ({MIXED_MSGTYPES})" in out


@pytest.mark.parametrize("fmt,name", [("rosbag2", "s.mcap"), ("rosbag1", "s.bag"), ("video", "s")])
def test_simulate_writes_every_format(tmp_path, fmt, name):
    from fusion.log import ImuNoise
    from fusion.sim.simulate import simulate

    # every option reaches the conversion path too (the velocity's own rate was once dropped)
    res = simulate(
        tmp_path / "s",
        duration_s=0.4,
        camera_rate_hz=10,
        workers=1,
        progress=False,
        fmt=fmt,
        velocity_rate_hz=5.0,
        imu_noise_stated=0.5,
    )
    assert res.root == tmp_path / name and res.root.exists()
    assert not (tmp_path / "s.euroc").exists()
    flight = open_flight(res.root)
    assert len(flight.floor) == res.n_frames and len(flight.imu.timestamps_ns) == res.n_imu
    assert flight.floor.load_image(0).shape == (480, 640)
    assert len(flight.velocity.timestamps_ns) == 3  # 0, 200, 400 ms
    stated = flight.imu.noise.gyroscope_noise_density
    assert stated == pytest.approx(0.5 * ImuNoise().gyroscope_noise_density)


def test_roles_by_type_and_overrides(tmp_path):
    from fusion.log.rosbag import ODOMETRY, TWIST, assign_roles

    types = {
        "/a/image": IMAGE,
        "/b/image": COMPRESSED,
        "/imu": IMU,
        "/odom": ODOMETRY,
        "/fusion/groundtruth": ODOMETRY,
    }
    r = assign_roles(tmp_path, types, LogOptions())
    assert (r.floor, r.front, r.imu, r.velocity) == ("/a/image", "/b/image", "/imu", "/odom")
    r = assign_roles(tmp_path, types, LogOptions(floor_topic="/b/image"))
    assert (r.floor, r.front) == ("/b/image", "/a/image")
    r = assign_roles(tmp_path, types, LogOptions(front_topic="none", velocity_topic="none"))
    assert (r.floor, r.front, r.velocity) == ("/a/image", None, None)  # e.g. EuRoC's stereo
    # Kalibr's rostopic names the floor camera (cam0)
    r = assign_roles(tmp_path, types, LogOptions(), kalibr_topics={"cam0": "/b/image"})
    assert (r.floor, r.front) == ("/b/image", "/a/image")
    # TwistStamped is preferred to Odometry; two of a kind need an override
    r = assign_roles(tmp_path, {**types, "/tw": TWIST}, LogOptions())
    assert r.velocity == "/tw"
    with pytest.raises(LogError, match=r"2 IMU topics \(/imu, /imu2\); say which with --imu-topic"):
        assign_roles(tmp_path, {**types, "/imu2": IMU}, LogOptions())
    assert assign_roles(tmp_path, {**types, "/imu2": IMU}, LogOptions(imu_topic="/imu2")).imu == "/imu2"
    with pytest.raises(LogError, match=r"3 image topics"):
        assign_roles(tmp_path, {**types, "/c/image": IMAGE}, LogOptions())
    # the floor topic named and two others left: no front camera, and the reader's named warning
    # (`bag_image_topics_unused`) says which topics were passed over
    r = assign_roles(tmp_path, {**types, "/c/image": IMAGE}, LogOptions(floor_topic="/c/image"))
    assert (r.floor, r.front, r.unused_images) == ("/c/image", None, ["/a/image", "/b/image"])
    assert assign_roles(tmp_path, types, LogOptions()).unused_images == []
    # one topic in both camera roles (thirty-first session's audit: 0 loads, health ok)
    with pytest.raises(LogError, match=r"topic /a/image given as both the floor and the front camera"):
        assign_roles(tmp_path, types, LogOptions(floor_topic="/a/image", front_topic="/a/image"))


def test_euroc_folder_as_calibration_for_a_bag(tmp_path, sample):
    """The EuRoC dataset's own bags: images + IMU only, the calibration in the folder's
    sensor.yaml files (--calib FOLDER)."""
    from fusion.camera import CameraModel
    from fusion.geometry import make_T, rot_z

    sample.world.save(tmp_path / "world.yaml")
    cam = CameraModel(32, 24, 50.0, 50.0, 16.0, 12.0, T_body_cam=make_T(rot_z(0.2), [0, 0, 0.1]))
    calib = tmp_path / "calib"
    (calib / "mav0" / "cam0").mkdir(parents=True)
    cam.save(calib / "mav0" / "cam0" / "sensor.yaml")
    with euroc.FlightLogWriter(tmp_path / "tmp") as w:  # just for its imu0/sensor.yaml
        w.write_imu(
            euroc.ImuData(
                np.arange(3), np.zeros((3, 3)), np.zeros((3, 3)), euroc.ImuNoise(1e-4, 1e-5, 1e-3, 1e-4)
            )
        )
    shutil.copytree(tmp_path / "tmp" / "mav0" / "imu0", calib / "mav0" / "imu0")
    bag = _write_bag(tmp_path / "euroc.bag", _images(4))
    flight = open_flight(bag, LogOptions(calib=calib))
    np.testing.assert_array_equal(flight.floor.camera.T_body_cam, cam.T_body_cam)
    assert flight.imu.noise == euroc.ImuNoise(1e-4, 1e-5, 1e-3, 1e-4)
    np.testing.assert_allclose(flight.imu.accel_m_s2[0], [0, 0, 9.81])
    np.testing.assert_allclose(flight.imu.gyro_rad_s[0], [0.01, 0, 0])
    assert flight.front is None and flight.velocity is None


def test_detection_in_worker_processes_after_the_parent_read(bags, tmp_path):
    """Forked detection workers must not read through a reader the parent left open (shared
    file offsets): same detections as in one process."""
    from fusion.qr.detect import detect_flight

    flight = open_flight(bags["mcap"])
    for s in flight.cameras.values():
        s.load_image(3)  # parent opens its reader, iterator mid-bag
    par = detect_flight(flight, workers=2, progress=False, chunk_frames=3)
    one = detect_flight(open_flight(bags["mcap"]), workers=1, progress=False)
    assert len(one.detections) > 5 and not par.skipped
    assert [(d.camera, d.timestamp_ns, d.payload, d.corners_px.tolist()) for d in par.detections] == [
        (d.camera, d.timestamp_ns, d.payload, d.corners_px.tolist()) for d in one.detections
    ]
    # the guard itself: a stream used from another process id reopens its reader
    s = flight.floor
    reader = s._reader
    s._pid = -1  # as seen from a forked child
    np.testing.assert_array_equal(s.load_image(4), open_flight(bags["mcap"]).floor.load_image(4))
    assert s._reader is not reader and s._pid > 0


def test_export_never_overwrites_its_source_or_a_folder_not_its_own(tmp_path, bags, sample):
    """`export X.bag X.bag --force` deleted the bag before reading its images and wrote one
    without them; `export LOG DIR --force` deleted any folder at DIR (thirty-first session's
    second audit).  --force replaces only a previous export of the same kind."""
    bag = tmp_path / "self.bag"
    shutil.copy(bags["bag"], bag)
    size = bag.stat().st_size
    with pytest.raises(LogError, match="is, holds or lies inside the log being exported"):
        export_flight(bag, bag, overwrite=True)
    assert bag.stat().st_size == size
    mine = tmp_path / "mydata"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me\n")
    with pytest.raises(LogError, match="is not a previous video export"):
        export_flight(sample, mine, overwrite=True)
    assert (mine / "notes.txt").read_text() == "keep me\n"
    (tmp_path / "x.mcap").mkdir()
    with pytest.raises(LogError, match="is a folder, not a previous .mcap export"):
        export_flight(sample, tmp_path / "x.mcap", overwrite=True)
    video = export_flight(sample, tmp_path / "video")
    assert export_flight(sample, video, overwrite=True) == video  # a previous export: replaced
    again = export_flight(sample, tmp_path / "again.bag")
    assert export_flight(sample, again, overwrite=True) == again


def test_export_says_what_the_copy_lost(tmp_path, capsys):
    """An export wrote only the frames that decode and said nothing: the copy read as a clean
    camera (second audit).  It prints the frames left out, as `import` does."""
    log = tmp_path / "log"
    shutil.copytree(SAMPLE, log)
    bad = sorted((log / "mav0" / "cam0" / "data").iterdir())[3]
    bad.write_bytes(b"\\x89PNG\\r\\n\\x1a\\n corrupt")
    assert main(["export", str(log), str(tmp_path / "x.mcap")]) == 0
    out = capsys.readouterr().out
    assert "warning: [frames_skipped] x1: cam0: frames that could not be read were left out" in out
