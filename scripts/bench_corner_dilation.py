"""Can a flight's PnP residuals see a corner bias common to every code, and does removing it make
the fused σ honest?  (Issue 10.3: the defocus r 1 flight's constant corner bias.)

Model: every refined floor code's four edges move outward along their image normal n by
b_u n_u^2 + b_v n_v^2 px (b_u: left / right edges, b_v: top / bottom; a code that looks wider /
taller), each corner where its two moved edges meet (fusion.qr.pnp.bias.dilation_pattern, (8, 2)
per code; the pipeline's own estimate, fusion.estimate.cornerbias, uses the dilation alone).  Per
flight, three numbers:

  truth    least-squares (b_u, b_v, plus a common shift) of the refined corners' error against
           their true projection (the simulator's ground truth), unweighted and weighted by each
           code's corner covariance (as PnP weighs them)
  resid    the same (b_u, b_v, shift) estimated from the PnP residuals alone: per posed frame the
           whitened residual r, Jacobian J (pose) and A (bias) at the PnP pose, accumulated over
           the flight as sum A^T M A b = sum A^T M r with M = I - J (J^T J)^-1 J^T (the bias
           that the pose cannot absorb: the normal equations reduced by the pose, a Schur
           complement); t = b / σ_b with σ_b from the flight's χ²/dof
  NEES     PnP / smoother / EKF 6-dof NEES (bench_realism.back_end, noise scales on, the
           pipeline's own correction, fusion.estimate.cornerbias, off) with the detections as
           they are, and with every refined cam0 corner moved by -resid

The decoder-fallback codes (σ = refine.FALLBACK_SIGMA_PX) are left out of the bias (their corners
are whole-pixel decoder output, not the edge model's).

    PYTHONPATH=$PWD python3 scripts/bench_corner_dilation.py [--effects clean defocus] [--workers 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import logging
import math
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_realism as br  # noqa: E402

from fusion.evaluate.metrics import interpolate_poses  # noqa: E402
from fusion.log import read_flight  # noqa: E402
from fusion.qr.codes import classify  # noqa: E402
from fusion.qr.detect import detect_flight  # noqa: E402
from fusion.qr.pnp import estimate_floor_poses  # noqa: E402
from fusion.qr.pnp.bias import dilation_pattern  # noqa: E402
from fusion.qr.pnp.whitening import CORNER_CLASSES, corner_classes, corner_whitening  # noqa: E402
from fusion.qr.reprojection import floor_reprojection  # noqa: E402
from fusion.sim.render import project_code_corners  # noqa: E402
from fusion.sim.scenarios import build_scenario  # noqa: E402
from fusion.sim.simulate import simulate  # noqa: E402

DECODER = CORNER_CLASSES.index("decoder")


def bias_columns(corners_px: np.ndarray, refined: bool) -> np.ndarray:
    """(8, 4): [b_u, b_v] dilation (refined codes only) and a common [u, v] shift."""
    a = np.zeros((8, 4))
    if refined:
        a[:, :2] = dilation_pattern(corners_px)
    a[0::2, 2] = 1.0
    a[1::2, 3] = 1.0
    return a


def truth_fit(log, det, resolution, weighted: bool) -> np.ndarray:
    """(4,) least-squares [b_u, b_v, shift u, shift v] of the refined cam0 corners' errors
    (`weighted`: whitened by each code's corner covariance, corner_whitening)."""
    sc = build_scenario("default", resolution)
    codes = {c.payload: c for c in sc.codes() if c.is_floor}
    cam, gt = log.floor.camera, log.groundtruth
    frames = det.by_frame("cam0")
    t = np.array(sorted(frames), dtype=np.int64)
    T_gt, ok = interpolate_poses(gt.timestamps_ns, gt.T_world_body, t)
    A, e = [], []
    for T_wb, ts in zip(T_gt, t[ok]):
        T_wc = cam.T_world_cam(T_wb)
        dets = [d for d in frames[int(ts)] if d.payload in codes]
        for d, cls in zip(dets, corner_classes(dets)):
            if cls == DECODER:
                continue
            uv = project_code_corners(cam, T_wc, codes[d.payload])
            W = corner_whitening([d], 0.15)[0] if weighted else np.eye(8)
            A.append(W @ bias_columns(d.corners_px, True))
            e.append(W @ (np.asarray(d.corners_px, dtype=float) - uv).reshape(-1))
    b, *_ = np.linalg.lstsq(np.vstack(A), np.concatenate(e), rcond=None)
    return b


def residual_fit(log, det) -> tuple[np.ndarray, np.ndarray]:
    """(4,) [b_u, b_v, shift u, shift v] from the PnP residuals and their (4,) σ."""
    cam = log.floor.camera
    frames = det.by_frame("cam0")
    floors = [classify(frames[t], log.world).floor for t in sorted(frames)]
    N, y = np.zeros((4, 4)), np.zeros(4)
    chi2 = dof = 0.0
    for floor, res in zip(floors, estimate_floor_poses(floors, cam)):
        if res is None:
            continue
        used = [s for s in floor if s.detection.payload in res.payloads]
        uv, J = floor_reprojection(cam, res.T_world_body, np.vstack([s.corners_world for s in used]))
        dets = [s.detection for s in used]
        W = corner_whitening(dets, 0.15)
        n = len(used)
        Wb = np.zeros((8 * n, 8 * n))
        for i in range(n):
            Wb[8 * i : 8 * i + 8, 8 * i : 8 * i + 8] = W[i]
        z = np.vstack([d.corners_px for d in dets]).reshape(-1)
        A = np.vstack([bias_columns(d.corners_px, c != DECODER) for d, c in zip(dets, corner_classes(dets))])
        r, Jw, Aw = Wb @ (z - uv.reshape(-1)), Wb @ J, Wb @ A
        M = np.eye(8 * n) - Jw @ np.linalg.solve(Jw.T @ Jw, Jw.T)
        N += Aw.T @ M @ Aw
        y += Aw.T @ M @ r
        chi2 += float(r @ M @ r)
        dof += 8 * n - 6
    unused = np.diag(N) == 0  # no refined code: no dilation column
    N[unused, unused] = 1.0
    b = np.linalg.solve(N, y)
    return b, np.sqrt(np.diag(np.linalg.inv(N)) * chi2 / dof)


def corrected(det, b: np.ndarray):
    """The detections with every refined cam0 code's corners moved by minus dilation b[:2]."""
    out = []
    for d in det.detections:
        if d.camera == "cam0" and corner_classes([d])[0] != DECODER:
            c = np.asarray(d.corners_px, dtype=float)
            d = dataclasses.replace(d, corners_px=c - (dilation_pattern(c) @ b[:2]).reshape(4, 2))
        out.append(d)
    return dataclasses.replace(det, detections=out)


def nees_row(log, det) -> tuple[float, float, float]:
    out = br.back_end(log, det, honest=True, corner_bias=False)  # the pipeline's own correction off
    return br.nees6(log, out["pnp"]), br.nees6(log, out["smoother"]), br.nees6(log, out["ekf"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--effects", nargs="*", default=["clean", "defocus"], choices=list(br.EFFECTS))
    ap.add_argument("--duration", type=float, default=12.0)
    ap.add_argument("--start", type=float, default=5.0)
    ap.add_argument("--fps", type=float, default=10.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    work = Path(tempfile.mkdtemp(prefix="bench_dilation_"))
    rows = []
    t0 = time.perf_counter()
    try:
        for effect in args.effects:
            for label, fields in br.EFFECTS[effect]:
                opts, resolution = br.camera_options(dict(fields))
                simulate(
                    work / "log",
                    "default",
                    duration_s=args.duration,
                    start_s=args.start,
                    seed=args.seed,
                    overwrite=True,
                    progress=False,
                    workers=args.workers,
                    resolution=resolution,
                    camera_rate_hz=args.fps,
                    camera_options=opts,
                )
                log = read_flight(work / "log")
                det = detect_flight(log, workers=args.workers, progress=False)
                truth = truth_fit(log, det, resolution, weighted=False)
                truth_w = truth_fit(log, det, resolution, weighted=True)
                b, sd = residual_fit(log, det)
                before, after = nees_row(log, det), nees_row(log, corrected(det, b))
                row = (effect, label, truth, truth_w, b, b / sd, before, after)
                rows.append(row)
                elapsed = time.perf_counter() - t0
                print(f"{effect} {label}: done ({elapsed:.0f} s)", file=sys.stderr, flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(
        f"# bench_corner_dilation ({datetime.date.today()}; {args.duration:.0f} s from {args.start:.0f} s "
        f"at {args.fps:.0f} fps, seed {args.seed})\n"
    )
    print(
        "| effect | level | truth b_u / b_v px | truth weighted | resid b_u / b_v px (t) "
        "| NEES pnp / smoother / ekf | NEES, corners moved by -resid |"
    )
    print("|---|---|---|---|---|---|---|")

    def nees(x) -> str:
        return " / ".join("-" if not math.isfinite(v) else f"{v:.1f}" for v in x)

    for effect, label, truth, truth_w, b, t, before, after in rows:
        print(
            f"| {effect} | {label} | {truth[0]:+.4f} / {truth[1]:+.4f} | "
            f"{truth_w[0]:+.4f} / {truth_w[1]:+.4f} | "
            f"{b[0]:+.4f} ({t[0]:+.1f}) / {b[1]:+.4f} ({t[1]:+.1f}) | {nees(before)} | {nees(after)} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
