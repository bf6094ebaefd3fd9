"""Memory of a `fusion run`'s calls, in process: what each keeps and what it needs at its peak.

    python scripts/bench_run_memory_calls.py LOG OUT [--read-only DETECTIONS_CSV]

Runs `fusion.pipeline.run(LOG, OUT)` (workers as by default; put a copy of the flight's
detections.csv in OUT to skip detection) with tracemalloc on, and prints, for each wrapped call
(CALLS: the stages of `fusion.pipeline` and the evaluation's plots), in the order they ended: the
traced memory (Python objects and numpy arrays; not GTSAM's C++ heap) before and after it, its
traced peak above what was live when it started, and the process's RSS before and after.
`--read-only`: only `read_flight(LOG)` and `read_cache(DETECTIONS_CSV)`, each measured so, in a
fresh process (what reading leaves in RSS).  Complements `bench_run_memory.py`, which samples the
whole run's RSS from outside per announced stage.  Linux only (/proc)."""

from __future__ import annotations

import argparse
import functools
import importlib
import sys
import time
import tracemalloc
from collections.abc import Callable
from pathlib import Path

CALLS = [
    ("fusion.pipeline", "read_flight"),
    ("fusion.pipeline", "detect_flight"),
    ("fusion.pipeline", "detection_statistics"),
    ("fusion.pipeline", "localize_stage"),
    ("fusion.pipeline", "_apply_time_offsets"),
    ("fusion.pipeline", "_apply_extrinsics"),
    ("fusion.pipeline", "smooth_windowed"),
    ("fusion.pipeline", "smooth_incremental"),
    ("fusion.pipeline", "run_ekf"),
    ("fusion.pipeline", "fuse_stage"),
    ("fusion.pipeline", "_write_estimates"),
    ("fusion.pipeline", "evaluate"),
    ("fusion.pipeline", "export_groundtruth_tum"),
    ("fusion.pipeline", "_floor_codes_seen"),
    ("fusion.evaluate.plots", "associate_all"),
    ("fusion.evaluate.plots", "plot_trajectories"),
    ("fusion.evaluate.plots", "plot_error_overview"),
    ("fusion.evaluate.plots", "plot_position_errors_zoom"),
    ("fusion.evaluate.plots", "plot_error_boxplots"),
    ("fusion.evaluate.report", "plot_all"),
    ("fusion.evaluate.report", "report_hook"),
    ("fusion.pipeline", "write_report"),
    ("fusion.pipeline", "_evaluate_and_report"),
]


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def measured(label: str, fn: Callable) -> Callable:
    """`fn`, printing its memory line when it returns."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        live0, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        rss0 = rss_mb()
        out = fn(*args, **kwargs)
        live1, peak = tracemalloc.get_traced_memory()
        print(
            f"| {label} | {live0 / 2**20:.1f} | {live1 / 2**20:.1f} | {(peak - live0) / 2**20:.1f} "
            f"| {rss0:.0f} | {rss_mb():.0f} |",
            flush=True,
        )
        return out

    return wrapper


HEADER = (
    "| call | traced before MB | traced after MB | traced peak above before MB "
    "| RSS before MB | RSS after MB |\n|---|--:|--:|--:|--:|--:|"
)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("out", type=Path, nargs="?")
    ap.add_argument("--read-only", type=Path, metavar="DETECTIONS_CSV", help="only read LOG and this")
    args = ap.parse_args()
    from fusion.log import read_flight
    from fusion.pipeline import RunConfig, run
    from fusion.qr.detect import read_cache

    print(f"{time.strftime('%Y-%m-%d %H:%M')} UTC, {args.log}; RSS after the imports {rss_mb():.0f} MB\n")
    print(HEADER)
    tracemalloc.start()
    if args.read_only is not None:
        measured("read_flight", read_flight)(args.log)
        measured("read_cache", read_cache)(args.read_only)
        return 0
    if args.out is None:
        ap.error("OUT is needed (unless --read-only)")
    for module_name, name in CALLS:
        module = importlib.import_module(module_name)
        setattr(module, name, measured(name, getattr(module, name)))
    run(args.log, args.out, RunConfig(progress=False, force=True))
    return 0


if __name__ == "__main__":
    sys.exit(main())
