"""Rolling-shutter benchmark (issue 10, item 1): PnP and fused errors, NEES, readout recovery.

Flights: the default warehouse's floor grid (fusion.sim.scenarios, floor camera cam0 only, 640x480,
f = 550 px, 30 fps), a 20 s zig-zag along aisle 1 at 1.2-1.7 m height with yaw swings, flown with
a PEAK speed of 1 and 2 m/s (smootherstep segments: mean speed = peak / 2.1875), exposure 2 ms
(motion blur <= 2 px, so that decoding is not what is measured), no blackouts.  Each flight is
rendered with a global shutter and with a rolling-shutter readout of 10, 20 and 30 ms (stamp at
the first row, one true pose per row: fusion.sim.render.rolling_shutter_poses); same seed, so
the global-shutter run is the same flight.

Per flight (fusion.pipeline.run, incremental smoother off): PnP position error (mean, median,
p95, over the frames with a pose), smoother ATE RMSE, 6-dof pose NEES of PnP and smoother (mean
and median over frames; ideal 6), the uncorrected PnP error (raw corners: what happens without
the model), and the readout estimated by `fusion.qr.rolling_shutter.calibrate_readout` from a
camera model that says 0 (with its sigma).

Targets: PnP and fused errors within 1.2x the global-shutter run's; NEES within [0.5, 2] x 6
(judged against the global-shutter run's own NEES too); readout within 5 %.  Also reported: the
floor camera's estimated camera-IMU time offset (true 0), which must not be significant
(fusion.estimate.timeoffset applies it only beyond 3 sigma).

    PYTHONPATH=$PWD python3 scripts/bench_rolling_shutter.py [--dir /tmp/rs_bench] [--duration 20]
        [--speeds 1 2] [--readouts-ms 0 10 20 30] [--workers 2] [--seed 0]
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from fusion.geometry import R_from_quat_wxyz, interpolate_poses
from fusion.log import read_flight
from fusion.pipeline import RunConfig, run
from fusion.qr.detect import read_cache
from fusion.qr.pnp import pnp_trajectory
from fusion.qr.rolling_shutter import calibrate_readout
from fusion.sim.scenarios import build_scenario
from fusion.sim.simulate import simulate
from fusion.sim.trajectory import KeyframeTrajectory, survey_keyframes

PEAK_OVER_MEAN = 2.1875  # smootherstep: peak speed / mean speed of a segment
EXPOSURE_S = 0.002
YAW_RATE_RAD_S = 0.8
ERROR_RATIO_TARGET = 1.2
NEES_BAND = (0.5, 2.0)
READOUT_TOLERANCE = 0.05
WAYPOINTS = [  # (x, y, z, yaw[, hover_s]) along aisle 1, out and back, repeated
    (0.5, 1.5, 1.4, 0.0, 0.5),
    (2.5, 1.8, 1.6, 0.5),
    (4.5, 1.2, 1.3, -0.3),
    (6.5, 1.7, 1.7, 0.4),
    (8.5, 1.3, 1.2, -0.2),
    (9.5, 1.5, 1.4, math.pi / 2),
    (7.5, 1.8, 1.5, math.pi),
    (5.5, 1.2, 1.3, math.pi - 0.5),
    (3.5, 1.7, 1.6, math.pi + 0.4),
    (1.5, 1.3, 1.3, math.pi),
    (0.5, 1.5, 1.4, math.pi / 2),
]


def bench_scenario(peak_speed_m_s: float, duration_s: float):
    """The benchmark flight at `peak_speed_m_s`: floor camera only, short exposure, no blackouts."""
    sc = build_scenario("default")
    sc.cameras = {"cam0": sc.cameras["cam0"]}
    wps = list(WAYPOINTS)
    while True:
        kf = survey_keyframes(wps, speed_m_s=peak_speed_m_s / PEAK_OVER_MEAN, yaw_rate_rad_s=YAW_RATE_RAD_S)
        if kf[-1].t_s >= duration_s:
            break
        wps += WAYPOINTS[1:]
    sc.trajectory = KeyframeTrajectory(kf)
    sc.duration_s = duration_s
    sc.blackouts = []
    sc.exposure_s = EXPOSURE_S
    sc.name = f"rs_bench_{peak_speed_m_s:g}mps"
    return sc


def position_errors_cm(log, traj) -> np.ndarray:
    gt = log.groundtruth
    T = np.tile(np.eye(4), (len(gt.timestamps_ns), 1, 1))
    T[:, :3, :3] = R_from_quat_wxyz(gt.q_world_body_wxyz)
    T[:, :3, 3] = gt.p_world
    # (a time offset applied by the pipeline can move the last pose past the ground truth's end)
    t = traj.timestamps_ns * 1e-9
    inside = (t >= gt.timestamps_ns[0] * 1e-9) & (t <= gt.timestamps_ns[-1] * 1e-9)
    Tq = interpolate_poses(gt.timestamps_ns * 1e-9, T, t[inside])
    return 100.0 * np.linalg.norm(traj.T_world_body[inside, :3, 3] - Tq[:, :3, 3], axis=1)


def one_flight(root: Path, speed: float, readout_ms: float, args) -> dict:
    log_dir = root / f"v{speed:g}_ro{readout_ms:g}" / "log"
    out_dir = log_dir.parent / "out"
    if not (log_dir / "manifest.json").exists():
        simulate(
            log_dir,
            bench_scenario(speed, args.duration),
            duration_s=args.duration,
            seed=args.seed,
            overwrite=True,
            progress=False,
            workers=args.workers,
            readout_s=readout_ms * 1e-3,
        )
    res = run(
        log_dir, out_dir, RunConfig(workers=args.workers, progress=False, force=True, incremental=False)
    )
    m = res.metrics["trajectories"]
    row: dict = {"speed_m_s": speed, "readout_ms": readout_ms}
    log = read_flight(log_dir)
    pnp_err = position_errors_cm(log, res.trajectories["pnp"])
    row["pnp_n"] = len(pnp_err)
    row["pnp_mean_cm"] = float(pnp_err.mean())
    row["pnp_median_cm"] = float(np.median(pnp_err))
    row["pnp_p95_cm"] = float(np.percentile(pnp_err, 95))
    row["smoother_ate_cm"] = 100.0 * m["smoother"]["ate_rmse_m"] if "smoother" in m else math.nan
    for est in ("pnp", "smoother"):
        nees = (m.get(est) or {}).get("nees_pose_6dof") or {}
        row[f"{est}_nees_mean"] = nees.get("nees_mean", math.nan)
        row[f"{est}_nees_median"] = nees.get("nees_median", math.nan)
    # the floor camera's camera-IMU time offset (true 0 here): estimate, sigma, applied
    floor_offset = (res.metrics.get("time_offsets") or {}).get("cam0") or {}
    for key in ("offset_ms", "sigma_ms", "applied_ms"):
        row[f"time_offset_{key}"] = floor_offset.get(key, math.nan)
    det = read_cache(out_dir / "detections.csv")
    if readout_ms > 0:
        cam = log.floor.camera
        raw = pnp_trajectory(det.by_frame("cam0"), cam, log.world)[0]
        row["pnp_uncorrected_mean_cm"] = float(position_errors_cm(log, raw).mean())
        calib = calibrate_readout(det, replace(cam, line_delay_s=0.0), log.world, log.imu)
        row["readout_est_ms"] = 1e3 * calib.readout_s
        row["readout_sigma_ms"] = 1e3 * calib.sigma_s
        row["readout_err_pct"] = 100.0 * (calib.readout_s - readout_ms * 1e-3) / (readout_ms * 1e-3)
    return row


def markdown(rows: list[dict]) -> str:
    gs = {r["speed_m_s"]: r for r in rows if r["readout_ms"] == 0}
    lines = [
        "| peak m/s | readout ms | PnP mean / med / p95 cm | ratio to GS (mean) | uncorrected PnP mean cm "
        "| smoother ATE cm | ratio to GS | NEES PnP mean / med | NEES smoother mean / med "
        "| readout est. ms (err %) | time offset ms (applied) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        g = gs.get(r["speed_m_s"])
        ratio = r["pnp_mean_cm"] / g["pnp_mean_cm"] if g else math.nan
        fratio = r["smoother_ate_cm"] / g["smoother_ate_cm"] if g else math.nan
        ro = (
            f"{r['readout_est_ms']:.2f} +- {r['readout_sigma_ms']:.2f} ({r['readout_err_pct']:+.1f} %)"
            if "readout_est_ms" in r
            else "-"
        )
        unc = f"{r['pnp_uncorrected_mean_cm']:.2f}" if "pnp_uncorrected_mean_cm" in r else "-"
        lines.append(
            f"| {r['speed_m_s']:g} | {r['readout_ms']:g} | "
            f"{r['pnp_mean_cm']:.3f} / {r['pnp_median_cm']:.3f} / "
            f"{r['pnp_p95_cm']:.3f} | {ratio:.2f} | {unc} | {r['smoother_ate_cm']:.3f} | {fratio:.2f} | "
            f"{r['pnp_nees_mean']:.1f} / {r['pnp_nees_median']:.1f} | "
            f"{r['smoother_nees_mean']:.1f} / {r['smoother_nees_median']:.1f} | {ro} | "
            f"{r.get('time_offset_offset_ms', math.nan):+.2f} +- "
            f"{r.get('time_offset_sigma_ms') or math.nan:.2f} "
            f"({r.get('time_offset_applied_ms', math.nan):+.2f}) |"
        )
    return "\n".join(lines)


def verdicts(rows: list[dict]) -> list[str]:
    gs = {r["speed_m_s"]: r for r in rows if r["readout_ms"] == 0}
    out = []
    rs = [r for r in rows if r["readout_ms"] > 0 and r["speed_m_s"] in gs]
    if not rs:
        return out
    pnp_ratio = max(r["pnp_mean_cm"] / gs[r["speed_m_s"]]["pnp_mean_cm"] for r in rs)
    fused_ratio = max(r["smoother_ate_cm"] / gs[r["speed_m_s"]]["smoother_ate_cm"] for r in rs)
    ro = max(abs(r["readout_err_pct"]) for r in rs)
    lo, hi = NEES_BAND[0] * 6, NEES_BAND[1] * 6
    nees = [r[f"{e}_nees_mean"] for r in rs for e in ("pnp", "smoother")]
    out.append(
        f"PnP error within {ERROR_RATIO_TARGET}x GS: worst ratio {pnp_ratio:.2f} -> "
        f"{'met' if pnp_ratio <= ERROR_RATIO_TARGET else 'missed'}"
    )
    out.append(
        f"fused error within {ERROR_RATIO_TARGET}x GS: worst ratio {fused_ratio:.2f} -> "
        f"{'met' if fused_ratio <= ERROR_RATIO_TARGET else 'missed'}"
    )
    out.append(
        f"NEES (mean) within [{lo:g}, {hi:g}]: range {min(nees):.1f}-{max(nees):.1f} -> "
        f"{'met' if lo <= min(nees) and max(nees) <= hi else 'missed'}"
    )
    out.append(
        f"readout within {100 * READOUT_TOLERANCE:g} %: worst {ro:.1f} % -> "
        f"{'met' if ro <= 100 * READOUT_TOLERANCE else 'missed'}"
    )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dir", type=Path, default=Path("/tmp/rs_bench"))
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--speeds", type=float, nargs="+", default=[1.0, 2.0])
    ap.add_argument("--readouts-ms", type=float, nargs="+", default=[0.0, 10.0, 20.0, 30.0])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    rows = []
    for speed in args.speeds:
        for ro in args.readouts_ms:
            rows.append(one_flight(args.dir, speed, ro, args))
            print(json.dumps(rows[-1]), flush=True)
    print(f"\n{datetime.date.today()}, {args.duration:g} s flights, seed {args.seed}\n")
    print(markdown(rows))
    print()
    for v in verdicts(rows):
        print("- " + v)
    (args.dir / "results.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
