"""Can the image beat the gyro over a rolling-shutter readout?  (issue 10.1, BENCHMARKS.md `rsjoint`)

On a flight written by scripts/bench_rolling_shutter.py (its log and detections cache), for
every floor frame, linearised at the TRUE per-row poses with the refinement's corner covariances
(fusion.qr.pnp.readout_information):

- the PnP position error the gyro's white noise over the readout adds (as PnP weights the
  corners now), and what the best linear estimator using the image and the gyro together would
  leave (generalised least squares: a rolling-shutter PnP with the gyro as a prior can do no
  better, to first order);
- the image's information on a constant body-rate error over the readout against the gyro's
  (readout / sigma_g^2 per axis);
- the same with a prior on the stamp pose (--prior-position-mm per axis, --prior-rotation-mrad
  per axis: a fused estimate's, for a second correction pass that takes the pose from the
  smoother);
- PnP's rotation sigma against the gyro's rotation over one frame period (what the smoother's
  images could add to the gyro between two stamps, i.e. to a readout rotation kept as a state).

    PYTHONPATH=$PWD python3 scripts/rs_rate_information.py --dir D [--speed 2] [--readout-ms 30]
        [--prior-position-mm 0.15] [--prior-rotation-mrad 0.05]
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_rolling_shutter import bench_scenario  # noqa: E402

from fusion.log import read_flight  # noqa: E402
from fusion.qr.codes import classify  # noqa: E402
from fusion.qr.detect import read_cache  # noqa: E402
from fusion.qr.pnp import DEFAULT_CORNER_SIGMA_PX  # noqa: E402
from fusion.qr.pnp.readout_information import ReadoutInformation, frame_readout_information  # noqa: E402


def flight_information(flight: Path, speed: float, pose_prior_cov: np.ndarray) -> list[ReadoutInformation]:
    """`ReadoutInformation` of every floor frame of the bench flight directory `flight`, with
    `pose_prior_cov` (6, 6) as the stamp pose's prior for its `_with_prior` field."""
    log = read_flight(flight / "log")
    cam = log.floor.camera
    gt_end_s = float(log.groundtruth.timestamps_ns[-1]) * 1e-9
    trajectory = bench_scenario(speed, gt_end_s + 0.005).trajectory
    frames = read_cache(flight / "out" / "detections.csv").by_frame("cam0")
    out = []
    for ts in sorted(frames):
        codes = classify(frames[ts], log.world).floor
        if not codes:
            continue
        P = np.concatenate([np.asarray(s.corners_world, float) for s in codes])
        uv = np.concatenate([np.asarray(s.detection.corners_px, float).reshape(4, 2) for s in codes])
        covs = np.stack(
            [
                np.asarray(s.detection.corner_cov_px2, float)
                if s.detection.corner_cov_px2 is not None
                else (s.detection.corner_sigma_px or DEFAULT_CORNER_SIGMA_PX) ** 2 * np.eye(8)
                for s in codes
            ]
        )
        dt = cam.row_time_offset_s(uv[:, 1])
        rows = trajectory.state(ts * 1e-9 + dt).T_world_body
        out.append(
            frame_readout_information(
                cam,
                rows,
                P,
                covs,
                dt,
                log.imu.noise.gyroscope_noise_density,
                cam.readout_s,
                1 / cam.rate_hz,
                pose_prior_cov,
            )
        )
    return out


def summary(infos: list[ReadoutInformation]) -> list[str]:
    """Printable lines: flight-wide RMS position errors and the information ratios."""
    c0 = np.array([i.pos_var_corners for i in infos])
    now = np.array([i.pos_var_now for i in infos])
    best = np.array([i.pos_var_best for i in infos])
    xy = np.array([i.pos_var_now_xy for i in infos])
    excess = float(now.sum() - c0.sum())
    won = (now.sum() - best.sum()) / excess if excess > 0 else math.nan
    yaw = 1.0 - (xy.sum() - c0.sum()) / excess if excess > 0 else math.nan
    rate = np.array([i.rate_information_image / i.rate_information_gyro for i in infos])
    prior = np.array([i.rate_information_image_with_prior / i.rate_information_gyro for i in infos])
    rot = np.array([(i.rotation_sigma_gyro / (math.sqrt(2.0) * i.rotation_sigma_pnp)) ** 2 for i in infos])
    return [
        f"{len(infos)} frames; PnP position RMS (mm): corners only {1e3 * math.sqrt(c0.mean()):.4f}, "
        f"with the gyro's readout noise as now {1e3 * math.sqrt(now.mean()):.4f} "
        f"(x {math.sqrt(now.mean() / c0.mean()):.3f}), best linear use of image + gyro "
        f"{1e3 * math.sqrt(best.mean()):.4f} (x {math.sqrt(best.mean() / c0.mean()):.3f})",
        f"per frame, median RMS ratio now {np.median(np.sqrt(now / c0)):.3f}, best "
        f"{np.median(np.sqrt(best / c0)):.3f}; share of the gyro's excess variance the best "
        f"estimator removes {won:.3f}; share due to the rotation about body z {yaw:.3f}",
        "constant body rate over the readout, image / gyro information per axis (x, y, z; upper "
        f"bound): median {np.round(np.median(rate, axis=0), 4)}, mean {np.round(rate.mean(axis=0), 4)}, "
        f"p90 {np.round(np.percentile(rate, 90, axis=0), 4)}",
        f"the same with the stamp pose's prior: median {np.round(np.median(prior, axis=0), 4)}, "
        f"mean {np.round(prior.mean(axis=0), 4)}",
        "rotation between consecutive stamps, images / gyro information per axis: median "
        f"{np.round(np.median(rot, axis=0), 4)} (PnP rotation sigma median "
        f"{np.round(1e3 * np.median([i.rotation_sigma_pnp for i in infos], axis=0), 4)} mrad, gyro "
        f"{1e3 * infos[0].rotation_sigma_gyro:.4f} mrad per frame period)",
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dir", type=Path, required=True)
    ap.add_argument("--speed", type=float, default=2.0)
    ap.add_argument("--readout-ms", type=float, default=30.0)
    ap.add_argument("--prior-position-mm", type=float, default=0.15)
    ap.add_argument("--prior-rotation-mrad", type=float, default=0.05)
    args = ap.parse_args()
    if not (args.prior_position_mm > 0 and args.prior_rotation_mrad > 0):
        sys.exit("error: --prior-position-mm and --prior-rotation-mrad must be positive")
    prior = np.diag([(1e-3 * args.prior_rotation_mrad) ** 2] * 3 + [(1e-3 * args.prior_position_mm) ** 2] * 3)
    flight = args.dir / f"v{args.speed:g}_ro{args.readout_ms:g}"
    infos = flight_information(flight, args.speed, prior)
    if not infos:
        sys.exit(f"error: {flight}: no floor frame with a code")
    print(f"{flight} (stamp pose prior {args.prior_position_mm:g} mm, {args.prior_rotation_mrad:g} mrad):")
    for line in summary(infos):
        print("  " + line)


if __name__ == "__main__":
    main()
