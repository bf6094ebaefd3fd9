"""Speed of the causal back ends and the report of one `fusion run`: the incremental smoother,
the EKF, metrics and report (plots), replayed on the exact inputs the pipeline gave them.

    # once: run the pipeline and keep the inputs of those four stages (OUT holds detections.csv)
    PYTHONPATH=$PWD python3 scripts/bench_report_speed.py capture LOG OUT CAPTURE.pkl
    # then, as often as needed (before / after a change):
    PYTHONPATH=$PWD python3 scripts/bench_report_speed.py replay CAPTURE.pkl OUT2 [--json F]
        [--compare OLD.json] [--profile F.prof] [--only incremental,ekf,metrics,report]

CPU time is time.process_time (this process), meaningful on a loaded machine.  Memory: RSS at
each stage's entry and its peak inside the stage (VmHWM reset at entry through
/proc/self/clear_refs, so GTSAM's heap counts; bench_backend_speed.rss_mb).  `replay --json`
keeps every estimate (trajectory, covariance) so that `--compare` can print how far the new
estimates are from the old ones (max |difference|), next to the accuracy (ATE, yaw MAE, NEES)."""

from __future__ import annotations

import argparse
import cProfile
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np
from bench_backend_speed import _reset_peak, rss_mb  # scripts/ is sys.path[0]

import fusion.pipeline as pipeline
from fusion.evaluate.metrics import evaluate
from fusion.evaluate.report import write_report
from fusion.pipeline import RunConfig, run

CAPTURED = ("smooth_incremental", "run_ekf", "evaluate", "write_report")


def capture(log: Path, out: Path, dest: Path) -> None:
    """Run the pipeline on LOG into OUT and pickle the arguments of the captured stages."""
    calls: dict[str, tuple] = {}

    def hook(name, fn):
        def wrapped(*args, **kwargs):
            calls[name] = (args, kwargs)
            return fn(*args, **kwargs)

        return wrapped

    for name in CAPTURED:
        setattr(pipeline, name, hook(name, getattr(pipeline, name)))
    run(log, out, RunConfig(progress=False, force=True))
    with open(dest, "wb") as f:
        pickle.dump(calls, f, protocol=pickle.HIGHEST_PROTOCOL)
    print("captured", sorted(calls), "into", dest)


def _traj_arrays(res) -> dict:
    t = res.trajectory
    loads = {l.load_id: (np.asarray(l.p_world, float), l.cov_world) for l in res.loads.loads}
    return {
        "t": np.asarray(t.timestamps_ns),
        "T": np.asarray(t.T_world_body),
        "cov": t.covariances,
        "loads": loads,
    }


def replay(path: Path, out: Path, only: set[str], prof: cProfile.Profile | None) -> dict:
    with open(path, "rb") as f:
        calls = pickle.load(f)
    from fusion.estimate import run_ekf, smooth_incremental

    fns = {"smooth_incremental": smooth_incremental, "run_ekf": run_ekf}
    rows, estimates, replayed = {}, {}, {}
    memory: dict[str, tuple[float, float]] = {}  # label -> (RSS at entry, peak inside) MB
    out.mkdir(parents=True, exist_ok=True)
    for name, label in (("smooth_incremental", "incremental"), ("run_ekf", "ekf")):
        if label not in only:
            continue
        args, kwargs = calls[name]
        _reset_peak()
        rss_in = rss_mb()
        w, c = time.perf_counter(), time.process_time()
        if prof is not None:
            prof.enable()
        res = fns[name](*args, **kwargs)
        if prof is not None:
            prof.disable()
        rows[label] = (time.perf_counter() - w, time.process_time() - c)
        memory[label] = (rss_in, rss_mb("VmHWM"))
        estimates[label] = _traj_arrays(res)
        replayed[label] = res.trajectory
    metrics = None
    if "metrics" in only:
        args, kwargs = calls["evaluate"]
        # the metrics of the estimates just replayed (the captured ones for the others)
        args = (args[0], {**args[1], **{k: replayed[k] for k in replayed if k in args[1]}}, *args[2:])
        w, c = time.perf_counter(), time.process_time()
        if prof is not None:
            prof.enable()
        metrics = evaluate(*args, **kwargs)
        if prof is not None:
            prof.disable()
        rows["metrics"] = (time.perf_counter() - w, time.process_time() - c)
    if "report" in only:
        args, kwargs = calls["write_report"]
        args = (out, *args[1:])
        w, c = time.perf_counter(), time.process_time()
        if prof is not None:
            prof.enable()
        write_report(*args, **kwargs)
        if prof is not None:
            prof.disable()
        rows["report"] = (time.perf_counter() - w, time.process_time() - c)
    load = os.getloadavg()[0]
    print(f"{time.strftime('%Y-%m-%d %H:%M')} UTC, load {load:.1f}")
    print("\n| stage | wall s | CPU s |\n|---|--:|--:|")
    for label, (w, c) in rows.items():
        print(f"| {label} | {w:.2f} | {c:.2f} |")
    print(f"| **total** | {sum(r[0] for r in rows.values()):.2f} | {sum(r[1] for r in rows.values()):.2f} |")
    if memory:
        print("\n| stage | RSS at entry MB | peak RSS MB | growth MB |\n|---|--:|--:|--:|")
        for label, (a, b) in memory.items():
            print(f"| {label} | {a:.0f} | {b:.0f} | {b - a:.0f} |")
    acc = {}
    if metrics is not None:
        for name, m in (metrics.get("trajectories") or {}).items():
            acc[name] = {
                "ate_rmse_m": m.get("ate_rmse_m"),
                "yaw_mae_deg": m.get("mae_yaw_deg"),
                "nees_pose_6dof": (m.get("nees_pose_6dof") or {}).get("nees_mean"),
                "nees_position_3dof": (m.get("nees_position_3dof") or {}).get("nees_mean"),
            }
        print("\n| estimator | ATE mm | yaw MAE deg | NEES 3 | NEES 6 |\n|---|--:|--:|--:|--:|")
        for name, a in acc.items():
            vals = [a["ate_rmse_m"] and a["ate_rmse_m"] * 1e3, a["yaw_mae_deg"]]
            vals += [a["nees_position_3dof"], a["nees_pose_6dof"]]
            print(f"| {name} | " + " | ".join("-" if v is None else f"{v:.6g}" for v in vals) + " |")
    return {
        "rows": rows,
        "memory": memory,
        "accuracy": acc,
        "estimates": estimates,
        "metrics": metrics,
        "load": load,
    }


def compare_estimates(old: dict, new: dict) -> None:
    for label in sorted(set(old["estimates"]) & set(new["estimates"])):
        a, b = old["estimates"][label], new["estimates"][label]
        if a["T"].shape != b["T"].shape:
            print(f"{label}: shapes differ {a['T'].shape} vs {b['T'].shape}")
            continue
        dT = np.abs(a["T"] - b["T"]).max()
        dc = np.abs(a["cov"] - b["cov"]).max() if a["cov"] is not None and b["cov"] is not None else None
        rc = None
        if dc is not None:
            rc = np.max(np.abs(a["cov"] - b["cov"]) / (np.abs(a["cov"]).max(axis=(1, 2))[:, None, None]))
        print(f"{label}: max |dT| {dT:.3g}, max |dcov| {dc}, max relative dcov {rc}")
        la, lb = a.get("loads"), b.get("loads")
        if la is not None and lb is not None:
            if set(la) != set(lb):
                print(f"{label}: load ids differ {sorted(set(la) ^ set(lb))}")
            common = sorted(set(la) & set(lb))
            dp = max((np.abs(la[i][0] - lb[i][0]).max() for i in common), default=0.0)
            dcl = max(
                (
                    np.abs(la[i][1] - lb[i][1]).max() / np.abs(la[i][1]).max()
                    for i in common
                    if la[i][1] is not None and lb[i][1] is not None
                ),
                default=0.0,
            )
            print(f"{label} loads: {len(common)} common, max |dp| {dp:.3g} m, max relative dcov {dcl:.3g}")
    for name in sorted(set(old["accuracy"]) & set(new["accuracy"])):
        for q, v in new["accuracy"][name].items():
            u = old["accuracy"][name].get(q)
            if u is not None and v is not None and u != v:
                print(f"{name} {q}: {u:.9g} -> {v:.9g}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("capture")
    c.add_argument("log", type=Path)
    c.add_argument("out", type=Path)
    c.add_argument("capture", type=Path)
    r = sub.add_parser("replay")
    r.add_argument("capture", type=Path)
    r.add_argument("out", type=Path)
    r.add_argument("--json", type=Path, help="pickle the timings, accuracy and estimates here")
    r.add_argument("--compare", type=Path, help="an earlier --json to compare with")
    r.add_argument("--profile", type=Path)
    r.add_argument("--only", default="incremental,ekf,metrics,report")
    args = ap.parse_args()
    if args.cmd == "capture":
        capture(args.log, args.out, args.capture)
        return 0
    prof = cProfile.Profile() if args.profile else None
    rec = replay(args.capture, args.out, set(args.only.split(",")), prof)
    if prof is not None:
        prof.dump_stats(str(args.profile))
    if args.json:
        with open(args.json, "wb") as f:
            pickle.dump(rec, f)
    if args.compare:
        with open(args.compare, "rb") as f:
            compare_estimates(pickle.load(f), rec)
    return 0


if __name__ == "__main__":
    sys.exit(main())
