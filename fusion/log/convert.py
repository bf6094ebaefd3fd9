"""Format conversion: `import_flight` (any log -> EuRoC folder) and `export_flight` (any log ->
ROS 1 bag, ROS 2 MCAP bag or a video folder).  Both stream the frames."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from fusion.errors import LogError
from fusion.fileio import path_overlap
from fusion.log.euroc import FlightLog, FlightLogWriter, LogWarning
from fusion.log.options import LogFormat, LogOptions
from fusion.log.sources import open_flight

log = logging.getLogger(__name__)


def _as_flight(src, opts: LogOptions | None) -> FlightLog:
    return src if isinstance(src, FlightLog) else open_flight(Path(src), opts)


def import_flight(
    src,
    out: Path,
    opts: LogOptions | None = None,
    overwrite: bool = False,
    warnings: list[LogWarning] | None = None,
) -> Path:
    """Write the EuRoC layout of `src` (a path or a FlightLog) to `out`; images as PNG, frames
    that cannot be read are skipped.  `warnings` (a list, extended): the reader's own named
    warnings (a truncated bag, unordered stamps, ...: the EuRoC copy no longer carries them) and
    one `frames_skipped` per camera (count: its frames left out; the copy simply lacks them)."""
    flight = _as_flight(src, opts)
    if warnings is not None:
        warnings.extend(flight.warnings)
    with FlightLogWriter(Path(out), overwrite=overwrite, written_by="fusion import") as w:
        w.write_world(flight.world)
        for name, stream in sorted(flight.cameras.items()):
            w.add_camera(name, stream.camera, comment=f"imported from {flight.root}")
            for frame in stream.frames():
                if frame.image is not None:
                    w.write_frame(name, frame.timestamp_ns, frame.image)
            for msg in stream.skipped:
                log.warning("%s", msg)
        if flight.imu is not None:
            w.write_imu(flight.imu)
        if flight.velocity is not None:
            w.write_velocity(flight.velocity)
        if flight.groundtruth is not None:
            w.write_groundtruth(flight.groundtruth)
        if flight.loads_groundtruth is not None:
            w.write_loads_groundtruth(flight.loads_groundtruth)
        if flight.blackouts is not None:
            w.write_blackouts(flight.blackouts)
    if warnings is not None:
        warnings += _skipped_warnings(flight)
    return Path(out)


def _skipped_warnings(flight: FlightLog) -> list[LogWarning]:
    """One `frames_skipped` per camera whose frames could not be read while it was copied (count:
    the frames left out; the copy simply lacks them, and reads as a clean camera)."""
    return [
        LogWarning(
            "frames_skipped",
            len(stream.skipped),
            f"{name}: frames that could not be read were left out of the copy (first: {stream.skipped[0]})",
        )
        for name, stream in sorted(flight.cameras.items())
        if stream.skipped
    ]


def export_format(out: Path) -> LogFormat:
    """The format `export_flight` writes for `out`: .bag ROS 1, .mcap ROS 2, otherwise a video
    folder (.mkv inside)."""
    suffix = Path(out).suffix.lower()
    if suffix == ".bag":
        return LogFormat.ROSBAG1
    if suffix == ".mcap":
        return LogFormat.ROSBAG2
    return LogFormat.VIDEO


def export_flight(
    src,
    out: Path,
    opts: LogOptions | None = None,
    image_format: str = "raw",
    video_codec: str = "ffv1",
    overwrite: bool = False,
    fmt: LogFormat | None = None,
    warnings: list[LogWarning] | None = None,
) -> Path:
    """Write `src` (a path or a FlightLog) as OUT.bag (ROS 1), OUT.mcap (ROS 2, MCAP storage) or
    a video folder (`fmt=LogFormat.VIDEO`, or any other name).  `overwrite` replaces only a
    previous export of that kind (`_check_export_target`); an OUT that is the source, holds it
    or lies inside it is refused.  `warnings` (a list, extended): as `import_flight`'s, the
    reader's named warnings and the frames left out (an export had dropped both silently)."""
    flight = _as_flight(src, opts)
    if warnings is not None:
        warnings.extend(flight.warnings)
    fmt = fmt or export_format(out)
    _check_export_target(Path(src) if not isinstance(src, FlightLog) else flight.root, Path(out), fmt)
    if fmt in (LogFormat.ROSBAG1, LogFormat.ROSBAG2):
        from fusion.log.rosbag import write_bag

        want = ".bag" if fmt == LogFormat.ROSBAG1 else ".mcap"
        if Path(out).suffix.lower() != want:
            raise LogError(f"{out}: a {fmt.value} export must end in {want}")
        written = write_bag(flight, Path(out), image_format=image_format, overwrite=overwrite)
    elif fmt == LogFormat.VIDEO:
        from fusion.log.video import write_video_flight

        written = write_video_flight(flight, Path(out), codec=video_codec, overwrite=overwrite)
    else:
        raise LogError(f"cannot export to {fmt.value}; use `fusion import` for the EuRoC layout")
    if warnings is not None:
        warnings += _skipped_warnings(flight)
    return written


def _check_export_target(src: Path, out: Path, fmt: LogFormat) -> None:
    """LogError unless `out` may be written by an export, --force or not: not the source log,
    not a folder holding it or inside it (the export reads the source's images as it writes:
    `export X.bag X.bag --force` deleted the bag first and wrote one without images), and, when
    it exists, a previous export of the same kind: a .bag / .mcap file, or a video export's
    folder (its camchain and cam0 frame times).  `--force` had deleted any folder at OUT, a
    user's files or a EuRoC flight (thirty-first session's audit)."""
    if path_overlap(out, src) is not None:
        raise LogError(
            f"{out}: is, holds or lies inside the log being exported ({src}); choose another output"
        )
    if not os.path.lexists(out):
        return
    if fmt in (LogFormat.ROSBAG1, LogFormat.ROSBAG2):
        if out.is_dir():
            raise LogError(f"{out}: is a folder, not a previous {out.suffix} export; choose another output")
        return
    if not out.is_dir():
        raise LogError(f"{out}: is a file, not a previous video export (a folder); choose another output")
    from fusion.log.video import CAMCHAIN_FILE

    entries = {p.name for p in out.iterdir()}
    if entries and not ({CAMCHAIN_FILE, "cam0.csv"} <= entries and "mav0" not in entries):
        raise LogError(
            f"{out}: is not a previous video export (no {CAMCHAIN_FILE} and cam0.csv, or a flight's "
            "mav0/): --force replaces only an export; choose another output"
        )
