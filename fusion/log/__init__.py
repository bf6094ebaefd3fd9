"""Flight-log reading and writing: the EuRoC / ASL layout, ROS 1 / ROS 2 bags, video + IMU
logs, Kalibr calibration; trajectory / load-map files.  `read_flight` (= `open_flight`) opens any
of them as the same FlightLog."""

from fusion.log.euroc import (
    CameraStream,
    FlightLog,
    FlightLogWriter,
    Frame,
    GroundTruth,
    ImuData,
    ImuNoise,
    LogWarning,
    VelocityData,
)
from fusion.log.options import LogFormat, LogOptions, StampSource
from fusion.log.sources import detect_format, open_flight

read_flight = open_flight
"""Any supported log (EuRoC folder, bag, video) as a FlightLog; see fusion.log.sources."""

__all__ = [
    "CameraStream",
    "Frame",
    "FlightLog",
    "FlightLogWriter",
    "GroundTruth",
    "ImuData",
    "ImuNoise",
    "LogFormat",
    "LogOptions",
    "LogWarning",
    "StampSource",
    "VelocityData",
    "detect_format",
    "open_flight",
    "read_flight",
]
