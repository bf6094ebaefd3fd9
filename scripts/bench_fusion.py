"""Benchmark of the fusion back end (fusion.estimate) on simulated flights.

Truth and IMU from the simulator (fusion.sim.trajectory / fusion.sim.imu: keyframe survey flight,
200 Hz IMU with Kalibr noise and random-walk biases); floor-camera frames at 30 Hz; raw poses =
truth * Exp(n), n ~ N(0, cov) with a PnP-like covariance (2 mm and 0.05 deg per axis, roll/y and
pitch/x correlated 0.8); blackouts of 0.5, 1, 2 and 5 s with no raw pose; load observations from
the front camera (code centres within 4 m in front of it, 1 / 1 / 2 cm noise).

Prints Markdown tables: accuracy (ATE RMSE vs raw, max error inside each gap length, yaw RMSE,
NEES) for smoother / incremental / EKF, the 5 %-misread-codes test, and batch time and peak
memory (max RSS) for 1, 5, 10, 30 minute flights plus incremental / EKF speed vs real time.

    /work/venv/bin/python scripts/bench_fusion.py [--quick] [--speed-only] [--durations 1 5 10 30]
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import resource
import sys
import time

import gtsam
import numpy as np

from fusion.camera import CameraModel
from fusion.conventions import R_BODY_FRONTCAM
from fusion.estimate import FusionConfig, run_ekf, smooth, smooth_incremental
from fusion.geometry import inv_T, make_T, wrap_angle, yaw_of
from fusion.log.euroc import ImuNoise
from fusion.sim.imu import synthesize_imu
from fusion.sim.trajectory import random_aisle_survey
from fusion.types import LoadObservation, Trajectory

T_BODY_FRONTCAM = make_T(R_BODY_FRONTCAM, [0.1, 0.0, 0.05])
# the back ends take the front camera's model (its mount matters); intrinsics are not used
FRONT_CAMERA = CameraModel(640, 480, 400.0, 400.0, 320.0, 240.0, T_body_cam=T_BODY_FRONTCAM)
GAP_LENGTHS_S = (0.5, 1.0, 2.0, 5.0)
SIGMA_POS_M = 0.002
SIGMA_ROT_RAD = math.radians(0.05)


def pnp_like_cov() -> np.ndarray:
    cov = np.diag([SIGMA_ROT_RAD**2] * 3 + [SIGMA_POS_M**2] * 3)
    c = 0.8 * SIGMA_ROT_RAD * SIGMA_POS_M
    cov[0, 4] = cov[4, 0] = -c
    cov[1, 3] = cov[3, 1] = c
    return cov


def make_flight(
    duration_s: float, seed: int, with_gaps: bool = True, with_loads: bool = True, raw_scale: float = 1.0
):
    """Simulated flight: dict with frame_t, imu, raw, load_obs, T_true, gap_of_frame, loads.
    `raw_scale` multiplies the raw-pose noise (sigmas) of pnp_like_cov()."""
    rng = np.random.default_rng(seed)
    # random survey waypoints in a 20 m x 10 m aisle area, 1-2.5 m high
    traj = random_aisle_survey(duration_s, rng)
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(), rng)
    frame_t = np.round(np.arange(0.0, duration_s, 1 / 30.0) * 1e9).astype(np.int64)
    st = traj.state(frame_t * 1e-9)
    T_true = st.T_world_body
    gap_of_frame = np.zeros(len(frame_t))  # gap length (s) the frame lies in, 0 = none
    if with_gaps:
        t = 5.0
        while t + 6.0 < duration_s:
            for g in GAP_LENGTHS_S:
                if t + g + 2.0 >= duration_s:
                    break
                inside = (frame_t * 1e-9 >= t) & (frame_t * 1e-9 < t + g)
                gap_of_frame[inside] = g
                t += g + 4.0
    keep = gap_of_frame == 0
    cov = pnp_like_cov() * raw_scale**2
    Lc = np.linalg.cholesky(cov)
    xi = rng.standard_normal((keep.sum(), 6)) @ Lc.T
    raw_T = np.array([T @ gtsam.Pose3.Expmap(x).matrix() for T, x in zip(T_true[keep], xi)])
    raw = Trajectory("pnp", frame_t[keep], raw_T, np.repeat(cov[None], keep.sum(), 0))
    loads, obs = {}, []
    if with_loads:
        for j in range(int(duration_s // 20) + 3):
            loads[f"L{j:03d}"] = np.array([rng.uniform(-11, 11), rng.uniform(-6, 6), rng.uniform(0.5, 2.5)])
        ids = list(loads)
        P = np.array([loads[i] for i in ids])
        cov_cam = np.diag([0.01, 0.01, 0.02]) ** 2
        for k in range(0, len(frame_t), 3):
            T_cw = inv_T(T_true[k] @ T_BODY_FRONTCAM)
            pc = P @ T_cw[:3, :3].T + T_cw[:3, 3]
            vis = (
                (pc[:, 2] > 0.5)
                & (np.linalg.norm(pc, axis=1) < 4.0)
                & (np.abs(pc[:, 0]) < pc[:, 2])
                & (np.abs(pc[:, 1]) < pc[:, 2])
            )
            for j in np.flatnonzero(vis):
                z = pc[j] + rng.standard_normal(3) * np.sqrt(np.diag(cov_cam))
                obs.append(LoadObservation(int(frame_t[k]), ids[j], np.zeros(3), None, z, cov_cam))
    return dict(
        frame_t=frame_t, imu=imu, raw=raw, load_obs=obs, T_true=T_true, gap_of_frame=gap_of_frame, loads=loads
    )


def misread(raw: Trajectory, frac: float, seed: int) -> Trajectory:
    """Replace `frac` of the raw poses by the pose at a wrong floor code (1-3 m off in x/y)."""
    rng = np.random.default_rng(seed)
    T = raw.T_world_body.copy()
    bad = rng.choice(len(T), size=int(round(frac * len(T))), replace=False)
    T[bad, :2, 3] += rng.uniform(1.0, 3.0, (len(bad), 2)) * rng.choice([-1, 1], (len(bad), 2))
    return Trajectory(raw.name, raw.timestamps_ns, T, raw.covariances)


def metrics(res_traj: Trajectory, fl: dict) -> dict:
    idx = np.searchsorted(fl["frame_t"], res_traj.timestamps_ns)
    T_true = fl["T_true"][idx]
    gaps = fl["gap_of_frame"][idx]
    err = np.linalg.norm(res_traj.positions_xyz - T_true[:, :3, 3], axis=1)
    yaw = wrap_angle(res_traj.yaw_rad - yaw_of(T_true[:, :3, :3]))
    out = {
        "ate_cm": 100 * math.sqrt(np.mean(err**2)),
        "ate_seen_cm": 100 * math.sqrt(np.mean(err[gaps == 0] ** 2)),
        "yaw_deg": math.degrees(math.sqrt(np.mean(yaw**2))),
    }
    for g in GAP_LENGTHS_S:
        m = gaps == g
        out[f"gap{g}"] = 100 * err[m].max() if m.any() else float("nan")
    if res_traj.covariances is not None:
        # the estimator's own prediction of its ATE: sqrt(mean trace(position covariance))
        out["ate_pred_cm"] = 100 * math.sqrt(
            np.mean(np.trace(res_traj.covariances[:, 3:, 3:], axis1=1, axis2=2))
        )
        ne = []
        for Te, Tt, P in zip(res_traj.T_world_body, T_true, res_traj.covariances):
            x = gtsam.Pose3.Logmap(gtsam.Pose3(Te).between(gtsam.Pose3(Tt)))
            ne.append(x @ np.linalg.solve(P, x))
        out["nees"] = float(np.mean(ne))
    return out


def load_rmse_cm(res, fl) -> float:
    d = [np.linalg.norm(l.p_world - fl["loads"][l.load_id]) for l in res.loads.loads]
    return 100 * math.sqrt(np.mean(np.square(d))) if d else float("nan")


def accuracy_table(duration_s: float, seed: int, raw_scale: float = 1.0) -> None:
    fl = make_flight(duration_s, seed, raw_scale=raw_scale)
    args = (fl["frame_t"], fl["imu"], fl["raw"], fl["load_obs"])
    raw_m = metrics(fl["raw"], fl)
    rows = [("raw (PnP-like)", raw_m, float("nan"), float("nan"))]
    solvers = (
        ("smoother", smooth, None),
        ("incremental (lag 0.5 s)", smooth_incremental, None),
        ("incremental (iSAM2, no lag)", smooth_incremental, FusionConfig(incremental_lag_s=None)),
        ("ekf", run_ekf, None),
    )
    for name, fn, cfg in solvers:
        t0 = time.perf_counter()
        res = fn(*args, front_camera=FRONT_CAMERA, config=cfg)
        rows.append((name, metrics(res.trajectory, fl), load_rmse_cm(res, fl), time.perf_counter() - t0))
    print(
        f"\n### Accuracy, {duration_s:.0f} s flight, seed {seed}, raw noise x{raw_scale:g} "
        f"({SIGMA_POS_M * raw_scale * 1000:g} mm, {math.degrees(SIGMA_ROT_RAD) * raw_scale:g} deg "
        f"per axis; {len(fl['raw'])} raw poses of {len(fl['frame_t'])} frames, "
        f"{len(fl['load_obs'])} load observations)\n"
    )
    gh = " | ".join(f"max err in {g:g} s gap (cm)" for g in GAP_LENGTHS_S)
    print(
        f"| estimator | ATE RMSE all (cm) | / raw | ATE predicted by its covariance (cm) | "
        f"ATE RMSE seen (cm) | / raw | {gh} | yaw RMSE (deg) | NEES (6-dof) | load RMSE (cm) | "
        "time (s) |"
    )
    print("|---" * (11 + len(GAP_LENGTHS_S)) + "|")
    for name, m, lr, tm in rows:
        gaps = " | ".join(f"{m[f'gap{g}']:.2f}" for g in GAP_LENGTHS_S)
        print(
            f"| {name} | {m['ate_cm']:.3f} | {m['ate_cm'] / raw_m['ate_cm']:.2f} | "
            f"{m.get('ate_pred_cm', float('nan')):.3f} | {m['ate_seen_cm']:.3f} | "
            f"{m['ate_seen_cm'] / raw_m['ate_cm']:.2f} | {gaps} | "
            f"{m['yaw_deg']:.4f} | {m.get('nees', float('nan')):.2f} | {lr:.2f} | {tm:.2f} |"
        )


def outlier_table(duration_s: float, seed: int) -> None:
    fl = make_flight(duration_s, seed, with_loads=False)
    bad = misread(fl["raw"], 0.05, seed + 100)
    print(f"\n### 5 % misread floor codes (1-3 m off), {duration_s:.0f} s flight\n")
    print("| estimator | kernel | ATE clean (cm) | ATE 5 % misread (cm) | growth | rejected / misread |")
    print("|---|---|---|---|---|---|")
    n_bad = int(round(0.05 * len(fl["raw"])))
    for name, fn in (("smoother", smooth), ("ekf", run_ekf)):
        for kernel in ("huber", "cauchy"):
            cfg = FusionConfig(robust_kernel=kernel)
            a = fn(fl["frame_t"], fl["imu"], fl["raw"], [], front_camera=FRONT_CAMERA, config=cfg)
            b = fn(fl["frame_t"], fl["imu"], bad, [], front_camera=FRONT_CAMERA, config=cfg)
            ea, eb = metrics(a.trajectory, fl)["ate_cm"], metrics(b.trajectory, fl)["ate_cm"]
            print(
                f"| {name} | {kernel} | {ea:.3f} | {eb:.3f} | {100 * (eb / ea - 1):+.1f} % | "
                f"{b.stats['rejected_pose_factors']} / {n_bad} |"
            )


def max_rss_mb() -> float:
    """Peak resident memory of this process (MB): VmHWM, which starts afresh at exec (ru_maxrss
    would carry the parent's peak over into a subprocess), else ru_maxrss."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def speed_one(d_min: float) -> dict:
    """Time and memory of one flight length (run in a fresh process so max RSS is its own)."""
    fl = make_flight(60.0 * d_min, seed=int(d_min))
    args = (fl["frame_t"], fl["imu"], fl["raw"], fl["load_obs"])
    rss0 = max_rss_mb()
    c0, t0 = time.process_time(), time.perf_counter()
    res = smooth(*args, front_camera=FRONT_CAMERA)
    out = dict(
        frames=len(fl["frame_t"]),
        loads=len(res.loads.loads),
        batch_s=time.perf_counter() - t0,
        batch_cpu_s=time.process_time() - c0,
        rss_before_mb=rss0,
        rss_mb=max_rss_mb(),
    )
    out.update(
        {
            k: v
            for k, v in res.stats.items()
            if k.startswith("time_") or k in ("iterations", "covariance_method")
        }
    )
    del res
    if d_min <= 10:
        out["inc_rt"] = smooth_incremental(*args, front_camera=FRONT_CAMERA).stats["realtime_factor"]
        out["ekf_rt"] = run_ekf(*args, front_camera=FRONT_CAMERA).stats["realtime_factor"]
    return out


def speed_table(durations_min) -> None:
    import json
    import subprocess

    print("\n### Speed and memory (30 Hz frames, 200 Hz IMU, gaps, loads; one process per row)\n")
    print(
        "| flight (min) | frames | loads | batch total (s) | batch CPU (s) | build / LM / covariances (s) | "
        "LM iters | max RSS before / after batch (MB) | incremental (lag 0.5 s) x real time | "
        "EKF x real time |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for d in durations_min:
        code = (
            "import json, sys; sys.path.insert(0, 'scripts'); import bench_fusion as b; "
            f"print(json.dumps(b.speed_one({d!r})))"
        )
        r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        if r.returncode != 0:
            print(f"| {d:g} | failed: {r.stderr.strip().splitlines()[-1]} |")
            continue
        s = json.loads(r.stdout.strip().splitlines()[-1])
        print(
            f"| {d:g} | {s['frames']} | {s['loads']} | {s['batch_s']:.2f} | {s['batch_cpu_s']:.2f} | "
            f"{s['time_build_s']:.2f} / {s['time_optimize_s']:.2f} / {s['time_covariance_s']:.2f} | "
            f"{s['iterations']} | {s['rss_before_mb']:.0f} / {s['rss_mb']:.0f} | "
            f"{s.get('inc_rt', float('nan')):.1f} | {s.get('ekf_rt', float('nan')):.1f} |",
            flush=True,
        )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short flights only")
    ap.add_argument(
        "--durations",
        type=float,
        nargs="*",
        default=None,
        help="speed-table flight lengths in minutes (default 1 5 10 30)",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--speed-only", action="store_true", help="only the speed / memory table")
    a = ap.parse_args(argv)
    print(
        f"# bench_fusion  {datetime.datetime.now().isoformat(timespec='seconds')}  "
        f"(load average at start {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores)"
    )
    acc_s = 60.0 if a.quick else 180.0
    if not a.speed_only:
        accuracy_table(acc_s, a.seed)
        accuracy_table(acc_s, a.seed, raw_scale=2.5)
        outlier_table(60.0 if a.quick else 120.0, a.seed + 1)
    speed_table(a.durations if a.durations is not None else ([1] if a.quick else [1, 5, 10, 30]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
