"""The tasks of one flight's graph, run on dask workers; each wraps a stage function of
fusion.pipeline / fusion.qr.detect, so `fusion batch` writes what `fusion run` writes.

    open_flight_task(path)                         -> FlightLog (stays on the cluster)
    plan_task(log, chunk_frames)                   -> FlightPlan (to the driver)
    detect_task(log, chunk, backend)               -> Timed(DetectionPart)   one per chunk, packed
    floor_task(log, detected, cfg)                 -> Timed(floor part)      one per cam0 chunk
    merge_floor_task(cfg, *floor)                  -> Timed(LocalizeResult)  raw trajectories
    front_task(log, floor, detected, cfg)          -> Timed(front part)      one per cam1 chunk
    report_task(log, out_dir, cfg, n_det, *parts)  -> FlightDone             fusion, metrics, report

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


def detect_task(log: FlightLog, chunk: tuple[str, int, int], backend: str) -> Timed:
    """One chunk's DetectionPart with its detections packed (`pack_detections`): the cluster
    keeps every chunk until the flight's report task ends, and sends them to it; packed, they
    take about half the memory and 1/30 of the pickling CPU of the objects."""
    t = time.perf_counter()
    camera, dets, stats, skipped = detect_chunk(log, chunk, backend)
    return Timed((camera, pack_detections(dets), stats, skipped), time.perf_counter() - t)


def _unpacked(part: tuple) -> DetectionPart:
    """`detect_task`'s part with its detections as objects again (bit for bit)."""
    camera, packed, stats, skipped = part
    return camera, unpack_detections(packed), stats, skipped


def _frames(part: tuple) -> dict:
    """{timestamp_ns: detections} of one packed detection chunk (frames without codes absent)."""
    camera, dets, _, _ = _unpacked(part)
    return DetectionResult(dets, {}).by_frame(camera)


def floor_task(log: FlightLog, detected: Timed, cfg: RunConfig) -> Timed:
    t = time.perf_counter()
    part = localize_floor_chunk(floor_context(log, cfg), _frames(detected.value))
    return Timed(part, time.perf_counter() - t)


def merge_floor_task(cfg: RunConfig, *floor: Timed) -> Timed:
    """The merged floor result; its time includes the floor chunks' (they reach the report
    task only through this one)."""
    t = time.perf_counter()
    merged = merge_floor_parts([p.value for p in floor], cfg)
    return Timed(merged, time.perf_counter() - t + sum(p.elapsed_s for p in floor))


def front_task(log: FlightLog, floor: Timed, detected: Timed, cfg: RunConfig) -> Timed:
    t = time.perf_counter()
    part = localize_front_chunk(front_context(log, floor.value, cfg), _frames(detected.value))
    return Timed(part, time.perf_counter() - t)


def report_task(log: FlightLog, out_dir: str, cfg: RunConfig, n_detect: int, *parts: Timed) -> FlightDone:
    """Fusion, evaluation and report into `out_dir` (pipeline.run with the detections and the
    per-frame estimates computed by the other tasks).  `parts`: the `n_detect` detection
    chunks in plan order, then the merged floor result, then the front chunks in time order."""
    t = time.perf_counter()
    detected, floor, front = parts[:n_detect], parts[n_detect], parts[n_detect + 1 :]
    log = _own_copy(log)
    # no variable here holds the detections or the per-frame results: `run` lets them go
    # before the fusion (Computed)
    computed = Computed(
        assemble_detections(log, [_unpacked(p.value) for p in detected], cfg.backend),
        merge_front_parts(log, floor.value, [p.value for p in front]),
    )
    result = run(log, Path(out_dir), cfg, computed=computed)
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
