"""The tasks of one flight's graph, run on dask workers; each wraps a stage function of
fusion.pipeline / fusion.qr.detect, so `fusion batch` writes what `fusion run` writes.

    open_flight_task(path)                            -> FlightLog (stays on the cluster)
    plan_task(log, chunk_frames)                      -> FlightPlan (to the driver)
    detect_task(log, chunk, backend, parts, i)        -> Timed(PartFile)    one per chunk, packed
    floor_task(log, detected, cfg)                    -> Timed(floor part)  one per cam0 chunk
    merge_floor_task(cfg, parts, *floor)              -> Timed(PartFile)    LocalizeResult, raw
    front_context_task(log, merged, cfg)              -> the front chunks' context
    front_task(context, detected, parts, i)           -> Timed(PartFile)    one per cam1 chunk
    report_task(log, out_dir, parts, cfg, n_det, *p)  -> FlightDone         fusion, metrics, report

The detection chunks, the merged floor result and the front parts reach the report task as
files in the flight's parts folder (`parts`: fusion.fleet.parts), not as Dask data: Dask keeps a
running task's arguments for its whole duration, and these are the flight's largest results.
The floor parts and the front context stay Dask data; nothing holds them once their dependents
have run (the driver keeps only the log's, the plan's and the report's futures).

Tasks are module-level functions (pickled by reference) and never start processes themselves
(RunConfig.workers = 1): the cluster is the parallelism.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fusion.fleet.parts import PartFile, read_part, remove_parts, write_part
from fusion.log import FlightLog, open_flight
from fusion.pipeline import (
    Computed,
    RunConfig,
    floor_context,
    front_context,
    localize_floor_chunk,
    localize_front_chunk,
    merge_floor_parts,
    merge_front_parts,
    run,
)
from fusion.qr.detect import (
    DetectionPart,
    DetectionResult,
    assemble_detections,
    detect_chunk,
    detection_chunks,
    pack_detections,
    unpack_detections,
)
from fusion.types import CameraRole


@dataclass
class Timed:
    """A task's result and the seconds it took on its worker."""

    value: Any
    elapsed_s: float


@dataclass
class FlightPlan:
    """What the driver needs to lay out a flight's graph."""

    chunks: list[tuple[str, int, int]]  # (camera, start, stop) frame ranges
    n_frames: int  # every camera's frames
    duration_s: float
    has_front: bool


@dataclass
class FlightDone:
    """A finished flight: its output folder and the time its tasks took."""

    out_dir: str
    compute_s: float  # task seconds summed over the flight's tasks
    timings_s: dict[str, float] = field(default_factory=dict)  # pipeline.run's stages (report task)
    task_s: dict[str, float] = field(default_factory=dict)  # task seconds: detect, localize, report_task
    trusted: bool = False


def open_flight_task(path: str) -> FlightLog:
    return open_flight(Path(path))


def plan_task(log: FlightLog, chunk_frames: int) -> FlightPlan:
    chunks = detection_chunks(log, chunk_frames)
    return FlightPlan(
        chunks, sum(len(s) for s in log.cameras.values()), log.duration_s, log.front is not None
    )


def detect_task(log: FlightLog, chunk: tuple[str, int, int], backend: str, parts: str, index: int) -> Timed:
    """One chunk's DetectionPart with its detections packed (`pack_detections`: about half the
    memory of the objects), written to the flight's parts folder."""
    t = time.perf_counter()
    camera, dets, stats, skipped = detect_chunk(log, chunk, backend)
    part = write_part(parts, f"detect{index:05d}", (camera, pack_detections(dets), stats, skipped))
    return Timed(part, time.perf_counter() - t)


def _unpacked(part: tuple) -> DetectionPart:
    """`detect_task`'s part with its detections as objects again (bit for bit)."""
    camera, packed, stats, skipped = part
    return camera, unpack_detections(packed), stats, skipped


def _frames(part: PartFile) -> dict:
    """{timestamp_ns: detections} of one detection chunk's file (frames without codes absent)."""
    camera, dets, _, _ = _unpacked(read_part(part))
    return DetectionResult(dets, {}).by_frame(camera)


def floor_task(log: FlightLog, detected: Timed, cfg: RunConfig) -> Timed:
    t = time.perf_counter()
    part = localize_floor_chunk(floor_context(log, cfg), _frames(detected.value))
    return Timed(part, time.perf_counter() - t)


def merge_floor_task(cfg: RunConfig, parts: str, *floor: Timed) -> Timed:
    """The merged floor result, written to the parts folder; its time includes the floor
    chunks' (they reach the report task only through this one)."""
    t = time.perf_counter()
    merged = merge_floor_parts([p.value for p in floor], cfg)
    part = write_part(parts, "floor", merged)
    return Timed(part, time.perf_counter() - t + sum(p.elapsed_s for p in floor))


def front_context_task(log: FlightLog, merged: Timed, cfg: RunConfig) -> tuple:
    """What every front chunk needs of the merged floor result (`pipeline.front_context`: the
    front camera, the world and the raw paper / PnP trajectories)."""
    return front_context(log, read_part(merged.value), cfg)


def front_task(context: tuple, detected: Timed, parts: str, index: int) -> Timed:
    t = time.perf_counter()
    part = write_part(parts, f"front{index:05d}", localize_front_chunk(context, _frames(detected.value)))
    return Timed(part, time.perf_counter() - t)


def report_task(
    log: FlightLog, out_dir: str, parts: str, cfg: RunConfig, n_detect: int, *handles: Timed
) -> FlightDone:
    """Fusion, evaluation and report into `out_dir` (pipeline.run with the detections and the
    per-frame estimates computed by the other tasks).  `handles`: the `n_detect` detection
    chunks' files in plan order, then the merged floor result's, then the front chunks' in time
    order.  Each file is read and let go in turn; the flight's parts folder is removed once its
    outputs are written."""
    t = time.perf_counter()
    detected, floor, front = handles[:n_detect], handles[n_detect], handles[n_detect + 1 :]
    log = _own_copy(log)
    # no variable here holds the detections or the per-frame results: `run` lets them go
    # before the fusion (Computed)
    computed = Computed(
        assemble_detections(log, (_unpacked(read_part(p.value)) for p in detected), cfg.backend),
        merge_front_parts(log, read_part(floor.value), [read_part(p.value) for p in front]),
    )
    result = run(log, Path(out_dir), cfg, computed=computed)
    remove_parts(Path(parts))
    elapsed = time.perf_counter() - t
    task_s = {
        "detect": sum(p.elapsed_s for p in detected),
        "localize": floor.elapsed_s + sum(p.elapsed_s for p in front),
        "report_task": elapsed,
    }
    return FlightDone(
        str(result.out_dir), sum(task_s.values()), dict(result.timings_s), task_s, result.trusted
    )


def _own_copy(log: FlightLog) -> FlightLog:
    """A copy of `log` whose camera streams (their skip messages) this task may change: the
    worker shares the original between the flight's tasks."""
    cameras = {}
    for name, stream in log.cameras.items():
        c = copy.copy(stream)
        c.skipped = list(stream.skipped)
        cameras[name] = c
    return dataclasses.replace(log, cameras=cameras, warnings=list(log.warnings))


FLOOR, FRONT = CameraRole.FLOOR.value, CameraRole.FRONT.value
