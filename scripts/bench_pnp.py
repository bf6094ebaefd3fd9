"""Benchmark our per-frame PnP floor pose (fusion.qr.pnp) against its Cramér–Rao bound.

Views of the default scenario's kind (fusion.sim.scenarios: cam0 of make_cameras(), body-fixed,
640x480, f = 550 px, 0.20 m floor codes on a 1 m grid): body height 0.8-3 m, any yaw, roll and pitch
N(0, 5 deg), 1-4 codes fully in view (the 4 nearest the image centre when more are).

Modes:
  projected  corners = CameraModel.project of the true corners + N(0, sigma^2) per coordinate
  rendered   frames rendered by fusion.sim.render (sensor noise 2 DN, gain 1, no blur), decoded
             and refined by fusion.qr.detect.detect_frame; all decoded floor codes are used

Per group (codes in view, height): mean absolute error of world x, y, z (cm) and yaw (deg);
RMSE / sqrt(mean CRB variance) per axis (world frame; the CRB at the true pose with the corner
sigma); mean NEES of the PnP pose with its own covariance (6 is consistent); solve time per frame
(estimate_floor_pose only, one frame per call, CPU time of this process: the machine is shared),
and below each table the per-frame time when all views are solved in one call
(estimate_floor_poses, what pnp_trajectory does).  Targets: MAE <= 0.5 cm and <= 0.3 deg; RMSE
within 1.5x the CRB; the pose well under 1 ms per frame (detection + refinement + pose >= 300
frames/s per core at 640x480).

  flight     (--flight LOG --detections CSV) a recorded or simulated flight with cached
             detections: per-frame CPU time of pnp_trajectory (floor poses) and
             pnp_load_observations (load codes), and the floor poses' MAE and NEES against the
             flight's ground truth

    /work/venv/bin/python scripts/bench_pnp.py [--mode projected|rendered|both] [--n 600]
                                               [--sigma 0.13] [--seed 0]
    /work/venv/bin/python scripts/bench_pnp.py --mode flight --flight /tmp/demo1/log \
                                               --detections /tmp/demo1/out/detections.csv
"""

from __future__ import annotations

import argparse
import math
import time

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from fusion.geometry import inv_T, make_T, transform_points, wrap_angle, yaw_of
from fusion.qr.codes import classify
from fusion.qr.pnp import estimate_floor_pose, estimate_floor_poses
from fusion.qr.reprojection import floor_pose_crb
from fusion.sim.scenarios import build_scenario
from fusion.types import QRDetection

HEIGHT_BINS = [(0.8, 1.5), (1.5, 2.2), (2.2, 3.0)]


def world_cov(T_world_body: np.ndarray, cov_body: np.ndarray) -> np.ndarray:
    """6x6 body-frame [r, t] covariance -> world-frame [rotation, position] (first order)."""
    R = T_world_body[:3, :3]
    A = np.zeros((6, 6))
    A[:3, :3] = R
    A[3:, 3:] = R
    return A @ cov_body @ A.T


def sample_view(rng, scen, max_codes=4, margin_px=4.0):
    """A random body pose and the floor codes fully in its view (at most `max_codes`)."""
    cam = scen.cameras["cam0"]
    world = scen.layout.world
    centres = scen.layout.floor_centres_world()
    while True:
        tilt = np.clip(rng.normal(0.0, 5.0, 2), -15.0, 15.0)
        R = Rotation.from_euler("ZYX", [rng.uniform(-180, 180), tilt[0], tilt[1]], degrees=True).as_matrix()
        T = make_T(R, [rng.uniform(0.3, 9.7), rng.uniform(0.3, 6.7), rng.uniform(0.8, 3.0)])
        T_cam_world = inv_T(cam.T_world_cam(T))
        seen = []
        for c in centres:
            uv = cam.project(transform_points(T_cam_world, world.floor_corners_world(c)))
            if (
                np.all(np.isfinite(uv))
                and np.all(uv >= margin_px)
                and np.all(uv <= [cam.width - 1 - margin_px, cam.height - 1 - margin_px])
            ):
                seen.append((float(np.linalg.norm(uv.mean(axis=0) - cam.image_centre_px)), c, uv))
        if seen:
            seen.sort(key=lambda s: s[0])
            return T, [(c, uv) for _, c, uv in seen[:max_codes]]


def errors_row(T_true, res, crb_body):
    """(dx, dy, dz, dyaw, xi, nees, crb_world_diag)."""
    d = res.T_world_body[:3, 3] - T_true[:3, 3]
    dyaw = float(wrap_angle(yaw_of(res.T_world_body[:3, :3]) - yaw_of(T_true[:3, :3])))
    xi = gtsam.Pose3(T_true).localCoordinates(gtsam.Pose3(res.T_world_body))
    nees = float(xi @ np.linalg.solve(res.covariance, xi))
    return d, dyaw, nees, np.diag(world_cov(T_true, crb_body))


def run_projected(scen, n, sigma, seed):
    rng = np.random.default_rng(seed)
    cam = scen.cameras["cam0"]
    world = scen.layout.world
    from fusion.conventions import floor_payload

    rows = []
    for _ in range(n):
        T, seen = sample_view(rng, scen)
        dets = [
            QRDetection(
                "cam0",
                0,
                floor_payload(c[0] / world.payload_unit_m, c[1] / world.payload_unit_m),
                uv + rng.normal(0.0, sigma, uv.shape),
                uv,
            )
            for c, uv in seen
        ]
        floor = classify(dets, world).floor
        t0 = time.process_time()
        res = estimate_floor_pose(floor, cam, sigma)
        dt = time.process_time() - t0
        crb = floor_pose_crb(cam, T, [world.floor_corners_world(c) for c, _ in seen], sigma)
        rows.append((T, len(seen), res, crb, dt, floor))
    return rows


def run_rendered(scen, n, sigma, seed):
    from fusion.qr.detect import detect_frame
    from fusion.sim.render import RenderEffects, project_code_corners, render_view

    rng = np.random.default_rng(seed)
    cam = scen.cameras["cam0"]
    world = scen.layout.world
    codes = [c for c in scen.codes() if c.is_floor]
    rows, corner_err, corner_h, n_truth, n_decoded = [], [], [], 0, 0
    t_render = t_detect = 0.0
    for _ in range(n):
        T, seen = sample_view(rng, scen, max_codes=99)
        T_wc = cam.T_world_cam(T)
        t0 = time.process_time()
        img = render_view(cam, T_wc, codes, rng, RenderEffects(noise_sigma_dn=2.0))
        t1 = time.process_time()
        dets = detect_frame(img, "cam0", 0, cam)
        t2 = time.process_time()
        t_render += t1 - t0
        t_detect += t2 - t1
        floor = classify(dets, world).floor
        n_truth += len(seen)
        n_decoded += len(floor)
        truth = {c.payload: project_code_corners(cam, T_wc, c) for c in codes}
        for s in floor:
            if s.detection.payload in truth:
                corner_err.append(s.detection.corners_px - truth[s.detection.payload])
                corner_h.append(np.full(4, T[2, 3]))
        if not floor:
            rows.append((T, 0, None, None, 0.0))
            continue
        t0 = time.process_time()
        res = estimate_floor_pose(floor, cam, sigma)
        dt = time.process_time() - t0
        crb = floor_pose_crb(cam, T, [s.corners_world for s in floor], sigma)
        rows.append((T, len(floor), res, crb, dt, floor))
    ce = np.concatenate(corner_err) if corner_err else np.zeros((0, 2))
    extra = {
        "corner_rms_px": float(np.sqrt(np.mean(ce**2))) if len(ce) else float("nan"),
        "corner_mean_abs_px": float(np.mean(np.abs(ce))) if len(ce) else float("nan"),
        "corner_rms_by_height": {
            f"{a}-{b} m": float(np.sqrt(np.mean(ce[(hh >= a) & (hh < b)] ** 2)))
            for a, b in HEIGHT_BINS
            for hh in [np.concatenate(corner_h) if corner_h else np.zeros(0)]
            if np.any((hh >= a) & (hh < b))
        },
        "decoded": f"{n_decoded}/{n_truth}",
        "render_ms": 1e3 * t_render / n,
        "detect_ms": 1e3 * t_detect / n,
    }
    return rows, extra


def batch_ms_per_frame(rows, cam, sigma) -> float:
    """CPU ms per frame of estimate_floor_poses on all the rows' views in one call (best of 3)."""
    views = [r[5] for r in rows if len(r) > 5 and r[5]]
    best = math.inf
    for _ in range(3):
        t0 = time.process_time()
        estimate_floor_poses(views, cam, sigma)
        best = min(best, time.process_time() - t0)
    return 1e3 * best / max(len(views), 1)


def run_flight(log_dir, detections, sigma):
    """Per-frame time and accuracy of pnp_trajectory / pnp_load_observations on a flight."""
    from fusion.log import read_flight
    from fusion.qr.detect import read_cache
    from fusion.qr.pnp import pnp_load_observations, pnp_trajectory, pose_at
    from fusion.types import Trajectory

    log = read_flight(log_dir)
    det = read_cache(detections)
    floor, front = det.by_frame("cam0"), det.by_frame("cam1")
    t_floor = t_load = math.inf
    for _ in range(3):  # best of 3: the machine is shared
        t0 = time.process_time()
        traj, stats = pnp_trajectory(floor, log.floor.camera, log.world, sigma)
        t1 = time.process_time()
        obs = (
            pnp_load_observations(front, log.front.camera, log.world, traj, sigma)
            if log.front is not None
            else []
        )
        t2 = time.process_time()
        t_floor, t_load = min(t_floor, t1 - t0), min(t_load, t2 - t1)
    n_front = sum(1 for ts in front if front[ts])
    print(f"\n### Flight {log_dir} ({len(floor)} floor frames with detections, {n_front} front)\n")
    print("| part | frames | posed / observations | CPU ms per frame (best of 3) |")
    print("|---|---|---|---|")
    print(
        f"| floor poses (pnp_trajectory) | {len(floor)} | {stats.n_posed} | "
        f"{1e3 * t_floor / max(len(floor), 1):.3f} |"
    )
    print(
        f"| load codes (pnp_load_observations) | {n_front} | {len(obs)} | "
        f"{1e3 * t_load / max(n_front, 1):.3f} |"
    )
    gt = log.groundtruth
    if gt is None or len(traj) == 0:
        return
    truth = Trajectory("gt", np.asarray(gt.timestamps_ns), gt.T_world_body)
    d, dyaw, nees = [], [], []
    for ts, T, cov in zip(traj.timestamps_ns, traj.T_world_body, traj.covariances):
        ref = pose_at(truth, int(ts), 0.05)
        if ref is None:
            continue
        d.append(T[:3, 3] - ref[0][:3, 3])
        dyaw.append(wrap_angle(yaw_of(T[:3, :3]) - yaw_of(ref[0][:3, :3])))
        xi = gtsam.Pose3(ref[0]).localCoordinates(gtsam.Pose3(T))
        nees.append(float(xi @ np.linalg.solve(cov, xi)))
    mae = 100 * np.mean(np.abs(d), axis=0)
    print(
        f"\nFloor poses vs ground truth ({len(d)} poses): MAE x, y, z {mae[0]:.3f}, {mae[1]:.3f}, "
        f"{mae[2]:.3f} cm, yaw {math.degrees(np.mean(np.abs(dyaw))):.4f} deg; pose NEES mean "
        f"{np.mean(nees):.2f} (ideal 6), median {np.median(nees):.2f}; ambiguous "
        f"{stats.n_ambiguous}, codes dropped {stats.n_codes_dropped}."
    )


def table(rows, title):
    print(f"\n### {title}\n")
    print(
        "| group | frames | posed | MAE x cm | MAE y cm | MAE z cm | MAE yaw deg | "
        "√CRB x, y, z cm | RMSE/√CRB x | y | z | yaw | mean NEES (6) | solve ms CPU (mean / p95) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    groups = [("all", lambda r: True)]
    groups += [(f"{k} code{'s' if k > 1 else ''}", lambda r, k=k: r[1] == k) for k in (1, 2, 3, 4)]
    groups += [(f"h {a}-{b} m", lambda r, a=a, b=b: a <= r[0][2, 3] < b) for a, b in HEIGHT_BINS]
    if any(r[1] > 4 for r in rows):
        groups.insert(5, ("5+ codes", lambda r: r[1] > 4))
    for name, sel in groups:
        sub = [r for r in rows if sel(r) and r[1] > 0]
        posed = [r for r in sub if r[2] is not None]
        if not posed:
            print(f"| {name} | {len(sub)} | 0 | | | | | | | | | | | |")
            continue
        e = [errors_row(r[0], r[2], r[3]) for r in posed]
        d = np.array([x[0] for x in e])
        dyaw = np.array([x[1] for x in e])
        nees = np.array([x[2] for x in e])
        crbw = np.array([x[3] for x in e])  # world [rx, ry, rz, x, y, z] variances
        rmse = np.sqrt(np.mean(np.column_stack([d, dyaw]) ** 2, axis=0))
        bound = np.sqrt(np.mean(crbw[:, [3, 4, 5, 2]], axis=0))
        ratio = rmse / bound
        ms = 1e3 * np.array([r[4] for r in posed])
        mae = np.mean(np.abs(d), axis=0) * 100
        print(
            f"| {name} | {len(sub)} | {len(posed)} | {mae[0]:.2f} | {mae[1]:.2f} | {mae[2]:.2f} | "
            f"{math.degrees(np.mean(np.abs(dyaw))):.3f} | "
            f"{100 * bound[0]:.2f}, {100 * bound[1]:.2f}, {100 * bound[2]:.2f} | "
            f"{ratio[0]:.2f} | {ratio[1]:.2f} | "
            f"{ratio[2]:.2f} | {ratio[3]:.2f} | {np.mean(nees):.1f} | "
            f"{ms.mean():.2f} / {np.percentile(ms, 95):.2f} |"
        )
    med = np.median([errors_row(r[0], r[2], r[3])[2] for r in rows if r[2] is not None])
    print(
        "\nNEES: mean over frames of xi^T Sigma^-1 xi with xi = Logmap(T_true^-1 T_est) (GTSAM) "
        f"and Sigma the estimator's own covariance (consistent: mean 6); median {med:.1f} "
        "(chi-square(6) median: 5.35)."
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mode", choices=("projected", "rendered", "both", "flight"), default="both")
    ap.add_argument("--flight", help="flight log folder (mode flight)")
    ap.add_argument("--detections", help="its cached detections.csv (mode flight)")
    ap.add_argument("--n", type=int, default=600, help="views in projected mode")
    ap.add_argument("--n-rendered", type=int, default=150, help="views in rendered mode")
    ap.add_argument("--sigma", type=float, default=0.13, help="corner noise, px per coordinate")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.mode == "flight":
        if not (args.flight and args.detections):
            ap.error("--mode flight needs --flight and --detections")
        run_flight(args.flight, args.detections, args.sigma)
        return
    scen = build_scenario("default")
    cam = scen.cameras["cam0"]
    print(
        f"PnP benchmark: cam0 of the default scenario ({cam.width}x{cam.height}, f = {cam.fu:.0f} "
        f"px, {cam.mount}), floor codes {scen.layout.world.floor_side_m} m on a "
        f"{scen.layout.world.payload_unit_m} m grid, corner sigma {args.sigma} px, seed {args.seed}."
    )
    if args.mode in ("projected", "both"):
        rows = run_projected(scen, args.n, args.sigma, args.seed)
        table(rows, f"Projected corners + N(0, {args.sigma}²) px, {args.n} views")
        print(
            f"\nAll {args.n} views in one call (estimate_floor_poses): "
            f"{batch_ms_per_frame(rows, cam, args.sigma):.3f} ms CPU per frame."
        )
    if args.mode in ("rendered", "both"):
        rows, extra = run_rendered(scen, args.n_rendered, args.sigma, args.seed + 1)
        table(
            rows,
            f"Rendered + detected frames, {args.n_rendered} views (all decoded floor codes "
            f"used; CRB with sigma {args.sigma} px)",
        )
        print(
            f"\nAll views in one call (estimate_floor_poses): "
            f"{batch_ms_per_frame(rows, cam, args.sigma):.3f} ms CPU per frame."
        )
        print(
            f"\nRendered mode: floor codes decoded / fully in view: {extra['decoded']}; "
            f"refined corner error vs projection: RMS {extra['corner_rms_px']:.3f} px, mean abs "
            f"{extra['corner_mean_abs_px']:.3f} px per coordinate (RMS by body height: "
            + ", ".join(f"{k} {v:.3f} px" for k, v in extra["corner_rms_by_height"].items())
            + f"); render {extra['render_ms']:.1f} "
            f"ms, detect+refine {extra['detect_ms']:.1f} ms per frame."
        )


if __name__ == "__main__":
    main()
