"""`inspect_log`: what a log holds, whatever its format - streams (topics), types, counts, rates,
durations, gaps, out-of-order and duplicate stamps, which stream fills which role, whether
the IMU's units look like rad/s and m/s^2, and the plausibility warnings a run would give about
the log (euroc.check_log: rate_mismatch, imu_saturated, ...)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import GRAVITY_M_S2
from fusion.errors import LogError
from fusion.log.options import LogFormat, LogOptions, StampSource
from fusion.log.sources import detect_format, open_flight
from fusion.types import CameraRole
from fusion.world import Placement, World

if TYPE_CHECKING:  # rosbag (and rosbags) imported when a bag is inspected
    from fusion.log.rosbag import BagPass

GAP_FACTOR = 2.5
"""A step longer than this many median steps is a gap."""
ACCEL_G_RANGE_M_S2 = (0.5, 1.5)  # median |a| here: the accelerometer logs in g
ACCEL_OK_RANGE_M_S2 = (0.8 * GRAVITY_M_S2, 1.2 * GRAVITY_M_S2)
GYRO_DEG_S_SUSPECT_RAD_S = 20.0  # 99th percentile |w| above this: probably deg/s
GYRO_PERCENTILE = 99
ROLE_NAMES = {
    CameraRole.FLOOR.value: "floor camera",
    CameraRole.FRONT.value: "front camera",
    "imu0": "IMU",
    "vel0": "velocity",
    "groundtruth": "ground truth",
}


@dataclass
class StreamStats:
    name: str  # topic or stream name
    msgtype: str
    count: int
    rate_hz: float | None
    duration_s: float
    n_gaps: int
    max_gap_s: float
    n_out_of_order: int
    n_duplicates: int
    role: str = ""


@dataclass
class LogReport:
    path: Path
    format: LogFormat
    stamps: StampSource
    streams: list[StreamStats] = field(default_factory=list)
    roles: dict[str, str] = field(default_factory=dict)  # role -> stream
    imu_units: str = ""
    problems: list[str] = field(default_factory=list)
    calibration: list[str] = field(default_factory=list)  # per camera: how well it is known

    def format_text(self) -> str:
        bag = self.format in (LogFormat.ROSBAG1, LogFormat.ROSBAG2)
        clock = 'header stamps' if self.stamps == StampSource.HEADER else 'receive time'
        lines = [f"{self.path}: {self.format.value} log" + (f", times from {clock}" if bag else "")]
        head = (
            f"{'stream':<28} {'type':<32} {'count':>7} {'rate Hz':>8} {'dur s':>8} "
            f"{'gaps':>5} {'max gap s':>9} {'back':>5} {'dup':>5}  role"
        )
        lines.append(head)
        for s in self.streams:
            rate = f"{s.rate_hz:8.2f}" if s.rate_hz else f"{'-':>8}"
            lines.append(
                f"{s.name[:28]:<28} {s.msgtype[:32]:<32} {s.count:7d} {rate} "
                f"{s.duration_s:8.2f} {s.n_gaps:5d} {s.max_gap_s:9.3f} "
                f"{s.n_out_of_order:5d} {s.n_duplicates:5d}  {s.role}"
            )
        for role in (CameraRole.FLOOR.value, CameraRole.FRONT.value, "imu0", "vel0"):
            lines.append(f"{ROLE_NAMES[role]:<13}: {self.roles.get(role, '(none)')}")
        if self.imu_units:
            lines.append(f"IMU units    : {self.imu_units}")
        lines += self.calibration
        for p in self.problems:
            lines.append(f"problem: {p}")
        return "\n".join(lines)


def calibration_line(name: str, camera: CameraModel) -> str:
    """How well a camera's calibration is known, as the run will take it: its intrinsics' and
    mount's 1-sigma, stated in sensor.yaml (or the camchain) or assumed (the defaults)."""
    fu, fv, cu, cv = camera.intrinsics_sigmas
    intr = "stated" if camera.intrinsics_sigma_px is not None else "assumed: not in sensor.yaml"
    deg, m = camera.mount_sigmas
    if camera.mount_sigma_deg is not None or camera.mount_sigma_m is not None:
        mount = f"mount sigma {math.degrees(deg):.3g} deg, {1000 * m:.3g} mm (stated)"
    elif name == CameraRole.FLOOR.value and not camera.gimbaled:
        # an unstated floor mount adds nothing to the poses: the run's mount check measures it
        mount = "mount sigma not stated (the run's mount check measures it)"
    else:
        mount = f"mount sigma {math.degrees(deg):.3g} deg, {1000 * m:.3g} mm (assumed: not in sensor.yaml)"
    px = f"fu {fu:.3g} fv {fv:.3g} cu {cu:.3g} cv {cv:.3g} px"
    return f"{name} calib  : intrinsics sigma {px} ({intr}); {mount}"


def lens_line(name: str, camera: CameraModel) -> str:
    """The camera model as the run will use it: size, intrinsics and distortion (model and
    coefficients), so that a user sees whether a fisheye or OpenCV's k3 was read."""
    k = ", ".join(f"{v:.4g}" for v in camera.dist_cv[: 4 if camera.equidistant or not camera.k3 else 5])
    names = "k1..k4" if camera.equidistant else ("k1, k2, p1, p2, k3" if camera.k3 else "k1, k2, p1, p2")
    size = f"{camera.width}x{camera.height}"
    f = f"f {camera.fu:.1f} / {camera.fv:.1f}, c {camera.cu:.1f} / {camera.cv:.1f} px"
    return f"{name} lens   : {size}, {f}; {camera.distortion_model} [{k}] ({names})"


def placement_line(world: World) -> str:
    """How exactly the floor codes lie on their payloads, as PnP and the back ends will take it
    (world.Placement: world.yaml's floor_qr.placement_sigma_m / _deg, or the defaults)."""
    p = Placement.from_world(world)
    stated = world.placement_sigma_m is not None or world.placement_sigma_deg is not None
    how = "stated" if stated else "assumed: not in world.yaml"
    if not p.enabled:
        return f"floor codes: laid exactly on their payloads ({how})"
    sigma = f"{100 * p.sigma_m:.3g} cm, {math.degrees(p.sigma_rad):.3g} deg"
    return f"floor codes: placement sigma {sigma} ({how})"


def time_stats(name: str, msgtype: str, t_ns, role: str = "") -> StreamStats:
    """Statistics of a stream's times as recorded (unsorted)."""
    t = np.asarray(t_ns, np.int64)
    n = len(t)
    if n < 2:
        return StreamStats(name, msgtype, n, None, 0.0, 0, 0.0, 0, 0, role)
    d = np.diff(t)
    ts = np.sort(t)
    steps = np.diff(ts)
    pos = steps[steps > 0]
    med = float(np.median(pos)) if len(pos) else 0.0
    gaps = steps[steps > GAP_FACTOR * med] if med > 0 else np.zeros(0)
    return StreamStats(
        name,
        msgtype,
        n,
        1e9 / med if med > 0 else None,
        float(ts[-1] - ts[0]) * 1e-9,
        int(len(gaps)),
        float(gaps.max()) * 1e-9 if len(gaps) else 0.0,
        int(np.sum(d < 0)),
        int(np.sum(steps == 0)),
        role,
    )


def imu_units_verdict(gyro_rad_s: np.ndarray, accel_m_s2: np.ndarray) -> str:
    """A one-line check that the IMU logs rad/s and m/s^2 (gravity included)."""
    a = float(np.median(np.linalg.norm(accel_m_s2, axis=1)))
    w = float(np.percentile(np.linalg.norm(gyro_rad_s, axis=1), GYRO_PERCENTILE))
    notes = []
    if ACCEL_OK_RANGE_M_S2[0] <= a <= ACCEL_OK_RANGE_M_S2[1]:
        notes.append(f"accel OK (median |a| {a:.2f} m/s^2, gravity {GRAVITY_M_S2})")
    elif ACCEL_G_RANGE_M_S2[0] <= a <= ACCEL_G_RANGE_M_S2[1]:
        notes.append(f"accel looks like g, not m/s^2 (median |a| {a:.2f})")
    else:
        notes.append(
            f"accel suspicious (median |a| {a:.2f}, expected about {GRAVITY_M_S2}: "
            "gravity missing or wrong units)"
        )
    if w > GYRO_DEG_S_SUSPECT_RAD_S:
        notes.append(f"gyro looks like deg/s ({GYRO_PERCENTILE}th percentile |w| {w:.1f})")
    else:
        notes.append(f"gyro OK ({GYRO_PERCENTILE}th percentile |w| {w:.2f} rad/s)")
    return "; ".join(notes)


def inspect_log(path: Path, opts: LogOptions | None = None) -> LogReport:
    """Inspect any supported log (bags topic by topic; other formats stream by stream)."""
    opts = opts or LogOptions()
    path = Path(path)
    fmt = detect_format(path)
    report = LogReport(path, fmt, opts.stamps)
    if fmt in (LogFormat.ROSBAG1, LogFormat.ROSBAG2):
        _inspect_bag(path, opts, report)
    else:
        _inspect_flight(path, opts, report)
    return report


def _inspect_flight(path: Path, opts: LogOptions, report: LogReport) -> None:
    flight = open_flight(path, opts)
    # the reader's named warnings, as `fusion run` gives them: its streams come sorted, so a
    # stamp out of order, say, would otherwise show nowhere (a bag's are counted per topic)
    report.problems += [str(w) for w in flight.warnings]
    for name, cam in sorted(flight.cameras.items()):
        kind = type(cam).__name__.replace("CameraStream", "").lower() or "images"
        report.streams.append(time_stats(name, f"camera ({kind})", cam.timestamps_ns, ROLE_NAMES[name]))
        report.roles[name] = name
        report.calibration.append(lens_line(name, cam.camera))
        report.calibration.append(calibration_line(name, cam.camera))
    report.calibration.append(placement_line(flight.world))
    if flight.imu is not None:
        report.streams.append(time_stats("imu0", "imu", flight.imu.timestamps_ns, "IMU"))
        report.roles["imu0"] = "imu0"
        report.imu_units = imu_units_verdict(flight.imu.gyro_rad_s, flight.imu.accel_m_s2)
    if flight.velocity is not None:
        report.streams.append(time_stats("vel0", "velocity", flight.velocity.timestamps_ns, "velocity"))
        report.roles["vel0"] = "vel0"
    if flight.groundtruth is not None:
        report.streams.append(
            time_stats("groundtruth", "pose", flight.groundtruth.timestamps_ns, "ground truth")
        )


def _inspect_bag(path: Path, opts: LogOptions, report: LogReport) -> None:
    import yaml

    from fusion.log import rosbag as rb
    from fusion.log.sources import external_calibration

    # a damaged bag is read from a recovered copy (rosbag.readable_bag_and_note): its note says
    # so, as `fusion run`'s bag_truncated does, else the counts below read as the recording's
    left_out: list = []  # a sqlite3 copy's messages of unknown types, named as a run names them
    bag, damage = rb.readable_bag_and_note(path, left_out)
    if damage:
        report.problems.append(damage)
    report.problems += [str(w) for w in left_out]
    first = rb.scan_bag(bag, first_of={rb.METADATA_TOPIC}, topics={rb.METADATA_TOPIC})
    meta: dict = {}
    if first.topics.get(rb.METADATA_TOPIC) and first.topics[rb.METADATA_TOPIC].first is not None:
        try:
            meta = yaml.safe_load(first.topics[rb.METADATA_TOPIC].first.data) or {}
        except yaml.YAMLError:
            report.problems.append(f"{rb.METADATA_TOPIC} is not YAML")
    roles = None
    try:
        calib = external_calibration(opts)
        roles = rb.assign_roles(path, first.types, opts, calib.topics if calib else None, meta)
    except LogError as e:
        report.problems.append(str(e))
    role_of = {}
    if roles is not None:
        for key, topic in (
            (CameraRole.FLOOR.value, roles.floor),
            (CameraRole.FRONT.value, roles.front),
            ("imu0", roles.imu),
            ("vel0", roles.velocity),
        ):
            if topic:
                report.roles[key] = topic
                role_of[topic] = ROLE_NAMES[key]
    has_truth = first.types.get(rb.GROUNDTRUTH_TOPIC) == rb.ODOMETRY
    if has_truth:
        role_of[rb.GROUNDTRUTH_TOPIC] = ROLE_NAMES["groundtruth"]
    imu_topic = roles.imu if roles else None
    # one pass over every topic, decoding what the run's reader decodes too (its sensors' numbers,
    # each camera's first image and calibration), so that the plausibility check below reads
    # the log from it instead of a second pass over the bag
    vectors = {t for t in (roles.imu, roles.velocity) if t} if roles else set()
    if has_truth:
        vectors.add(rb.GROUNDTRUTH_TOPIC)
    first_of = {t for t, ty in first.types.items() if ty == rb.CAMERA_INFO}
    first_of |= {t for t in (roles.floor, roles.front) if t} if roles else set()
    scan = rb.scan_bag(bag, vectors=vectors, first_of=first_of)
    if scan.truncated:
        report.problems.append(scan.truncated)
    for topic in sorted(scan.types):
        s = scan.topics[topic]
        t = rb.choose_times(s, opts.stamps, str(path)) if s.log_ns else np.zeros(0, np.int64)
        stats = time_stats(topic, scan.types[topic], t, role_of.get(topic, ""))
        if scan.counts.get(topic, stats.count) != stats.count:
            report.problems.append(
                f"{topic}: the index lists {scan.counts[topic]} messages, {stats.count} could be read"
            )
        report.streams.append(stats)
    if imu_topic and scan.topics[imu_topic].data:
        ga = np.array(scan.topics[imu_topic].data, dtype=float)
        report.imu_units = imu_units_verdict(ga[:, :3], ga[:, 3:])
    if roles is not None:
        done = rb.BagPass(bag, damage, left_out, scan, vectors, first_of)
        report.problems += _bag_plausibility(path, opts, done)


def _bag_plausibility(path: Path, opts: LogOptions, done: BagPass) -> list[str]:
    """The log's plausibility warnings as `fusion run` gives them (euroc.check_log: imu_saturated,
    imu_gaps, clock_offset, ...) for a bag read as the run reads it, from the pass `done`
    (rosbag.BagPass) inspect made over it: an EuRoC folder's or a video's come with open_flight's
    warnings, a bag's were shown by the run only.  A bag the run could not read is said to be
    unchecked, with the reason."""
    from fusion.log.euroc import check_log
    from fusion.log.rosbag import read_bag

    try:
        return [str(w) for w in check_log(read_bag(path, opts, done))]
    except LogError as e:
        return [f"plausibility not checked, the run could not read the log: {e}"]
