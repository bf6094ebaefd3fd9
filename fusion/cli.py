"""`fusion` command line: parse arguments, call the library, print.  No maths here.

Known errors (fusion.errors.FusionError) become one line on stderr and exit code 1; anything else
keeps its traceback, because it is a bug.  `--strict` runs exit 3 when an estimate is not trusted.
Ctrl-C (SIGINT), SIGTERM (what `timeout`, Slurm, `docker stop` and systemd send) and SIGHUP stop a
command the same way: its partial outputs are removed and its lock released, then one line and
exit code 128 + the signal's number (130, 143, 129).

Each subcommand imports its library module when it runs (the one place where imports sit inside
functions on purpose): `fusion --help` or `fusion qr-sheet` should not load GTSAM, OpenCV,
rosbags and PyAV.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import os
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

from fusion import __version__
from fusion.errors import FusionError
from fusion.types import Estimator

EXIT_NOT_TRUSTED = 3
"""`--strict`: the run finished and wrote its outputs, but an estimate cannot be trusted."""
EXIT_FLIGHTS_FAILED = 4
"""`batch`: the batch finished and wrote its summary, but some flights failed (fleet.md says why)."""


EXIT_INTERRUPTED = 128 + signal.SIGINT
"""Ctrl-C; a SIGTERM or SIGHUP exits 128 + its number (143, 129), as a shell reports them."""
STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


class Stopped(KeyboardInterrupt):
    """SIGTERM / SIGHUP, raised in the main thread as Ctrl-C raises KeyboardInterrupt, so that
    everything that cleans up after Ctrl-C (an output folder's roll-back and lock, a flight
    log's `.partial`, worker pools, a batch's cluster) cleans up after these too."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


@contextlib.contextmanager
def _stop_on_signals() -> Iterator[None]:
    """While the command runs, SIGTERM and SIGHUP raise `Stopped`; the previous handlers are
    restored afterwards.  A signal already ignored (`nohup`) stays ignored.  Repeats are ignored
    while the clean-up runs (it should finish; SIGKILL, which a supervisor sends after its grace
    period, still ends it).  Only this process: the workers are fresh interpreters (forkserver
    or spawn; dask's nanny spawns), which start with the default handlers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {s: signal.getsignal(s) for s in STOP_SIGNALS}

    def stop(signum, _frame):
        for s in previous:
            if previous[s] is not signal.SIG_IGN:
                signal.signal(s, signal.SIG_IGN)
        raise Stopped(signum)

    for s, handler in previous.items():
        if handler is not signal.SIG_IGN:
            signal.signal(s, stop)
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler if handler is not None else signal.SIG_DFL)


def _grid(text: str) -> tuple[int, int]:
    try:
        nx, ny = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected NXxNY like 10x6, got {text!r}") from None
    if nx < 1 or ny < 1:
        raise argparse.ArgumentTypeError("grid sizes must be positive")
    return nx, ny


def _workers(text: str) -> int:
    """--workers: a process count of at least 1 (0 and negative counts were taken as 1, silently)."""
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number of processes, got {text!r}") from None
    if n < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {n} (leave it out for all cores)")
    return n


def _time_offsets_ms(text: str) -> dict[str, float]:
    """--time-offset-ms: {camera: offset in s} (fusion.estimate.timeoffset.parse_time_offsets_ms)."""
    from fusion.estimate.timeoffset import parse_time_offsets_ms

    try:
        return parse_time_offsets_ms(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _clock_drift_ppm(text: str) -> dict[str, float]:
    """--clock-drift-ppm: "PPM" or "cam0=PPM,cam1=PPM" -> {camera: ppm} (the offsets' syntax)."""
    return {k: v * 1e3 for k, v in _time_offsets_ms(text).items()}  # parsed as ms, given in s


TIME_OFFSET_HELP = (
    "camera-IMU clock offsets in ms, t_imu = t_cam + offset (Kalibr's timeshift_cam_imu sign): "
    "MS for both cameras, or cam0=MS,cam1=MS (a camera left out is estimated).  Default: both "
    "estimated around Kalibr's timeshift_cam_imu (--calib), or 0"
)


def _add_camera_effect_options(p: argparse.ArgumentParser) -> None:
    """`fusion simulate`'s camera effects and lens changes (fusion.sim.scenarios.CameraOptions)."""
    g = p.add_argument_group("camera effects (on top of the scenario's 2 DN noise and 8 ms exposure)")
    g.add_argument(
        "--camera-effects",
        choices=("none", "realistic"),
        default="none",
        help="preset: realistic = JPEG 80, noise 4 DN + shot noise, 20 ms exposure, 30%% vignetting; "
        "the options below override it",
    )
    g.add_argument("--jpeg", type=int, default=None, metavar="Q", help="JPEG quality 1..100")
    g.add_argument("--noise", type=float, default=None, metavar="DN", help="read noise, DN (1 sigma)")
    g.add_argument("--shot-noise", type=float, default=None, metavar="G", help="shot noise variance per DN")
    g.add_argument("--exposure", type=float, default=None, metavar="S", help="exposure (s): motion blur")
    g.add_argument("--defocus", type=float, default=None, metavar="PX", help="defocus disc radius (px)")
    g.add_argument("--vignetting", type=float, default=None, metavar="V", help="corner light loss 0..1")
    g.add_argument("--overexposure", type=float, default=None, metavar="G", help="gain, >1 clips")
    g.add_argument("--contrast", type=float, default=None, metavar="C", help="scene contrast kept (0..1]")
    g.add_argument("--glare", type=float, default=None, metavar="F", help="glare over F of each code")
    g.add_argument("--occlusion", type=float, default=None, metavar="F", help="fraction of each code hidden")
    g.add_argument("--focal-scale", type=float, default=None, metavar="S", help="focal lengths times S")
    g.add_argument(
        "--distortion",
        type=float,
        nargs=4,
        default=None,
        metavar=("K1", "K2", "P1", "P2"),
        help="both cameras' distortion coefficients (radial-tangential k1 k2 p1 p2; equidistant k1..k4)",
    )
    g.add_argument(
        "--distortion-model",
        choices=("radtan", "equidistant"),
        default=None,
        help="both cameras' distortion model (default: the scenario's, radtan); equidistant is "
        "Kalibr's pinhole-equi (OpenCV's fisheye), for wide-angle lenses",
    )


def _camera_options(args):
    from fusion.sim.scenarios import CameraOptions

    return CameraOptions.preset(
        args.camera_effects,
        jpeg_quality=args.jpeg,
        noise_dn=args.noise,
        shot_noise_dn=args.shot_noise,
        exposure_s=args.exposure,
        defocus_px=args.defocus,
        vignetting=args.vignetting,
        overexposure=args.overexposure,
        contrast=args.contrast,
        glare_fraction=args.glare,
        occlusion_fraction=args.occlusion,
        focal_scale=args.focal_scale,
        distortion=tuple(args.distortion) if args.distortion is not None else None,
        distortion_model=args.distortion_model,
    )


def _add_log_options(p: argparse.ArgumentParser) -> None:
    """How to read a log that is not an EuRoC folder (fusion.log.LogOptions)."""
    g = p.add_argument_group("log input (ROS bags, video; ignored for EuRoC folders)")
    g.add_argument("--floor-topic", help="floor camera topic (default: found by type)")
    g.add_argument(
        "--front-topic", help="front camera topic (default: found by type; 'none': no front camera)"
    )
    g.add_argument("--imu-topic", help="sensor_msgs/Imu topic (default: found by type)")
    g.add_argument(
        "--velocity-topic", help="TwistStamped or Odometry topic (default: by type; 'none': ignore)"
    )
    g.add_argument(
        "--stamps",
        choices=("header", "receive"),
        default="header",
        help="bag message times: header stamps (default) or the bag's receive time",
    )
    g.add_argument(
        "--calib", type=Path, help="Kalibr camchain-imucam.yaml (cam0 floor, cam1 front), or an EuRoC folder"
    )
    g.add_argument("--imu-calib", type=Path, help="Kalibr imu.yaml (noise densities)")
    g.add_argument("--world", type=Path, help="world.yaml (default: in or next to the log)")
    g.add_argument("--front-video", type=Path, help="front camera video (video logs)")
    g.add_argument(
        "--frame-times", type=Path, help="floor video frame times CSV, ns per frame (default VIDEO.csv)"
    )
    g.add_argument("--front-frame-times", type=Path, help="front video frame times CSV")
    g.add_argument("--imu", type=Path, help="IMU CSV (EuRoC imu0 columns) or PX4 ULog (.ulg)")
    g.add_argument("--video-fps", type=_frame_rate, help="constant video rate (without frame times)")
    g.add_argument(
        "--video-start-ns",
        type=_start_ns,
        help="first frame's time in the IMU clock (constant-rate video)",
    )


def _frame_rate(text: str) -> float:
    """--video-fps: a finite rate > 0 (nan had stamped every frame INT64_MIN, -30 run the clock
    backwards, 0 fallen back to the container's rate)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a frame rate in Hz: {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"{text}: the frame rate must be a finite number of Hz > 0")
    return value


def _start_ns(text: str) -> int:
    """--video-start-ns: a time in the IMU clock as a log states one (>= 0, int64, digits only)."""
    from fusion.log.euroc import parse_timestamp_ns

    try:
        return parse_timestamp_ns(text.strip())
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def _log_options(args):
    from fusion.log import LogOptions, StampSource

    return LogOptions(
        floor_topic=args.floor_topic,
        front_topic=args.front_topic,
        imu_topic=args.imu_topic,
        velocity_topic=args.velocity_topic,
        stamps=StampSource(args.stamps),
        calib=args.calib,
        imu_calib=args.imu_calib,
        world=args.world,
        front_video=args.front_video,
        frame_times=args.frame_times,
        front_frame_times=args.front_frame_times,
        imu=args.imu,
        video_fps=args.video_fps,
        video_start_ns=args.video_start_ns,
        cameras_optional=getattr(args, "fixes", None) is not None,
    )


def _flight_arg(args):
    """The log path itself, or the opened FlightLog when a log option was given."""
    from fusion.log import LogOptions, open_flight

    opts = _log_options(args)
    return args.log if opts == LogOptions() else open_flight(args.log, opts)


def _add_fusion_choices(p: argparse.ArgumentParser) -> None:
    """The back ends' choices, shared by `smooth`, `run` and `batch`."""
    p.add_argument(
        "--robust",
        choices=("none", "huber", "cauchy", "tukey"),
        default="huber",
        help="robust kernel on QR pose factors (default: huber)",
    )
    p.add_argument(
        "--tight", action="store_true", help="tight coupling: floor-code corners as reprojection factors"
    )
    p.add_argument("--no-incremental", action="store_true", help="skip the incremental smoother")
    p.add_argument(
        "--smoother-window-s",
        type=_window_seconds,
        default=None,
        metavar="S",
        help="the batch smoother solves flights longer than 5 min in overlapping windows of S seconds "
        "(bounded memory; default 180, 120 with as-built floor codes); 0: always the whole flight",
    )


def _window_seconds(text: str) -> float:
    from fusion.estimate.window import WINDOW_OVERLAP_S

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number of seconds: {text!r}") from None
    if not (value == 0 or (math.isfinite(value) and value > WINDOW_OVERLAP_S)):
        raise argparse.ArgumentTypeError(
            f"{text}: 0 (whole flight) or more than the windows' {WINDOW_OVERLAP_S:g} s overlap"
        )
    return value


TRACK_HELP = (
    "the track pass (default off): floor codes that the pose predicted from the PnP poses puts in "
    "view but that did not decode (blur, glare, occlusion) are found, refined and named from the "
    "prediction, gated by the innovation; counted as tracked sightings"
)


def _add_run_options(p: argparse.ArgumentParser, stages: bool = True, time_offset: bool = True) -> None:
    p.add_argument(
        "log", type=Path, help="flight log: EuRoC folder, ROS 1 .bag, ROS 2 bag folder or .mcap, video"
    )
    _add_log_options(p)
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument(
        "--force",
        action="store_true",
        help="write into an existing output folder: the previous run's outputs (its "
        "manifest.json) are replaced, other files are kept; a flight log is never an output folder",
    )
    p.add_argument(
        "--backend", choices=("zxing", "aruco"), default="zxing", help="QR detector (default: zxing-cpp)"
    )
    p.add_argument(
        "--workers",
        type=_workers,
        default=None,
        help=(
            "processes for detection, per-frame estimates and, from 600 frames, the fusion "
            "back ends (default: all cores)"
        ),
    )
    if p.prog.split()[-1] != "detect":
        p.add_argument(
            "--calibrate-readout",
            action="store_true",
            help="estimate the floor camera's rolling-shutter readout time from the flight "
            "(PnP reprojection cost profile, golden section; reported with its sigma) and use it",
        )
        p.add_argument("--track", action=argparse.BooleanOptionalAction, default=None, help=TRACK_HELP)
    if time_offset:
        p.add_argument("--time-offset-ms", type=_time_offsets_ms, default=None, help=TIME_OFFSET_HELP)
    if stages:
        p.add_argument(
            "--calibrate-extrinsics",
            action="store_true",
            help="estimate the floor camera's mount rotation error (a Rot3 in the batch smoother, "
            "reported with its sigma) and the front camera's (against the floor camera's poses) "
            "and, when significant, apply them to every output",
        )
        _add_fusion_choices(p)
        p.add_argument(
            "--map",
            type=Path,
            default=None,
            help="a merged map (`fusion map merge --out MAP`) of the same warehouse: its as-built "
            "floor codes are the prior of this flight's",
        )
        p.add_argument(
            "--fixes",
            type=Path,
            help="external position fixes CSV (t_ns,x,y,z,sigma_m: GNSS, UWB, total station, "
            "mocap) fused beside the QR poses; a log without cameras is fused from IMU + fixes",
        )
        p.add_argument(
            "--strict",
            action="store_true",
            help=f"exit {EXIT_NOT_TRUSTED} when a fused estimator failed or its health "
            "is not ok (degraded, diverged)",
        )


def _verbosity_options() -> argparse.ArgumentParser:
    """-v / -q, accepted by every subcommand."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("-v", "--verbose", action="count", default=0, help="more log messages (-vv: debug)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars; warnings and errors only")
    return p


def configure_logging(verbose: int, quiet: bool) -> None:
    """Log records of the `fusion` package to stderr: INFO by default, WARNING with -q,
    DEBUG with -vv."""
    level = logging.WARNING if quiet else (logging.DEBUG if verbose >= 2 else logging.INFO)
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(
        logging.Formatter(
            "fusion: %(levelname)s: %(name)s: %(message)s" if verbose else "fusion: %(message)s"
        )
    )
    root = logging.getLogger("fusion")
    root.handlers[:] = [handler]
    root.setLevel(level)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="fusion",
        description="Drone 3D localization and load mapping from QR codes (Kang & Jung 2024), "
        "fused with IMU in GTSAM.",
    )
    parser.add_argument("--version", action="version", version=f"fusion {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    common = _verbosity_options()

    p = sub.add_parser("simulate", parents=[common], help="simulate a warehouse flight log with ground truth")
    p.add_argument("out", type=Path, help="output log folder")
    p.add_argument("--scenario", default="default", help="default | gimbaled | oblique | paper_a5")
    p.add_argument("--duration", type=float, default=None, help="seconds (default: the scenario's)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--resolution",
        type=_grid,
        default=(640, 480),
        help="both cameras' resolution WxH (default 640x480; the focal length scales with the width)",
    )
    p.add_argument("--fps", type=float, default=30.0, help="camera frame rate (default 30)")
    _add_camera_effect_options(p)
    p.add_argument(
        "--start", type=float, default=0.0, help="skip the first S seconds of the scenario's trajectory"
    )
    p.add_argument(
        "--velocity-rate-hz",
        type=float,
        default=None,
        help="the velocity sensor's rate (default: the scenario's 30 Hz, stamped with the frames)",
    )
    p.add_argument(
        "--imu-noise-scale",
        type=float,
        default=1.0,
        metavar="K",
        help="the IMU's noise densities and bias random walks K x the scenario's (a worse IMU, "
        "or one on a vibrating frame; imu0/sensor.yaml states them; default 1)",
    )
    p.add_argument(
        "--imu-noise-stated",
        type=float,
        default=1.0,
        metavar="F",
        help="imu0/sensor.yaml states F x the IMU's true noise (default 1: honest; below 1 an "
        "optimistic datasheet, e.g. without the propellers' vibration)",
    )
    p.add_argument(
        "--readout-ms",
        type=float,
        default=None,
        help="rolling shutter: whole-frame readout time of both cameras, ms, stamped at the "
        "first row (default: the scenario's, 0 = global shutter)",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace a flight log that `fusion simulate` or `import` wrote there (other files are "
        "kept; a folder holding a run's outputs is refused)",
    )
    p.add_argument("--workers", type=_workers, default=None, help="render processes (default: all cores)")
    p.add_argument(
        "--png-compression",
        type=int,
        choices=range(10),
        default=1,
        metavar="0-9",
        help="zlib level of the images (default 1: Huffman-only, Up filter; 0: stored, twice the size, "
        "~7x faster to decode, for throughput benchmarks; 9: smallest)",
    )
    p.add_argument(
        "--placement-error-m",
        type=float,
        default=0.0,
        help="floor codes stuck down off their grid by N(0, this) m per axis (default 0: exactly)",
    )
    p.add_argument(
        "--placement-error-deg",
        type=float,
        default=0.0,
        help="... and by N(0, this) degrees in yaw (default 0)",
    )
    p.add_argument(
        "--placement-seed",
        type=int,
        default=None,
        help="draw the floor codes' placement errors from this seed instead of --seed: flights of "
        "different seeds over one floor (for `fusion map merge`)",
    )
    p.add_argument(
        "--format",
        choices=("euroc", "rosbag1", "rosbag2", "video"),
        default="euroc",
        help="log format: EuRoC folder (default), ROS 1 OUT.bag, ROS 2 OUT.mcap, or "
        "a folder of lossless videos + CSV + Kalibr yaml",
    )
    p.add_argument(
        "--time-offset-ms",
        type=_time_offsets_ms,
        default=None,
        help="camera clock offsets to simulate, ms (t_imu = t_cam + offset: each frame is "
        "stamped its true time minus the offset): MS for both cameras, or cam0=MS,cam1=MS",
    )
    p.add_argument(
        "--clock-drift-ppm",
        type=_clock_drift_ppm,
        default=None,
        help="camera clocks running fast by PPM parts per million (the offset grows by PPM us per "
        "second of flight): PPM for both cameras, or cam0=PPM,cam1=PPM",
    )
    p.add_argument(
        "--stamp-jitter-ms",
        type=_time_offsets_ms,
        default=None,
        help="camera stamps off by white noise of this sigma (ms; a driver stamping on arrival): "
        "MS for both cameras, or cam0=MS,cam1=MS",
    )
    p.add_argument(
        "--extrinsic-error-deg",
        type=float,
        nargs=3,
        default=None,
        metavar=("RX", "RY", "RZ"),
        help="the camera's true mount turned by this rotation vector (degrees, body x/y/z) while "
        "sensor.yaml keeps the nominal T_BS (the floor camera's unless --extrinsic-error-camera); "
        "the truth goes to extrinsics_groundtruth.csv",
    )
    p.add_argument(
        "--extrinsic-error-camera",
        choices=("cam0", "cam1"),
        default="cam0",
        help="the camera --extrinsic-error-deg turns: cam0 the floor camera (default), cam1 the front one",
    )

    p = sub.add_parser("detect", parents=[common], help="detect and decode QR codes; writes detections.csv")
    _add_run_options(p, stages=False, time_offset=False)
    p = sub.add_parser("localize", parents=[common], help="per-frame estimates: paper (Alg. 1-6) and PnP")
    _add_run_options(p, stages=False)
    p = sub.add_parser("smooth", parents=[common], help="fusion only: smoother, incremental, EKF (no report)")
    _add_run_options(p)
    p = sub.add_parser("run", parents=[common], help="everything: detect, localize, fuse, evaluate, report")
    _add_run_options(p)

    p = sub.add_parser(
        "batch",
        parents=[common],
        help="many flights on a dask cluster: OUT/<flight>/ as `run` writes it, and OUT/fleet.md",
    )
    p.add_argument(
        "flights",
        type=Path,
        nargs="+",
        metavar="FLIGHT_OR_LIST",
        help="flight logs (as `run` takes), or text files listing them one a line",
    )
    p.add_argument("--out", type=Path, required=True, help="fleet output folder")
    p.add_argument(
        "--scheduler", default=None, help="address of a running dask scheduler, e.g. tcp://host:8786"
    )
    p.add_argument(
        "--workers", type=_workers, default=None, help="local cluster: worker processes (default: all cores)"
    )
    p.add_argument(
        "--retry-failed", action="store_true", help="run again the flights that failed in an earlier batch"
    )
    p.add_argument("--chunk-frames", type=int, default=None, help="frames per detection task (default 256)")
    p.add_argument(
        "--map",
        type=Path,
        default=None,
        help="a merged map (`fusion map merge`) of the fleet's warehouse: its as-built floor codes "
        "are every flight's prior",
    )
    p.add_argument("--time-offset-ms", type=_time_offsets_ms, default=None, help=TIME_OFFSET_HELP)
    p.add_argument(
        "--calibrate-readout",
        action="store_true",
        help="estimate each flight's floor-camera rolling-shutter readout time and use it",
    )
    p.add_argument("--track", action=argparse.BooleanOptionalAction, default=None, help=TRACK_HELP)
    p.add_argument(
        "--calibrate-extrinsics",
        action="store_true",
        help="estimate each flight's floor- and front-camera mount rotation errors and, when "
        "significant, apply them",
    )
    p.add_argument(
        "--backend", choices=("zxing", "aruco"), default="zxing", help="QR detector (default: zxing-cpp)"
    )
    _add_fusion_choices(p)

    p = sub.add_parser(
        "inspect", parents=[common], help="what a log holds: streams, rates, gaps, roles, IMU units"
    )
    p.add_argument("log", type=Path, help="EuRoC folder, ROS bag or video log")
    _add_log_options(p)
    p = sub.add_parser("import", parents=[common], help="write any log as an EuRoC folder")
    p.add_argument("log", type=Path, help="ROS bag or video log (or an EuRoC folder)")
    p.add_argument("out", type=Path, help="output EuRoC folder")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace a flight log that `fusion simulate` or `import` wrote there (other files are kept)",
    )
    _add_log_options(p)
    p = sub.add_parser(
        "export",
        parents=[common],
        help="write a flight as a ROS 1 (.bag) or ROS 2 (.mcap) bag, or a video folder",
    )
    p.add_argument("log", type=Path, help="flight log (any supported format)")
    p.add_argument("out", type=Path, help="OUT.bag (ROS 1), OUT.mcap (ROS 2), else a video folder")
    p.add_argument(
        "--image-format",
        choices=("raw", "png", "jpeg"),
        default="raw",
        help="bag images: raw mono8 Image (default) or png / jpeg CompressedImage",
    )
    p.add_argument(
        "--video-codec",
        choices=("ffv1", "h264"),
        default="ffv1",
        help="video folder codec: ffv1 lossless MKV (default) or h264 MP4 (lossy)",
    )
    p.add_argument("--force", action="store_true", help="overwrite an existing output")
    _add_log_options(p)

    p = sub.add_parser(
        "demo", parents=[common], help="simulate the default flight and run the whole pipeline on it"
    )
    p.add_argument(
        "--dir",
        type=Path,
        default=Path("demo-flight"),
        help="folder for the simulated log (DIR/log) and the results (DIR/out)",
    )
    p.add_argument("--duration", type=float, default=None, help="flight length in s (default 60)")
    p.add_argument("--seed", type=int, default=0)

    p = sub.add_parser(
        "inventory", parents=[common], help="compare a run's load map with the warehouse system's manifest"
    )
    p.add_argument("run_out", type=Path, help="output folder of `fusion run`")
    p.add_argument(
        "--expected",
        type=Path,
        required=True,
        help="manifest CSV: id,x_m,y_m,z_m[,tolerance_m] or a WMS export "
        "location,pallet_id,x,y,z,unit[,tolerance] (see fusion/warehouse/manifest.py)",
    )
    p.add_argument(
        "--estimator",
        default=str(Estimator.SMOOTHER),
        choices=[str(e) for e in Estimator],
        help="whose load map (default smoother)",
    )
    p.add_argument(
        "--log",
        type=Path,
        default=None,
        help="flight log for world.yaml and the front camera (default: the run's run.json)",
    )
    p = sub.add_parser("map", parents=[common], help="maps across flights")
    map_sub = p.add_subparsers(dest="map_command", required=True)
    p = map_sub.add_parser(
        "merge", parents=[common], help="fuse the load maps of several runs of one warehouse; list changes"
    )
    p.add_argument("run_outs", type=Path, nargs="+", help="output folders of `fusion run`, in flight order")
    p.add_argument("--out", type=Path, required=True, help="output folder of the merged map")
    p.add_argument(
        "--estimator",
        default=str(Estimator.SMOOTHER),
        choices=[str(e) for e in Estimator],
        help="whose load maps (default smoother)",
    )
    p.add_argument("--force", action="store_true", help="write into an existing output folder")

    p = sub.add_parser(
        "qr-sheet", parents=[common], help="printable PDF of floor codes and load labels at true size"
    )
    p.add_argument("out", type=Path, help="output PDF")
    p.add_argument("--grid", type=_grid, default=(10, 6), help="floor grid NXxNY (default 10x6)")
    p.add_argument("--spacing", type=float, default=1.0, help="grid spacing in m (default 1.0)")
    p.add_argument("--side", type=float, default=0.20, help="floor code side in m (default 0.20)")
    p.add_argument("--unit", type=float, default=1.0, help="payload unit in m (default 1.0)")
    p.add_argument("--loads", nargs="*", default=[], help="load ids to print as labels")
    p.add_argument("--load-side", type=float, default=0.15, help="load code side in m")
    p.add_argument(
        "--page",
        default="A3",
        choices=("A4", "A3", "letter"),
        help="paper size (default A3: a 0.20 m code with its quiet zone exceeds A4)",
    )
    p.add_argument(
        "--ecc",
        default="H",
        choices=("L", "M", "Q", "H"),
        help="error-correction level (default H: floor codes survive dirt, tyre marks and glare)",
    )
    return parser


def _run_config(args):
    from fusion.pipeline import RunConfig

    return RunConfig(
        backend=args.backend,
        workers=args.workers,
        progress=not args.quiet,
        force=getattr(args, "force", False),
        robust=getattr(args, "robust", "huber"),
        tight=getattr(args, "tight", False),
        incremental=not getattr(args, "no_incremental", False),
        calibrate_readout=getattr(args, "calibrate_readout", False),
        calibrate_extrinsics=getattr(args, "calibrate_extrinsics", False),
        floor_map=getattr(args, "map", None),
        time_offsets_s=getattr(args, "time_offset_ms", None),
        fixes=getattr(args, "fixes", None),
        **({} if getattr(args, "track", None) is None else {"track": args.track}),
        **(
            {}
            if getattr(args, "smoother_window_s", None) is None
            else {"smoother_window_s": args.smoother_window_s}
        ),
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    configure_logging(args.verbose, args.quiet)
    try:
        with _stop_on_signals():
            return _command(args)
    except FusionError as e:
        print(f"fusion: error: {e}", file=sys.stderr)
        return 1
    except Stopped as e:
        print(f"fusion: stopped by {signal.Signals(e.signum).name}", file=sys.stderr)
        return 128 + e.signum
    except KeyboardInterrupt:
        print("fusion: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


def _refuse_undecodable_paths(args: argparse.Namespace) -> None:
    """FusionError, before any work, for a path argument that is not valid UTF-8 (a Latin-1 name
    from an old USB stick or a Samba share: Python keeps its bytes as lone surrogates, and the
    report, plots and JSON that name the path could not be written at the very end).  The
    absolute path is checked, so a non-UTF-8 current folder counts; the message shows the bad
    bytes escaped (\\xe9)."""
    for value in vars(args).values():
        for path in value if isinstance(value, list) else [value]:
            if not isinstance(path, Path):
                continue
            for text in (str(path), os.path.abspath(path)):
                try:
                    text.encode("utf-8")
                except UnicodeEncodeError:
                    shown = os.fsencode(text).decode("utf-8", "backslashreplace")
                    raise FusionError(
                        f"{shown}: the path is not valid UTF-8; rename it (e.g. with convmv) or use another"
                    ) from None


def _command(args: argparse.Namespace) -> int:
    """Run the parsed command; its exit code (FusionError and interruptions: `main`)."""
    _refuse_undecodable_paths(args)
    if args.command == "simulate":
        from fusion.sim.simulate import simulate

        res = simulate(
            args.out,
            scenario=args.scenario,
            duration_s=args.duration,
            seed=args.seed,
            overwrite=args.force,
            progress=not args.quiet,
            workers=args.workers,
            resolution=args.resolution,
            camera_rate_hz=args.fps,
            start_s=args.start,
            fmt=args.format,
            readout_s=None if args.readout_ms is None else args.readout_ms * 1e-3,
            placement_error_m=args.placement_error_m,
            placement_error_deg=args.placement_error_deg,
            placement_seed=args.placement_seed,
            png_compression=args.png_compression,
            time_offset_ms=(
                {k: v * 1e3 for k, v in args.time_offset_ms.items()} if args.time_offset_ms else None
            ),
            clock_drift_ppm=args.clock_drift_ppm,
            stamp_jitter_ms=(
                {k: v * 1e3 for k, v in args.stamp_jitter_ms.items()} if args.stamp_jitter_ms else None
            ),
            camera_options=_camera_options(args),
            extrinsic_error_deg=(
                None
                if args.extrinsic_error_deg is None
                else {args.extrinsic_error_camera: tuple(args.extrinsic_error_deg)}
            ),
            velocity_rate_hz=args.velocity_rate_hz,
            imu_noise_scale=args.imu_noise_scale,
            imu_noise_stated=args.imu_noise_stated,
        )
        print(
            f"wrote {res.root}: scenario {res.scenario}, {res.duration_s:.1f} s, "
            f"{res.n_frames} frames per camera ({', '.join(res.cameras)}), "
            f"{res.n_imu} IMU samples, {len(res.blackouts)} floor-camera blackouts, "
            f"{res.wall_time_s:.1f} s wall time"
        )
    elif args.command in ("detect", "localize", "smooth", "run"):
        from fusion import pipeline

        result = pipeline.run(_flight_arg(args), args.out, _run_config(args), until=args.command)
        print(result.summary())
        if getattr(args, "strict", False) and not result.trusted:
            print(
                "fusion: --strict: an estimate is not trusted, or none was made "
                "(see health and warnings above)",
                file=sys.stderr,
            )
            return EXIT_NOT_TRUSTED
    elif args.command == "batch":
        from fusion.fleet import BatchConfig, run_batch

        bcfg = BatchConfig(
            scheduler=args.scheduler,
            workers=args.workers,
            retry_failed=args.retry_failed,
            run=_run_config(args),
        )
        if args.chunk_frames is not None:
            if args.chunk_frames < 1:
                raise FusionError("--chunk-frames must be at least 1")
            bcfg.chunk_frames = args.chunk_frames
        batch = run_batch(args.flights, args.out, bcfg)
        print(batch.summary())
        if batch.failed:
            return EXIT_FLIGHTS_FAILED
    elif args.command == "inspect":
        from fusion.log.inspect import inspect_log

        print(inspect_log(args.log, _log_options(args)).format_text())
    elif args.command == "import":
        from fusion.log.convert import import_flight

        said: list = []
        out = import_flight(args.log, args.out, _log_options(args), overwrite=args.force, warnings=said)
        print(f"wrote {out} (EuRoC layout)")
        for w in said:  # what the EuRoC copy no longer says (the reader's, frames left out)
            print(f"warning: {w}")
    elif args.command == "export":
        from fusion.log.convert import export_flight

        said = []
        out = export_flight(
            args.log,
            args.out,
            _log_options(args),
            image_format=args.image_format,
            video_codec=args.video_codec,
            overwrite=args.force,
            warnings=said,
        )
        print(f"wrote {out}")
        for w in said:  # what the copy no longer says (the reader's, frames left out)
            print(f"warning: {w}")
    elif args.command == "demo":
        from fusion import pipeline

        result = pipeline.demo(args.dir, duration_s=args.duration, seed=args.seed, progress=not args.quiet)
        print(result.summary())
    elif args.command == "inventory":
        from fusion.warehouse.inventory import run_inventory

        inv = run_inventory(args.run_out, args.expected, args.estimator, args.log)
        print("inventory: " + ", ".join(f"{n} {s}" for s, n in inv.counts().items()))
        for note in inv.notes:
            print(f"note: {note}")
        print(f"wrote {args.run_out / 'inventory.csv'}")
    elif args.command == "map" and args.map_command == "merge":
        from fusion.warehouse.merge import run_merge

        merged = run_merge(args.run_outs, args.out, args.estimator, args.force)
        kinds: dict[str, int] = {}
        for c in merged.changes:
            kinds[str(c.kind)] = kinds.get(str(c.kind), 0) + 1
        print(
            f"merged {len(merged.runs)} runs: {len(merged.loads)} loads; changes: "
            + (", ".join(f"{n} {k}" for k, n in kinds.items()) or "none")
            + (f"; {len(merged.floor_codes)} as-built floor codes" if merged.floor_codes else "")
        )
        print(f"wrote {args.out}")
    elif args.command == "qr-sheet":
        from fusion.qrsheet import write_qr_sheet

        pages = write_qr_sheet(
            args.out,
            grid=args.grid,
            spacing_m=args.spacing,
            side_m=args.side,
            payload_unit_m=args.unit,
            load_ids=args.loads,
            load_side_m=args.load_side,
            page=args.page,
            ecc=args.ecc,
        )
        print(f"wrote {args.out} ({pages} pages)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
