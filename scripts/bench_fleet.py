"""Fleet scaling figures for `fusion batch` (fusion.fleet) on a dask LocalCluster (issue 13, item 3).

1. Parallel efficiency from 1 to 2 workers: the same K flights as a batch on 1 worker, then on
   2 workers; E = T1 / (2 T2), T = batch wall time.
2. Fleet throughput: M flights on 2 workers, in flight-minutes per wall-minute.
3. The costs a model of N nodes needs, from the flights' task seconds (fleet.json): per frame
   (detection + per-frame estimators), and per flight second of the report task (fusion,
   evaluation, report), then the N at which 160 flight-hours fit in 8 wall-hours.

One flight is simulated (two cameras, 30 fps, 640x480 PNG) and copied M times: every copy is
processed from scratch (each output folder detects afresh), so the work is that of M flights.

    PYTHONPATH=. python3 scripts/bench_fleet.py [--duration 120] [--flights 8] [--efficiency-flights 2]
        [--dir /tmp/bench-fleet]

Prints Markdown.  Wall times on a shared machine are pessimistic: other jobs take cores from the
workers (say so next to the numbers).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import time
from pathlib import Path

from fusion.fleet import BatchConfig, run_batch
from fusion.fleet.flights import FlightStatus
from fusion.sim.simulate import simulate

FLEET_FLIGHT_HOURS = 160.0  # 20 drones x 8 hours
WALL_HOURS = 8.0
NODE_CORES = (2, 16, 64)  # this machine, a typical compute node, a big one


def _flights(root: Path, duration_s: float, n: int, seed: int) -> list[Path]:
    src = root / "source"
    if not (src / "world.yaml").exists():
        t = time.perf_counter()
        simulate(src, duration_s=duration_s, seed=seed, progress=False, workers=2, overwrite=True)
        print(f"simulated a {duration_s:.0f} s flight in {time.perf_counter() - t:.0f} s")
    out = []
    for i in range(n):
        dst = root / f"flight{i:02d}"
        if not dst.exists():
            shutil.copytree(src, dst)
        out.append(dst)
    return out


def _batch(flights: list[Path], out: Path, workers: int) -> tuple[float, list]:
    if out.exists():
        shutil.rmtree(out)
    t = time.perf_counter()
    res = run_batch(flights, out, BatchConfig(workers=workers))
    wall = time.perf_counter() - t
    bad = [r for r in res.records if r.status != FlightStatus.OK]
    if bad:
        raise SystemExit(f"flights failed: {[(r.name, r.reason) for r in bad]}")
    return wall, res.records


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=120.0, help="seconds per flight (default 120)")
    ap.add_argument("--flights", type=int, default=8, help="flights of the throughput batch (default 8)")
    ap.add_argument("--efficiency-flights", type=int, default=2, help="flights of the 1 vs 2 worker runs")
    ap.add_argument("--dir", type=Path, default=Path("/tmp/bench-fleet"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-efficiency", action="store_true")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    flights = _flights(args.dir, args.duration, max(args.flights, args.efficiency_flights), args.seed)

    print(f"\n## fusion batch on a LocalCluster: {args.duration:.0f} s flights, 2 cameras at 30 fps\n")
    if not args.skip_efficiency:
        sub = flights[: args.efficiency_flights]
        t1, _ = _batch(sub, args.dir / "out-w1", 1)
        t2, _ = _batch(sub, args.dir / "out-w2", 2)
        eff = t1 / (2 * t2)
        print("| workers | flights | wall s | speed-up | efficiency |")
        print("|---:|---:|---:|---:|---:|")
        print(f"| 1 | {len(sub)} | {t1:.1f} | 1.00 | 100 % |")
        print(f"| 2 | {len(sub)} | {t2:.1f} | {t1 / t2:.2f} | {100 * eff:.0f} % |")
    else:
        eff = float("nan")

    wall, records = _batch(flights[: args.flights], args.dir / "out-fleet", 2)
    flown_s = sum(r.duration_s or 0.0 for r in records)
    frames = sum(r.n_frames or 0 for r in records)
    per_frame = sum(r.task_s.get("detect", 0.0) + r.task_s.get("localize", 0.0) for r in records) / frames
    report_per_s = sum(r.task_s.get("report_task", 0.0) for r in records) / flown_s
    fps_total = frames / flown_s
    task_per_flight_s = sum(r.compute_s or 0.0 for r in records) / flown_s
    print(
        f"\nthroughput, {len(records)} flights on 2 workers: {flown_s / 60:.1f} flight-min in "
        f"{wall / 60:.1f} wall-min = **{flown_s / wall:.2f} flight-min per wall-min** "
        f"({task_per_flight_s:.2f} task-s per flight-s)\n"
    )
    print("| cost (task seconds, measured in the throughput batch) | value |")
    print("|---|---:|")
    print(f"| detection + per-frame estimators, per frame | {1e3 * per_frame:.2f} ms |")
    print(f"| frames per flight second (both cameras) | {fps_total:.1f} |")
    print(f"| report task (fusion, evaluation, report) per flight second | {report_per_s:.3f} s |")
    for r in records[:1]:
        kinds = json.dumps({k: round(v, 1) for k, v in r.task_s.items()})
        print(f"| one flight's task seconds by kind | {kinds} |")

    # the model: work per flight second w = fps * c_frame + c_report; a fleet day is
    # FLEET_FLIGHT_HOURS * 3600 * w task-seconds, spread over N nodes of k cores at efficiency E
    w = fps_total * per_frame + report_per_s
    e = eff if math.isfinite(eff) else 1.0
    print(
        f"\nmodel: w = {fps_total:.0f} frames/s x {1e3 * per_frame:.2f} ms + {report_per_s:.3f} s = "
        f"{w:.2f} task-s per flight-s; efficiency E = {100 * e:.0f} %\n"
    )
    print("| cores per node | nodes for 160 flight-h in 8 wall-h | at E = 100 % |")
    print("|---:|---:|---:|")
    for k in NODE_CORES:
        need = FLEET_FLIGHT_HOURS * w / (WALL_HOURS * k * e)
        ideal = FLEET_FLIGHT_HOURS * w / (WALL_HOURS * k)
        print(f"| {k} | {math.ceil(need)} ({need:.1f}) | {math.ceil(ideal)} ({ideal:.1f}) |")


if __name__ == "__main__":
    main()
