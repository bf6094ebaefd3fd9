"""Benchmark of the as-built floor codes (issue #12, item 1; fusion/estimate/asbuilt.py).

Synthetic flights (no rendering): truth and IMU from the simulator (random aisle survey, 200 Hz
IMU), floor codes on a 1 m grid over the 22 m x 12 m area, each stuck down off its nominal pose
by N(0, 2 cm) per axis and N(0, 1 deg) in yaw (fusion.sim.placement); every frame sees the codes
under the floor camera with single-code-PnP-like noise (3 mm, 0.1 deg per axis; roll/y and
pitch/x correlated 0.8), and its raw PnP pose is what the nominal grid gives (the codes' mean).

Runs per seed: raw PnP; the smoother on a perfectly laid floor with today's model (placement
sigma 0); on the misplaced floor with today's model; on the misplaced floor as built (sigma =
2 cm / 1 deg, what world.yaml would say); on the perfect floor as built (default 1 cm / 1 deg:
what gets flagged).  Then the batch smoother's time on a long flight with and without the
as-built codes.

    PYTHONPATH=$PWD python3 scripts/bench_asbuilt.py [--seeds 0 1 2] [--duration 120] [--speed-minutes 3]
"""

from __future__ import annotations

import argparse
import datetime
import math
import time

import numpy as np

from fusion.conventions import floor_payload
from fusion.estimate import FusionConfig, smooth
from fusion.estimate.asbuilt import Placement, gauge_transform, groundtruth_errors
from fusion.log.euroc import ImuNoise
from fusion.sim.imu import synthesize_imu
from fusion.sim.placement import placement_offsets, synthetic_sightings, true_code_poses
from fusion.sim.trajectory import random_aisle_survey
from fusion.types import Trajectory

SIGMA_POS_M = 0.003
SIGMA_ROT_RAD = math.radians(0.1)
ERROR_M = 0.02
ERROR_RAD = math.radians(1.0)
MIN_OBS = 20


def sighting_cov() -> np.ndarray:
    cov = np.diag([SIGMA_ROT_RAD**2] * 3 + [SIGMA_POS_M**2] * 3)
    c = 0.8 * SIGMA_ROT_RAD * SIGMA_POS_M
    cov[0, 4] = cov[4, 0] = -c
    cov[1, 3] = cov[3, 1] = c
    return cov


def grid():
    xs, ys = np.meshgrid(np.arange(-11, 12), np.arange(-6, 7))
    xy = np.c_[xs.ravel(), ys.ravel()].astype(float)
    return xy, [floor_payload(x, y) for x, y in xy]


def flight(duration_s: float, seed: int, error_m: float, error_rad: float, placement: Placement):
    rng = np.random.default_rng(seed)
    traj = random_aisle_survey(duration_s, rng)
    imu, _, _ = synthesize_imu(traj, 200.0, ImuNoise(), rng)
    frame_t = np.round(np.arange(0.0, duration_s, 1 / 30.0) * 1e9).astype(np.int64)
    T_true = traj.state(frame_t * 1e-9).T_world_body
    xy, ids = grid()
    offsets = placement_offsets(len(xy), error_m, error_rad, seed)
    T_codes = true_code_poses(xy, offsets)
    ab, fk, fT, fcov = synthetic_sightings(
        frame_t, T_true, ids, xy, T_codes, sighting_cov(), placement, np.random.default_rng([seed, 9])
    )
    raw = Trajectory("pnp", frame_t[fk], fT, fcov)
    truth = {cid: np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])]) for cid, T in zip(ids, T_codes)}
    return dict(frame_t=frame_t, imu=imu, raw=raw, T_true=T_true, as_built=ab, truth=truth)


def ate_cm(traj: Trajectory, fl, frames=None, T_gauge=None) -> float:
    idx = np.searchsorted(fl["frame_t"], traj.timestamps_ns)
    p = traj.positions_xyz
    if T_gauge is not None:
        p = p @ T_gauge[:3, :3].T + T_gauge[:3, 3]
    if frames is not None:
        keep = np.isin(traj.timestamps_ns, frames)
        idx = idx[keep]
        p = p[keep]
    err = np.linalg.norm(p - fl["T_true"][idx, :3, 3], axis=1)
    return 100 * math.sqrt(np.mean(err**2))


def run_smoother(fl, as_built: bool):
    t0 = time.perf_counter()
    res = smooth(
        fl["frame_t"],
        fl["imu"],
        fl["raw"],
        [],
        config=FusionConfig(),
        as_built=fl["as_built"] if as_built else None,
    )
    return res, time.perf_counter() - t0


def accuracy(seeds, duration_s: float) -> None:
    print(
        f"## Accuracy ({duration_s:.0f} s flights; ATE like-for-like = on the frames with a raw PnP pose)\n"
    )
    print(
        "| seed | raw PnP, misplaced | smoother perfect floor (today) | smoother misplaced (today) | "
        "smoother misplaced, as built | gauge removed | ratio (gauge removed) | "
        f"codes ≥{MIN_OBS} frames | offset err RMS | "
        "gauge removed | true offset RMS | flagged misplaced | flagged, perfect floor |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for seed in seeds:
        fl_perfect = flight(duration_s, seed, 0.0, 0.0, Placement(0.0, 0.0))
        fl_bad = flight(duration_s, seed, ERROR_M, ERROR_RAD, Placement(ERROR_M, ERROR_RAD))
        fl_perfect_ab = flight(duration_s, seed, 0.0, 0.0, Placement())
        frames = fl_bad["raw"].timestamps_ns
        raw = ate_cm(fl_bad["raw"], fl_bad)
        perfect, _ = run_smoother(fl_perfect, False)
        today, _ = run_smoother(fl_bad, False)
        ab, _ = run_smoother(fl_bad, True)
        ab_perfect, _ = run_smoother(fl_perfect_ab, True)
        e = groundtruth_errors(ab.floor_codes, fl_bad["truth"], MIN_OBS)
        a_perf = ate_cm(perfect.trajectory, fl_perfect, frames)
        a_ab = ate_cm(ab.trajectory, fl_bad, frames)
        a_today = ate_cm(today.trajectory, fl_bad, frames)
        T_gauge = gauge_transform(ab.floor_codes, fl_bad["truth"])
        a_g = ate_cm(ab.trajectory, fl_bad, frames, T_gauge)
        print(
            f"| {seed} | {raw:.3f} cm | {a_perf:.3f} cm | {a_today:.3f} cm | "
            f"{a_ab:.3f} cm | {a_g:.3f} cm | {a_g / a_perf:.2f} | {e['n_codes']} | "
            f"{100 * e['offset_error_rms_m']:.3f} cm | "
            f"{100 * e['offset_error_rms_gauge_removed_m']:.3f} cm | "
            f"{100 * e['true_offset_rms_m']:.2f} cm | "
            f"{len(ab.floor_codes.misplaced)} | {len(ab_perfect.floor_codes.misplaced)} |"
        )


def speed(minutes: float, seed: int = 0) -> None:
    print(f"\n## Batch smoother time, {minutes:g}-minute flight\n")
    print("| floor | model | total | build / LM / covariances | iterations | covariances | ratio |")
    print("|---|---|---|---|---|---|---|")
    for floor, err_m, err_rad in (("perfect", 0.0, 0.0), ("misplaced 2 cm / 1°", ERROR_M, ERROR_RAD)):
        fl = flight(60 * minutes, seed, err_m, err_rad, Placement())
        r0, t0 = run_smoother(fl, False)
        r1, t1 = run_smoother(fl, True)
        for name, r, t in (("nominal codes (today)", r0, t0), ("as-built codes", r1, t1)):
            s = r.stats
            print(
                f"| {floor} | {name} | {t:.2f} s | {s['time_build_s']:.2f} / {s['time_optimize_s']:.2f} / "
                f"{s['time_covariance_s']:.2f} s | {s['iterations']} | {s['covariance_method']} | "
                f"{t / t0:.2f} |"
            )
    print(f"\n{len(fl['frame_t'])} frames, {len(fl['as_built'].sightings)} sightings")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--speed-minutes", type=float, nargs="*", default=[3.0])
    ap.add_argument("--speed-only", action="store_true")
    args = ap.parse_args(argv)
    print(f"# bench_asbuilt {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC\n")
    if not args.speed_only:
        accuracy(args.seeds, args.duration)
    for m in args.speed_minutes:
        speed(m)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
