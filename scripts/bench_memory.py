"""Peak memory of the batch smoother (issue 13 item 2: <= 1 GB per worker for a 30-minute flight).

    # once: the smoother's exact inputs of a `fusion run` (detections cached), pickled
    PYTHONPATH=$PWD python3 scripts/bench_memory.py capture LOG DETECTIONS_DIR WORK
    # then, as often as needed: the first M minutes of those inputs through the smoother
    PYTHONPATH=$PWD python3 scripts/bench_memory.py smooth WORK --minutes 2 5 10 [--window-s S]
        [--compare] [--json FILE]
    # or the back end fed a synthetic flight (tests/test_estimate.make_flight) of any length
    PYTHONPATH=$PWD python3 scripts/bench_memory.py smooth - --synthetic --minutes 10 30 --window-s 180
    # the causal estimators instead of the batch smoother, on either input
    PYTHONPATH=$PWD python3 scripts/bench_memory.py smooth - --synthetic --minutes 30 --estimator incremental

`capture` runs the pipeline up to the fusion stage on a copy of DETECTIONS_DIR/detections.csv
(the cache: detection is skipped) with the incremental smoother off, records every stage's peak
RSS, and pickles the arguments the pipeline passes to `smooth` (WORK/smooth_inputs.pkl).
`smooth` runs each truncated flight in a fresh child process (so one flight's heap does not
carry into the next) and reports its RSS before the solve, its peak inside each part of the
smoother (VmHWM, reset at the start of every wrapped call through /proc/self/clear_refs, so
GTSAM's C++ heap counts, which tracemalloc does not see), the growth per flight minute, and the
trajectory / load results for comparisons (windowed against whole: `--window-s`).
`--estimator incremental | ekf` runs the incremental smoother (iSAM2) or the EKF on the same
inputs instead (the smoother-only arguments dropped; `--window-s` does not apply)."""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import pickle
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_backend_speed import Timer, call_path_order, rss_mb  # scripts/ is sys.path[0]

# (module, attribute, label): functions whose peak RSS is reported (a module's own reference)
WRAPPED = [
    ("fusion.pipeline", "resolve_time_offsets", "time offsets"),
    ("fusion.estimate.timeoffset", "estimate_floor_offset", "floor profile"),
    ("fusion.estimate.timeoffset", "estimate_front_offset", "front profile"),
    ("fusion.pipeline", "estimate_mount_windowed", "whole flight, shared with the mount check"),
    ("fusion.estimate.window", "estimate_mount_and_states", "mount solve"),
    ("fusion.pipeline", "check_mount", "mount check"),
    ("fusion.pipeline", "fuse_stage", "fuse_stage"),
    ("fusion.pipeline", "smooth", "smoother"),
    ("fusion.estimate.window", "smooth_windowed", "smoother (windowed)"),
    ("fusion.estimate.window", "smooth", "window solve"),
    ("fusion.estimate.smoother", "_smooth_once", "batch solve"),
    ("fusion.estimate.smoother", "build_problem", "build problem"),
    ("fusion.estimate.smoother", "solve", "LM"),
    ("fusion.estimate.smoother", "problem_variance_components", "variance components"),
    ("fusion.estimate.smoother", "chain_marginals", "covariances (chain)"),
    ("fusion.estimate.smoother", "chain_marginals_with_codes", "covariances (chain + codes)"),
    ("fusion.pipeline", "run_ekf", "ekf"),
    ("fusion.estimate.smoother", "smooth_incremental", "incremental"),
    ("fusion.estimate.ekf", "run_ekf", "ekf"),
]
ESTIMATORS = ("smoother", "incremental", "ekf")
# the keyword arguments each causal estimator takes from the smoother's captured ones
CAUSAL_KWARGS = {
    "incremental": ("front_camera", "velocity", "config", "floor_frames", "floor_camera"),
    "ekf": ("front_camera", "velocity", "config", "floor_camera"),
}


def run_estimator(estimator: str, args: tuple, kwargs: dict, window_s: float | None):
    """One back end on the smoother's inputs: the (windowed) batch smoother, or a causal one."""
    from fusion.estimate import ekf, smoother, window

    if estimator == "smoother":
        kwargs = dict(kwargs)
        config = kwargs.pop("config", None)
        if config is None:
            from fusion.estimate.common import FusionConfig

            config = FusionConfig()
        wcfg = (
            window.WindowConfig(window_s=window_s, min_flight_s=0.0)
            if window_s is not None
            else window.WindowConfig(min_flight_s=float("inf"))
        )
        return window.smooth_windowed(*args, config=config, window=wcfg, **kwargs)
    kept = {k: v for k, v in kwargs.items() if k in CAUSAL_KWARGS[estimator]}
    if estimator == "incremental":
        return smoother.smooth_incremental(*args, **kept)
    return ekf.run_ekf(*args, **kept)


MB = 1024 * 1024
INPUTS = "smooth_inputs.pkl"
TRUTH = "truth.pkl"


def table(tracker: Timer) -> str:
    """The tracker's rows: calls, CPU s, RSS at entry and peak RSS per call path."""
    out = ["| stage | calls | CPU s | RSS at entry MB | peak RSS MB |", "|---|--:|--:|--:|--:|"]
    for path in sorted(tracker.rows, key=lambda p: call_path_order(p, tracker.rows)):
        r = tracker.rows[path]
        name = "&nbsp;" * 4 * (len(path) - 1) + path[-1]
        cells = f"{r['calls']:.0f} | {r['cpu_s']:.1f} | {r['rss_in_mb']:.0f} | {r['peak_mb']:.0f}"
        out.append(f"| {name} | {cells} |")
    return "\n".join(out)


# ---------------------------------------------------------------------------------- capture


def capture(log_dir: Path, det_dir: Path, work: Path) -> None:
    from fusion import pipeline

    work.mkdir(parents=True, exist_ok=True)
    out = work / "out"
    if out.exists():
        shutil.rmtree(out)
    out.mkdir()
    shutil.copy(det_dir / "detections.csv", out / "detections.csv")
    tracker = Timer()
    tracker.install(WRAPPED)
    inner = pipeline.smooth

    def grab(*args, **kwargs):
        with open(work / INPUTS, "wb") as f:
            pickle.dump((args, kwargs), f, protocol=pickle.HIGHEST_PROTOCOL)
        return inner(*args, **kwargs)

    pipeline.smooth = grab
    log = pipeline.read_flight(log_dir)
    with open(work / TRUTH, "wb") as f:
        pickle.dump(
            (log.groundtruth, log.loads_groundtruth, log.blackouts), f, protocol=pickle.HIGHEST_PROTOCOL
        )
    cfg = pipeline.RunConfig(progress=False, force=True, incremental=False, smoother_window_s=0.0)
    t = time.perf_counter()
    pipeline.run(log_dir, out, cfg, until="smooth")
    print(f"capture: {time.perf_counter() - t:.0f} s wall; inputs in {work / INPUTS}")
    print(table(tracker))
    print(f"peak RSS of the process: {rss_mb('VmPeak'):.0f} MB virtual, high-water {rss_mb('VmHWM'):.0f} MB")


# ---------------------------------------------------------------------------------- truncation


def truncate(args: tuple, kwargs: dict, minutes: float | None) -> tuple[tuple, dict]:
    """The smoother's inputs cut to the first `minutes` of the flight (None: whole)."""
    if minutes is None:
        return args, kwargs
    from fusion.log.euroc import ImuData

    frame_t, imu, raw, load_obs = args[:4]
    frame_t = np.asarray(frame_t)
    t_end = frame_t[0] + int(minutes * 60e9)
    keep = frame_t <= t_end
    frame_t = frame_t[keep]
    if imu is not None:
        m = imu.timestamps_ns <= t_end + int(1e9)
        imu = replace(
            imu,
            **{
                f: getattr(imu, f)[m]
                for f in ImuData.__dataclass_fields__
                if isinstance(getattr(imu, f), np.ndarray) and len(getattr(imu, f)) == len(m)
            },
        )
    r = np.asarray(raw.timestamps_ns) <= t_end
    raw = replace(
        raw,
        timestamps_ns=raw.timestamps_ns[r],
        T_world_body=raw.T_world_body[r],
        covariances=None if raw.covariances is None else raw.covariances[r],
    )
    if load_obs:
        load_obs = [o for o in load_obs if o.timestamp_ns <= t_end]
    kwargs = dict(kwargs)
    if kwargs.get("velocity") is not None:
        v = kwargs["velocity"]
        mv = v.timestamps_ns <= t_end
        kwargs["velocity"] = replace(
            v,
            **{
                f: getattr(v, f)[mv]
                for f in type(v).__dataclass_fields__
                if isinstance(getattr(v, f), np.ndarray) and len(getattr(v, f)) == len(mv)
            },
        )
    if kwargs.get("floor_frames"):
        kwargs["floor_frames"] = {t: s for t, s in kwargs["floor_frames"].items() if t <= t_end}
    if kwargs.get("as_built") is not None:
        raise SystemExit("truncating as-built floor-code inputs is not supported by this bench")
    return (frame_t, imu, raw, load_obs, *args[4:]), kwargs


# ---------------------------------------------------------------------------------- smooth


def _child(work: Path, minutes: float | None, window_s: float | None, queue, estimator: str) -> None:
    tracker = Timer()
    tracker.install(WRAPPED)
    with open(work / INPUTS, "rb") as f:
        args, kwargs = pickle.load(f)
    args, kwargs = truncate(args, kwargs, minutes)
    base = rss_mb()
    c = time.process_time()
    res = run_estimator(estimator, args, kwargs, window_s)
    cpu = time.process_time() - c
    # the wrappers reset VmHWM at each call: the run's peak is the largest one credited
    peak = max([rss_mb("VmHWM")] + [r["peak_mb"] for r in tracker.rows.values()])
    tr = res.trajectory
    accuracy = {}
    if (work / TRUTH).is_file():
        from fusion.evaluate.metrics import evaluate

        with open(work / TRUTH, "rb") as f:
            gt, loads_gt, blackouts = pickle.load(f)
        if gt is not None:
            m = evaluate(gt, {estimator: tr}, {estimator: res.loads}, loads_gt, blackouts)
            t = m["trajectories"][estimator]
            accuracy = {
                "ate_rmse_mm": 1e3 * t["ate_rmse_m"],
                "nees_position_3dof": (t.get("nees_position_3dof") or {}).get("nees_mean"),
                "nees_pose_6dof": (t.get("nees_pose_6dof") or {}).get("nees_mean"),
                "loads": {
                    k: v for k, v in m["load_maps"].get(estimator, {}).items() if isinstance(v, (int, float))
                },
            }
    queue.put(
        {
            "estimator": estimator,
            "minutes": minutes,
            "window_s": window_s,
            "frames": len(tr.timestamps_ns),
            "rss_before_mb": base,
            "peak_mb": peak,
            "accuracy": accuracy,
            "cpu_s": cpu,
            "table": table(tracker),
            "T": tr.T_world_body,
            "cov": tr.covariances,
            "loads": {e.load_id: (np.asarray(e.p_world), e.cov_world) for e in res.loads.loads},
            "stats": {k: v for k, v in res.stats.items() if isinstance(v, (int, float, str))},
        }
    )


def _synthetic_child(work: Path, minutes: float, window_s: float | None, queue, estimator: str) -> None:
    """The back end fed a synthetic flight: tests/test_estimate.make_flight (analytic trajectory,
    30 fps PnP-like poses, 200 Hz IMU, three loads seen every 6th frame), `minutes` long."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.test_estimate import FRONT_CAM, make_flight

    fl = make_flight(seed=0, duration_s=60.0 * minutes, gaps=((30.0, 32.0),))
    tracker = Timer()
    tracker.install(WRAPPED)
    base = rss_mb()
    c = time.process_time()
    res = run_estimator(
        estimator, (fl.frame_t, fl.imu, fl.raw, fl.load_obs), {"front_camera": FRONT_CAM}, window_s
    )
    cpu = time.process_time() - c
    peak = max([rss_mb("VmHWM")] + [r["peak_mb"] for r in tracker.rows.values()])
    n = len(res.trajectory.timestamps_ns)  # the causal estimators start at the first fix
    err = np.linalg.norm(res.trajectory.T_world_body[:, :3, 3] - fl.T_true[-n:, :3, 3], axis=1)
    queue.put(
        {
            "estimator": estimator,
            "minutes": minutes,
            "window_s": window_s,
            "frames": len(fl.frame_t),
            "rss_before_mb": base,
            "peak_mb": peak,
            "cpu_s": cpu,
            "table": table(tracker),
            "accuracy": {"ate_rmse_mm": 1e3 * float(np.sqrt(np.mean(err**2)))},
            "T": res.trajectory.T_world_body,
            "cov": res.trajectory.covariances,
            "loads": {e.load_id: (np.asarray(e.p_world), e.cov_world) for e in res.loads.loads},
        }
    )


def run_child(
    work: Path, minutes: float | None, window_s: float | None, target=None, estimator: str = "smoother"
) -> dict:
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    p = ctx.Process(target=target or _child, args=(work, minutes, window_s, q, estimator))
    p.start()
    out = q.get()
    p.join()
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("capture")
    c.add_argument("log", type=Path)
    c.add_argument("detections", type=Path)
    c.add_argument("work", type=Path)
    s = sub.add_parser("smooth")
    s.add_argument("work", type=Path)
    s.add_argument("--minutes", type=float, nargs="*", default=[])
    s.add_argument("--window-s", type=float, default=None, help="solve in windows of this length")
    s.add_argument("--compare", action="store_true", help="also solve whole and compare")
    s.add_argument("--json", type=Path)
    s.add_argument("--synthetic", action="store_true", help="a synthetic flight (WORK unused)")
    s.add_argument("--estimator", choices=ESTIMATORS, default="smoother", help="the back end measured")
    a = ap.parse_args()
    if a.cmd == "smooth" and a.estimator != "smoother" and (a.window_s is not None or a.compare):
        ap.error("--window-s and --compare apply to the batch smoother only")
    if a.cmd == "capture":
        capture(a.log, a.detections, a.work)
        return 0
    load = os.getloadavg()[0]
    print(f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load {load:.1f}, {os.cpu_count()} cores")
    records = []
    for minutes in a.minutes or [None]:
        target = _synthetic_child if a.synthetic else None
        runs = [run_child(a.work, minutes, a.window_s, target, a.estimator)]
        if a.compare and a.window_s is not None:
            runs.append(run_child(a.work, minutes, None, target))
        for r in runs:
            print(
                f"\n## {r['estimator']}, {r['minutes']} min, window {r['window_s']}: {r['frames']} frames, "
                f"RSS before {r['rss_before_mb']:.0f} MB, peak {r['peak_mb']:.0f} MB, CPU {r['cpu_s']:.1f} s"
            )
            print(r["table"])
            print("accuracy:", json.dumps(r["accuracy"]))
        if len(runs) == 2:
            w, whole = runs
            dp = np.linalg.norm(w["T"][:, :3, 3] - whole["T"][:, :3, 3], axis=1)
            print(
                f"\nwindowed vs whole: position diff max {dp.max() * 1e3:.4f} mm, "
                f"rms {np.sqrt(np.mean(dp**2)) * 1e3:.4f} mm"
            )
            if w["cov"] is not None and whole["cov"] is not None:
                ratio = np.array(
                    [np.trace(a_[3:, 3:]) / np.trace(b_[3:, 3:]) for a_, b_ in zip(w["cov"], whole["cov"])]
                )
                print(
                    f"position covariance trace ratio windowed/whole: min {ratio.min():.4f}, "
                    f"median {np.median(ratio):.4f}, max {ratio.max():.4f}"
                )
            dl = [
                np.linalg.norm(w["loads"][k][0] - whole["loads"][k][0])
                for k in whole["loads"]
                if k in w["loads"]
            ]
            if dl:
                print(f"loads: {len(dl)} common, position diff max {max(dl) * 1e3:.4f} mm")
        records += [{k: v for k, v in r.items() if k not in ("T", "cov", "loads")} for r in runs]
    if len(records) > 1:
        xs = np.array([r["minutes"] for r in records if r["minutes"] and r["window_s"] == a.window_s])
        ys = np.array([r["peak_mb"] for r in records if r["minutes"] and r["window_s"] == a.window_s])
        if len(xs) > 1:
            slope, icpt = np.polyfit(xs, ys, 1)
            print(
                f"\npeak RSS ~ {icpt:.0f} MB + {slope:.1f} MB per flight minute "
                f"-> 30 min: {icpt + 30 * slope:.0f} MB"
            )
    if a.json:
        a.json.write_text(json.dumps(records, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
