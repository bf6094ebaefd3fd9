"""Flight-log reading and writing (EuRoC / ASL layout) and trajectory / load-map files."""
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
                              read_flight,
)

__all__ = ["CameraStream", "Frame", "FlightLog", "FlightLogWriter", "GroundTruth", "ImuData",
           "ImuNoise", "LogWarning", "VelocityData", "read_flight"]
