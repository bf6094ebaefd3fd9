"""Exception hierarchy: one root, one subclass per module (evo's EvoException pattern).

The CLI turns any `FusionError` into one clear line and exit code 1; anything else keeps its
traceback because it is a bug, not bad input.
"""


class FusionError(Exception):
    """Root of every error `fusion` raises on purpose (bad input, bad configuration)."""


class PayloadError(FusionError):
    """A QR payload that is not one of ours (malformed, over-long, not text)."""


class CameraModelError(FusionError):
    """A camera `sensor.yaml` that is missing keys or has impossible values."""


class WorldError(FusionError):
    """A `world.yaml` that is missing keys or has impossible values."""


class LogError(FusionError):
    """A flight log that cannot be read; the message names the file and line."""


class SimulationError(FusionError):
    """Impossible simulator settings (unknown scenario, negative duration, ...)."""


class DetectionError(FusionError):
    """Detection could not run (unknown backend, unreadable cache)."""


class EstimationError(FusionError):
    """An estimator could not produce a result (no floor code at all, no IMU and no velocity)."""


class OutputError(FusionError):
    """An output folder or file that cannot be written (exists without --force, ...)."""


class EvaluationError(FusionError):
    """Evaluation inputs that cannot be compared (no ground truth overlap, malformed shapes)."""


class QRSheetError(FusionError):
    """A printable QR sheet that cannot be made (code larger than the page, unprintable id)."""


class WarehouseError(FusionError):
    """Inventory / map-merge inputs that cannot be used (bad manifest line, runs of different
    warehouses, a run folder without its outputs)."""


class FleetError(FusionError):
    """A batch of flights that cannot run (unreachable scheduler, a locked fleet folder, an
    unreadable flight list); one bad flight is not an error of the batch."""


def first_line(exc: BaseException) -> str:
    """An exception's message for one line of output: its first line (GTSAM's run to eleven,
    ending in a pointer to its Doxygen pages), or its type's name when it has none."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__
