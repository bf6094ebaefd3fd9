"""Where the rolling-shutter correction's remaining error comes from (issue 10.1): PnP (and,
with --pipeline, smoother) errors of a bench flight with parts of the readout motion replaced
by the truth.

Runs on a directory written by scripts/bench_rolling_shutter.py (its logs and detections
caches): the global-shutter flight `v{speed}_ro0` and the rolling-shutter flight
`v{speed}_ro{readout}` of the same seed.  Each variant patches fusion.qr.rolling_shutter for one
run and restores it:

    est         the code as it is
    rot         the body's rotation from the stamp to each row's time: the truth
    pos         the body's displacement from the stamp to each row's time: the truth
    all         both (the exact per-row pose relative to the estimated stamp pose)
    vel         the velocity at the stamp: the truth (rotation, IMU displacement as estimated)
    rotnoiseS   rotation: the truth times a random walk of S x the gyro's noise density (what
                the gyro's white noise alone does to the correction; S = 1 if not given)
    accelbias   the accelerometer's true bias taken off before the velocity fit
    truetrack   the same with the true attitude for the IMU's world acceleration

Prints per variant the PnP mean position error (cm), its ratio to the global-shutter flight's
PnP, and the final motion's mean velocity error (mm/s); --pipeline runs fusion.pipeline.run
instead (PnP and smoother ATE, NEES) into `out_diag_{variant}` next to the flight's `out`;
--calibrate the readout estimate (`calibrate_readout` from a camera model that says 0).

    PYTHONPATH=$PWD python3 scripts/diagnose_rolling_shutter.py --dir D [--speed 2] [--readout-ms 30]
        [--pipeline | --calibrate] VARIANT...
"""

from __future__ import annotations

import argparse
import shutil
import sys
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_rolling_shutter import bench_scenario, position_errors_cm  # noqa: E402

from fusion.geometry import so3_exp_stack  # noqa: E402
from fusion.log import read_flight  # noqa: E402
from fusion.pipeline import RunConfig, run  # noqa: E402
from fusion.qr import rolling_shutter as rs  # noqa: E402
from fusion.qr.detect import read_cache  # noqa: E402
from fusion.qr.pnp import pnp_trajectory  # noqa: E402
from fusion.types import Trajectory  # noqa: E402

RANDOM_WALK_STEP_S = 0.005  # the simulated gyro noise's grid (the bench IMU's 200 Hz)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dir", type=Path, required=True)
    ap.add_argument("--speed", type=float, default=2.0)
    ap.add_argument("--readout-ms", type=float, default=30.0)
    ap.add_argument("--pipeline", action="store_true")
    ap.add_argument(
        "--calibrate",
        action="store_true",
        help="the readout estimate (calibrate_readout, as the bench) instead",
    )
    ap.add_argument("variants", nargs="+")
    args = ap.parse_args()
    flight = args.dir / f"v{args.speed:g}_ro{args.readout_ms:g}"
    log = read_flight(flight / "log")
    cam = log.floor.camera
    gt = log.groundtruth
    t_gt = gt.timestamps_ns * 1e-9
    sc = bench_scenario(args.speed, float(t_gt[-1]) + 0.005)

    def truth(t) -> np.ndarray:
        return sc.trajectory.state(np.atleast_1d(np.asarray(t, float))).T_world_body

    def true_accel_bias(ts_ns: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(ts_ns * 1e-9, t_gt, gt.bias_accel[:, i]) for i in range(3)])

    gs_dir = args.dir / f"v{args.speed:g}_ro0"
    gs_log = read_flight(gs_dir / "log")
    gs_det = read_cache(gs_dir / "out" / "detections.csv")
    gs_traj = pnp_trajectory(gs_det.by_frame("cam0"), gs_log.floor.camera, gs_log.world)[0]
    gs_pnp = float(position_errors_cm(gs_log, gs_traj).mean())
    print(f"global shutter PnP mean {gs_pnp:.4f} cm", flush=True)

    orig_poses, orig_motion, orig_track = rs._body_poses_at, rs.frame_motion, rs._ImuTrack.__init__
    v_errors: list[np.ndarray] = []
    density = log.imu.noise.gyroscope_noise_density

    def body_poses(variant: str) -> Callable:
        def patched(motion, k, dt):
            est = orig_poses(motion, k, dt)
            t0 = motion.timestamps_ns[k] * 1e-9
            Ts, Tr = truth(t0), truth(t0 + dt)
            R_rel = np.einsum("nji,njk->nik", Ts[:, :3, :3], Tr[:, :3, :3])
            R_stamp, p_stamp = motion.T_world_body[k][:, :3, :3], motion.T_world_body[k][:, :3, 3]
            out = est.copy()
            if variant in ("rot", "all"):
                out[:, :3, :3] = R_stamp @ R_rel
            if variant in ("pos", "all"):
                out[:, :3, 3] = p_stamp + Tr[:, :3, 3] - Ts[:, :3, 3]
            if variant.startswith("rotnoise"):
                scale = float(variant[len("rotnoise") :] or 1.0)
                grid = np.arange(0.0, cam.readout_s + 2.0 * RANDOM_WALK_STEP_S, RANDOM_WALK_STEP_S)
                walk = np.zeros((len(dt), 3))
                for kk in np.unique(k):  # one random walk per frame, the same in every pass
                    rng = np.random.default_rng([7, int(kk)])
                    steps = rng.normal(0.0, scale * density * np.sqrt(RANDOM_WALK_STEP_S), (len(grid) - 1, 3))
                    path = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
                    sel = k == kk
                    walk[sel] = np.column_stack([np.interp(dt[sel], grid, path[:, i]) for i in range(3)])
                out[:, :3, :3] = R_stamp @ R_rel @ so3_exp_stack(walk)
            return out

        return patched

    def frame_motion(variant: str) -> Callable:
        def patched(trajectory, stamps_ns, camera, imu=None):
            m = orig_motion(trajectory, stamps_ns, camera, imu)
            v_true = sc.trajectory.state(np.asarray(stamps_ns) * 1e-9).v_world
            v_errors.append(np.linalg.norm(m.v_world - v_true, axis=1)[m.valid])
            if variant == "vel":
                m.v_world = v_true.copy()
            return m

        return patched

    def track_init(variant: str) -> Callable:
        def patched(self, imu, trajectory, accel_bias_body=None):
            imu = replace(imu, accel_m_s2=imu.accel_m_s2 - true_accel_bias(imu.timestamps_ns))
            if variant == "truetrack":
                trajectory = Trajectory("truth", gt.timestamps_ns, gt.T_world_body)
            orig_track(self, imu, trajectory)  # (the true bias: no fitted one on top)

        return patched

    det = read_cache(flight / "out" / "detections.csv")
    for variant in args.variants:
        v_errors.clear()
        rs._body_poses_at = body_poses(variant)
        rs.frame_motion = frame_motion(variant)
        if variant in ("accelbias", "truetrack"):
            rs._ImuTrack.__init__ = track_init(variant)  # type: ignore[method-assign]
        try:
            if args.calibrate:
                calib = rs.calibrate_readout(det, replace(cam, line_delay_s=0.0), log.world, log.imu)
                err = 100.0 * (calib.readout_s - cam.readout_s) / cam.readout_s
                ms = f"{1e3 * calib.readout_s:.2f} +- {1e3 * calib.sigma_s:.2f} ms"
                line = f"{variant:12s} readout {ms} ({err:+.1f} %)"
            elif args.pipeline:
                out = flight / f"out_diag_{variant}"
                out.mkdir(exist_ok=True)
                shutil.copy(flight / "out" / "detections.csv", out / "detections.csv")
                res = run(
                    flight / "log", out, RunConfig(workers=1, progress=False, force=True, incremental=False)
                )
                m = res.metrics["trajectories"]
                pnp = float(position_errors_cm(log, res.trajectories["pnp"]).mean())
                ate = 100.0 * m["smoother"]["ate_rmse_m"]
                nees = [m[e]["nees_pose_6dof"]["nees_mean"] for e in ("pnp", "smoother")]
                line = (
                    f"{variant:12s} PnP mean {pnp:.4f} cm, smoother ATE {ate:.4f} cm, "
                    f"NEES PnP / smoother {nees[0]:.1f} / {nees[1]:.1f}"
                )
            else:
                corrected, _ = rs.correct_flight(det, {"cam0": cam}, log.world, log.imu, streams=log.cameras)
                traj = pnp_trajectory(corrected.by_frame("cam0"), cam, log.world)[0]
                pnp = float(position_errors_cm(log, traj).mean())
                line = f"{variant:12s} PnP mean {pnp:.4f} cm, ratio to GS {pnp / gs_pnp:.3f}"
        finally:
            rs._body_poses_at, rs.frame_motion = orig_poses, orig_motion
            rs._ImuTrack.__init__ = orig_track  # type: ignore[method-assign]
        if v_errors:
            line += f", final motion's velocity error mean {1e3 * float(v_errors[-1].mean()):.2f} mm/s"
        print(line, flush=True)


if __name__ == "__main__":
    main()
