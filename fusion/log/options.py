"""How to open a log that is not an EuRoC folder: topic overrides, stamps, calibration and side
files.  Every field is optional; `open_flight` finds what it can by type and by file name."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from fusion.types import Choice


class StampSource(Choice):
    """Which clock gives a bag message its time."""

    HEADER = "header"  # header.stamp (sensor time; default)
    RECEIVE = "receive"  # the bag's receive (log) time


class LogFormat(Choice):
    """What `open_flight` / `fusion simulate --format` / `fusion export` handle."""

    EUROC = "euroc"  # EuRoC / ASL folder
    ROSBAG1 = "rosbag1"  # ROS 1 .bag
    ROSBAG2 = "rosbag2"  # ROS 2 bag: folder with metadata.yaml (+ .db3 / .mcap), or one .mcap
    VIDEO = "video"  # video file(s) + frame times + IMU CSV / PX4 ULog + Kalibr yaml


@dataclass
class LogOptions:
    """Overrides for `open_flight`.  Topics: bags only.  Files: any format."""

    floor_topic: str | None = None
    front_topic: str | None = None
    imu_topic: str | None = None
    velocity_topic: str | None = None
    stamps: StampSource = StampSource.HEADER
    calib: Path | None = None  # Kalibr camchain-imucam.yaml, or an EuRoC folder
    imu_calib: Path | None = None  # Kalibr imu.yaml
    world: Path | None = None  # world.yaml (default: next to the log, or in the bag)
    # video logs
    front_video: Path | None = None
    frame_times: Path | None = None  # floor video's frame times CSV (default <video>.csv)
    front_frame_times: Path | None = None
    imu: Path | None = None  # IMU CSV (EuRoC imu0 columns) or PX4 ULog (.ulg)
    video_fps: float | None = None  # constant rate when there is no frame-times file
    video_start_ns: int | None = None  # time of the first frame in the IMU clock (with video_fps)
    # EuRoC folders: accept a log without the floor camera (IMU + external fixes, --fixes)
    cameras_optional: bool = False
