"""Back-end speed of one `fusion run`: wall and CPU time of every stage after detection (time
offsets, each fused estimator and its parts, metrics, plots, report), peak memory of the main
process per stage, and every estimator's accuracy (ATE, NEES), for before/after comparisons.

    PYTHONPATH=$PWD python3 scripts/bench_backend_speed.py LOG OUT [--workers N] [--json FILE]
        [--compare OLD.json] [--profile FILE.prof]

OUT should hold a copy of the flight's detections.csv (the cache, reused when the log is
unchanged), so that detection is skipped; OUT is replaced (`--force`).  The stages are timed by
wrapping the pipeline's stage functions (nested calls are shown indented under their caller);
CPU time is time.process_time (this process, all threads) plus the CPU of the workers (fusion.
parallel.worker_usage: each one's process time since it was forked), so it stays meaningful on a
loaded machine where wall time does not; the "workers" column is their share.  "idle est.": this
process's CPU plus, for each pool of workers, its busiest worker's CPU (parallel.WorkerUsage.
longest_cpu_s): about the wall time on an idle machine, not counting the forks themselves.
`--workers` is RunConfig.workers (default: one per core, as `fusion run`); with more than one,
the functions the pipeline hands to workers (smooth, smooth_incremental, run_ekf) are not
wrapped (a wrapper cannot be sent to a process) and what runs inside workers has no row of its
own.  Peak memory: the main process's VmHWM, reset at the start of every timed call through
/proc/self/clear_refs (the peak so far credited to its callers), so each row shows the peak RSS
inside that stage; where the kernel refuses, the peak so far; the workers' largest peak is
printed below.  `--compare` prints the accuracy of both runs side by side and fails (exit 1)
when an estimator's ATE or NEES moved by more than --tolerance (relative)."""

from __future__ import annotations

import argparse
import cProfile
import functools
import importlib
import json
import os
import platform
import resource
import sys
import time
from pathlib import Path
from typing import Any

from fusion.parallel import worker_count, worker_usage
from fusion.pipeline import RunConfig, run

# (module, attribute, label): the functions timed; a module's own references are patched, so a
# name imported elsewhere is listed once per importing module
TIMED = [
    ("fusion.pipeline", "localize_stage", "localize (paper + PnP)"),
    ("fusion.pipeline", "resolve_time_offsets", "time offsets"),
    ("fusion.estimate.timeoffset", "estimate_floor_offset", "floor profile"),
    ("fusion.estimate.timeoffset", "estimate_front_offset", "front profile"),
    ("fusion.estimate.timeoffset", "smooth", "smoother solve"),
    ("fusion.pipeline", "estimate_mount_windowed", "whole flight, shared with the mount check"),
    ("fusion.estimate.window", "estimate_mount_and_states", "mount solve"),
    ("fusion.pipeline", "check_mount", "mount check"),
    ("fusion.pipeline", "fuse_stage", "fuse_stage"),
    ("fusion.warehouse.floorcodes", "as_built_input", "as-built input"),
    ("fusion.pipeline", "smooth_windowed", "smoother (windows)"),
    ("fusion.pipeline", "smooth", "smoother"),
    ("fusion.estimate.smoother", "_smooth_once", "batch solve"),
    ("fusion.estimate.smoother", "build_problem", "build problem"),
    ("fusion.estimate.smoother", "solve", "LM"),
    ("fusion.estimate.smoother", "problem_variance_components", "variance components"),
    ("fusion.estimate.smoother", "chain_marginals", "covariances (chain)"),
    ("fusion.estimate.smoother", "chain_marginals_with_codes", "covariances (chain + codes)"),
    ("fusion.pipeline", "smooth_incremental", "incremental"),
    ("fusion.pipeline", "run_ekf", "ekf"),
    ("fusion.pipeline", "assess_result", "health"),
    ("fusion.pipeline", "_write_estimates", "write estimates"),
    ("fusion.pipeline", "evaluate", "metrics"),
    ("fusion.pipeline", "write_report", "report"),
    ("fusion.evaluate.report", "plot_all", "plots"),
    ("fusion.evaluate.plots", "_save", "savefig"),
]
SENT_TO_WORKERS = {
    ("fusion.pipeline", "smooth"),
    ("fusion.pipeline", "smooth_incremental"),
    ("fusion.pipeline", "run_ekf"),
}
"""Functions the pipeline passes to worker processes as objects: left unwrapped with workers > 1."""


def rss_mb(field: str = "VmRSS") -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _reset_peak() -> bool:
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


class Timer:
    """Inclusive wall / CPU seconds, calls, RSS at entry and peak RSS per call path (also
    scripts/bench_memory.py's)."""

    def __init__(self) -> None:
        self.stack: list[str] = []
        self.rows: dict[tuple[str, ...], dict[str, float]] = {}
        self.peak_reset = _reset_peak()

    def wrap(self, fn, label: str):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            self.stack.append(label)
            path = tuple(self.stack)
            row = self.rows.setdefault(
                path,
                {
                    "wall_s": 0.0,
                    "cpu_s": 0.0,
                    "worker_cpu_s": 0.0,
                    "idle_s": 0.0,
                    "calls": 0,
                    "peak_mb": 0.0,
                    "rss_in_mb": 0.0,
                },
            )
            if self.peak_reset:  # the callers' peak so far, then a fresh peak for this call
                self._credit(path[:-1], rss_mb("VmHWM"))
                _reset_peak()
            row["rss_in_mb"] = max(row["rss_in_mb"], rss_mb())
            u, w, c = worker_usage(), time.perf_counter(), time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                row["wall_s"] += time.perf_counter() - w
                main_cpu, after = time.process_time() - c, worker_usage()
                in_workers = after.cpu_s - u.cpu_s
                row["cpu_s"] += main_cpu + in_workers
                row["worker_cpu_s"] += in_workers
                row["idle_s"] += main_cpu + after.longest_cpu_s - u.longest_cpu_s
                row["calls"] += 1
                self._credit(path, rss_mb("VmHWM"))
                self.stack.pop()

        return timed

    def _credit(self, path: tuple[str, ...], peak_mb: float) -> None:
        """A peak seen inside `path` counts for it and every caller."""
        for i in range(1, len(path) + 1):
            row = self.rows.get(path[:i])
            if row is not None:
                row["peak_mb"] = max(row["peak_mb"], peak_mb)

    def install(self, targets: list[tuple[str, str, str]] = TIMED, skip: set = frozenset()) -> None:
        for mod, attr, label in targets:
            if (mod, attr) in skip:
                continue
            try:
                m = importlib.import_module(mod)
            except ImportError:
                continue
            if hasattr(m, attr):
                setattr(m, attr, self.wrap(getattr(m, attr), label))


def accuracy(metrics: dict) -> dict[str, dict[str, Any]]:
    """Per estimator: ATE RMSE, yaw MAE, NEES (position 3-dof, pose 6-dof), loads mapped."""
    out: dict[str, dict[str, Any]] = {}
    for name, m in (metrics.get("trajectories") or {}).items():
        row = {
            "ate_rmse_m": m.get("ate_rmse_m"),
            "ate_on_ref_m": m.get("ate_rmse_on_reference_frames_m"),
            "yaw_mae_deg": m.get("mae_yaw_deg"),
            "n_poses": m.get("n_poses"),
        }
        for key in ("nees_position_3dof", "nees_pose_6dof"):
            if isinstance(m.get(key), dict):
                row[key] = m[key].get("nees_mean")
        out[name] = row
    for name, m in (metrics.get("load_maps") or {}).items():
        out.setdefault(name, {})["loads_mapped"] = m.get("n_mapped")
    return out


QUANTITIES = (
    "ate_rmse_m",
    "ate_on_ref_m",
    "yaw_mae_deg",
    "nees_position_3dof",
    "nees_pose_6dof",
    "loads_mapped",
)


def compare(old: dict, new: dict, tolerance: float) -> bool:
    ok = True
    print("\n| estimator | quantity | before | after | change |\n|---|---|--:|--:|--:|")
    for name in sorted(set(old) | set(new)):
        for q in QUANTITIES:
            a, b = old.get(name, {}).get(q), new.get(name, {}).get(q)
            if a is None and b is None:
                continue
            if a is None or b is None:
                print(f"| {name} | {q} | {a} | {b} | missing |")
                ok = False
                continue
            rel = (b - a) / abs(a) if a else (0.0 if b == a else float("inf"))
            flag = ""
            worse = rel > tolerance if q != "loads_mapped" else b < a
            if q.startswith("nees"):  # NEES: the distance from its dof matters, not its size
                dof = 3 if "3dof" in q else 6
                worse = abs(b - dof) > abs(a - dof) * (1 + tolerance) + 1e-9
            if worse:
                flag, ok = " **worse**", False
            print(f"| {name} | {q} | {a:.6g} | {b:.6g} | {100 * rel:+.2f} %{flag} |")
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--json", type=Path, help="write the timings and accuracy here")
    ap.add_argument("--compare", type=Path, help="an earlier --json to compare the accuracy with")
    ap.add_argument("--tolerance", type=float, default=0.02, help="relative change allowed (default 2 %%)")
    ap.add_argument("--profile", type=Path, help="also write a cProfile of the run here")
    ap.add_argument("--no-incremental", action="store_true")
    ap.add_argument("--workers", type=int, help="RunConfig.workers (default: one per core)")
    args = ap.parse_args()

    timer = Timer()
    timer.install(skip=SENT_TO_WORKERS if worker_count(args.workers) > 1 else set())
    cfg = RunConfig(progress=False, force=True, incremental=not args.no_incremental, workers=args.workers)
    prof = cProfile.Profile() if args.profile else None
    u, w, c = worker_usage(), time.perf_counter(), time.process_time()
    if prof is not None:
        prof.enable()
    res = run(args.log, args.out, cfg)
    if prof is not None:
        prof.disable()
        prof.dump_stats(str(args.profile))
    after = worker_usage()
    in_workers = after.cpu_s - u.cpu_s
    wall, main_cpu = time.perf_counter() - w, time.process_time() - c
    cpu, idle = main_cpu + in_workers, main_cpu + after.longest_cpu_s - u.longest_cpu_s
    load = os.getloadavg()
    print(
        f"{time.strftime('%Y-%m-%d %H:%M')} UTC, {platform.machine()}, {os.cpu_count()} cores, "
        f"workers {worker_count(args.workers)}, load "
        f"{load[0]:.1f}, python {platform.python_version()}; flight {res.log_summary['duration_s']:.0f} s, "
        f"{res.log_summary['floor_frames']} floor frames"
    )
    for note in res.notes:
        if "reused" in note:
            print("note:", note)
    print(
        "\n| stage | calls | wall s | CPU s | of which workers | idle est. s | peak RSS MB (main) |\n"
        "|---|--:|--:|--:|--:|--:|--:|"
    )
    for path, row in sorted(timer.rows.items(), key=lambda kv: call_path_order(kv[0], timer.rows)):
        name = "&nbsp;" * 4 * (len(path) - 1) + path[-1]
        w, c, cw, mb = row["wall_s"], row["cpu_s"], row["worker_cpu_s"], row["peak_mb"]
        print(
            f"| {name} | {row['calls']:.0f} | {w:.2f} | {c:.2f} | {cw:.2f} | {row['idle_s']:.2f} | {mb:.0f} |"
        )
    fr = ("time offsets", "fuse_stage", "health", "write estimates", "metrics", "report")
    top = [r for p, r in timer.rows.items() if len(p) == 1 and p[0] in fr]
    back_w, back_c, back_cw, back_i = (
        sum(r[k] for r in top) for k in ("wall_s", "cpu_s", "worker_cpu_s", "idle_s")
    )
    print(
        f"| **back end (time offsets to report)** | | **{back_w:.2f}** | **{back_c:.2f}** | {back_cw:.2f} "
        f"| **{back_i:.2f}** | |"
    )
    print(
        f"| total `run` | | {wall:.2f} | {cpu:.2f} | {in_workers:.2f} | {idle:.2f} | {rss_mb('VmHWM'):.0f} |"
    )
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\npeak RSS of the main process over the whole run: {peak:.0f} MB")
    print(
        f"largest peak RSS of a worker process (VmHWM at its last call): {worker_usage().peak_rss_mb:.0f} MB"
    )
    acc = accuracy(res.metrics or {})
    print(
        "\n| estimator | ATE RMSE mm | ATE@PnP mm | yaw MAE deg | NEES 3-dof | NEES 6-dof | loads |\n"
        "|---|--:|--:|--:|--:|--:|--:|"
    )
    for name, a in acc.items():

        def f(v, scale=1.0, fmt="{:.4f}"):
            return "-" if v is None else fmt.format(v * scale)

        print(
            f"| {name} | {f(a.get('ate_rmse_m'), 1e3)} | {f(a.get('ate_on_ref_m'), 1e3)} | "
            f"{f(a.get('yaw_mae_deg'))} | {f(a.get('nees_position_3dof'), fmt='{:.3f}')} | "
            f"{f(a.get('nees_pose_6dof'), fmt='{:.3f}')} | {a.get('loads_mapped', '-')} |"
        )
    record = {
        "date": time.strftime("%Y-%m-%d %H:%M UTC"),
        "load": load[0],
        "workers": worker_count(args.workers),
        "wall_s": wall,
        "cpu_s": cpu,
        "worker_cpu_s": in_workers,
        "back_end_wall_s": back_w,
        "back_end_cpu_s": back_c,
        "back_end_idle_estimate_s": back_i,
        "idle_estimate_s": idle,
        "peak_rss_mb": peak,
        "worker_peak_rss_mb": worker_usage().peak_rss_mb,
        "stages": [{"path": list(p), **r} for p, r in timer.rows.items()],
        "accuracy": acc,
        "timings_s": res.timings_s,
    }
    if args.json:
        args.json.write_text(json.dumps(record, indent=1))
    if args.compare:
        old = json.loads(args.compare.read_text())["accuracy"]
        if not compare(old, acc, args.tolerance):
            print("\naccuracy: WORSE than", args.compare)
            return 1
        print("\naccuracy: not worse than", args.compare)
    return 0


def call_path_order(path: tuple[str, ...], rows: dict) -> tuple:
    """Depth-first order: each path after its parent, siblings by first appearance."""
    keys = list(rows)
    return tuple(min(keys.index(k) for k in keys if k[: i + 1] == path[: i + 1]) for i in range(len(path)))


if __name__ == "__main__":
    sys.exit(main())
