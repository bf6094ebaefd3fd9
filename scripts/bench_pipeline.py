"""End-to-end speed of `fusion run` on a simulated two-camera flight (issue: 10-minute flight,
640x480, 30 fps, at least 10x faster than real time on this machine), with the time per stage
and the peak memory of the main process and of the detection workers.

    python scripts/bench_pipeline.py [--minutes 10] [--workdir /tmp/fusion-bench] [--keep]

The flight is simulated once into WORKDIR/log-<minutes>min and reused on later runs.
Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import platform
import resource
import shutil
import time
from pathlib import Path

from bench_run_memory import DescendantSampler  # scripts/, on the path when run as a script

from fusion.pipeline import RunConfig, run
from fusion.sim.simulate import simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--workdir", type=Path, default=Path("/tmp/fusion-bench"))
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    log = args.workdir / f"log-{args.minutes:g}min"
    t_sim = None
    if not (log / "world.yaml").exists():
        t = time.perf_counter()
        simulate(
            log,
            scenario="default",
            duration_s=60 * args.minutes,
            seed=args.seed,
            overwrite=True,
            progress=True,
        )
        t_sim = time.perf_counter() - t
    out = args.workdir / f"out-{args.minutes:g}min"
    shutil.rmtree(out, ignore_errors=True)
    # the detection workers are the forkserver's children, not this process's: RUSAGE_CHILDREN
    # does not see them (it printed 3 MB), their /proc VmHWM does
    workers = DescendantSampler(os.getpid())
    workers.start()
    t = time.perf_counter()
    res = run(log, out, RunConfig(progress=True, force=True))
    wall = time.perf_counter() - t
    # second run: detections come from the cache
    t = time.perf_counter()
    res2 = run(log, out, RunConfig(progress=False, force=True))
    wall_cached = time.perf_counter() - t
    workers.stop()
    self_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    child_mb = workers.largest_mb() or 0.0
    flight_s = res.log_summary["duration_s"]
    print(
        f"\n{time.strftime('%Y-%m-%d %H:%M')} UTC, {platform.machine()}, {os.cpu_count()} cores, "
        f"python {platform.python_version()}"
    )
    print(
        f"flight: {flight_s:.0f} s, {res.log_summary['floor_frames']} frames per camera (640x480, "
        f"two cameras), {res.log_summary['imu_samples']} IMU samples"
    )
    if t_sim is not None:
        print(f"simulation: {t_sim:.1f} s")
    print("\n| stage | time [s] |\n|---|--:|")
    for k, v in res.timings_s.items():
        print(f"| {k.removesuffix('_s')} | {v:.1f} |")
    print(f"| **total `fusion run`** | **{wall:.1f}** ({flight_s / wall:.1f}x real time) |")
    print(f"| total, detections cached | {wall_cached:.1f} ({flight_s / wall_cached:.1f}x real time) |")
    print(
        f"\npeak memory (MiB): main process {self_mb:.0f} MB, largest detection worker {child_mb:.0f} MB "
        f"(VmHWM of this process's descendants, sampled every {workers.interval:g} s)"
    )
    fused = (res.metrics or {}).get("trajectories", {})
    if fused:
        print("\n| estimator | ATE RMSE [cm] | yaw MAE [deg] |\n|---|--:|--:|")
        for name, m in fused.items():
            print(f"| {name} | {100 * m['ate_rmse_m']:.2f} | {m['mae_yaw_deg']:.3f} |")
    del res2


if __name__ == "__main__":
    main()
