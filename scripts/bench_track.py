"""Floor codes tracked through motion blur and occlusion (fusion.qr.track): how many floor-camera
frames still give a PnP pose, and whether any code is given a wrong identity.

Frames: the "default" scenario's floor camera (640x480) at 30 Hz over 5 s windows of its survey
(one window per seed; its first SEED_FRAMES frames clean, as the earlier frames where the codes
were decoded, and not counted), rendered with 10 px motion blur along the image motion
(RenderEffects) and, separately, with 10 % of each floor symbol hidden in every frame (a square
of a tenth of the symbol's area at a random place, random grey: drawn here over the rendered
image, since the renderer has no occluders on codes).  Each condition runs detection frame by
frame in time order (detect_frames) in three modes (TRACK_MODES): no tracker; the tracker with
its own pixel-motion prediction only (what detect_flight runs); and the tracker also fed the
floor codes that the pose extrapolated from the last PnP poses puts in view.  Then
estimate_floor_pose per frame.  "Floor frames": frames with at least one floor code entirely in
view.  A detection's identity is wrong when the code it names is not in view or another code's
true centre is nearer to it.  Also: zxing-cpp's try_downscale (its default, off in fusion) on
the same frames: codes read and time.

    PYTHONPATH=. python3 scripts/bench_track.py [--seeds 3] [--seconds 5]
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import zxingcpp

from fusion.geometry import interpolate_pose
from fusion.qr.codes import classify
from fusion.qr.detect import ZXING_FORMATS, ZXING_OPTIONS, CameraStats, detect_frames
from fusion.qr.pnp import estimate_floor_pose
from fusion.qr.track import CodeTracker
from fusion.sim.render import RenderEffects, project_code_corners, render_view
from fusion.sim.scenarios import build_scenario

RATE_HZ = 30.0
BLUR_PX = 10.0
OCCLUDED_FRACTION = 0.10
NOISE_DN = 2.0
PREDICTION_SIGMA_PX = 3.0  # 1-sigma of corners predicted from the extrapolated pose
MAX_PREDICTION_S = 0.5  # no prediction from poses older than this
VELOCITY_BASELINE_S = 0.05
TRACK_MODES = ("off", "motion", "pose")  # no tracker; own pixel motion only; + pose-predicted codes
SEED_FRAMES = 3  # first frames of a window: no blur, no occlusion (the earlier decode); not counted


def _blur_angle(camera, T_a, T_b) -> float:
    """Direction (rad) in which the floor point on the optical axis moves in the image."""
    p_cam = np.array([0.0, 0.0, 1.0])
    R, t = T_a[:3, :3], T_a[:3, 3]
    d = R @ p_cam
    s = -t[2] / d[2] if abs(d[2]) > 1e-9 else 1.0
    p_world = t + s * d
    T_b_inv = np.linalg.inv(T_b)
    p_b = T_b_inv[:3, :3] @ p_world + T_b_inv[:3, 3]
    uv_a = np.array([camera.cu, camera.cv])
    uv_b = camera.project(p_b[None])[0]
    delta = uv_b - uv_a
    return float(np.arctan2(delta[1], delta[0]))


def _occlude(img: np.ndarray, corners_px: np.ndarray, rng) -> None:
    """Hide OCCLUDED_FRACTION of the symbol whose corners (4, 2) are given: a square in symbol
    coordinates, random place and grey."""
    side = np.sqrt(OCCLUDED_FRACTION)
    u0, v0 = rng.uniform(0.0, 1.0 - side, 2)
    sq = np.array([[u0, v0], [u0 + side, v0], [u0 + side, v0 + side], [u0, v0 + side]], np.float32)
    src = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    H = cv2.getPerspectiveTransform(src, corners_px.astype(np.float32))
    quad = cv2.perspectiveTransform(sq[None], H)[0]
    cv2.fillConvexPoly(img, np.round(quad * 16).astype(np.int32), int(rng.uniform(40, 200)), cv2.LINE_AA, 4)


def render(scenario, seed: int, seconds: float, condition: str):
    """Frames (list of (H, W) uint8), timestamps_ns, per frame {payload: true corners (4, 2)} of
    the floor codes entirely in view."""
    cam = scenario.cameras["cam0"]
    codes = [c for c in scenario.codes() if c.is_floor]
    rng = np.random.default_rng(seed)
    t0 = 5.0 + 10.0 * seed
    ts = t0 + np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    T_body = scenario.trajectory.state(np.concatenate([ts, ts + 1.0 / RATE_HZ])).T_world_body
    frames, stamps, truths = [], [], []
    centres: list[dict] = [{} for _ in ts]  # every code in front of the camera: projected centre
    h, w = cam.height, cam.width
    for k, t in enumerate(ts):
        T_a = cam.T_world_cam(T_body[k])
        T_b = cam.T_world_cam(T_body[k + len(ts)])
        blur = BLUR_PX if condition == "blur" else 0.0
        clean = k < SEED_FRAMES  # an earlier decode: the drone slower, the code clean
        blur = 0.0 if clean else blur
        eff = RenderEffects(NOISE_DN, 1.0, blur, _blur_angle(cam, T_a, T_b) if blur else 0.0)
        img = render_view(cam, T_a, codes, rng, eff)
        truth = {}
        for c in codes:
            p = project_code_corners(cam, T_a, c)
            if p is None or not np.all(np.isfinite(p)):
                continue
            centres[k][c.payload] = p.mean(axis=0)
            if np.all((p >= 2) & (p <= [w - 3, h - 3])):
                truth[c.payload] = p
                if condition == "occlusion" and not clean:
                    _occlude(img, p, rng)
        frames.append(img)
        stamps.append(int(round(t * 1e9)))
        truths.append(truth)
    return frames, stamps, truths, centres


def _predictions(cam, codes, poses, t_ns: int) -> dict:
    """payload -> (corners, sigma px, modules) of the floor codes that the camera pose,
    extrapolated at constant velocity from the last two PnP poses, puts in view."""
    if len(poses) < 2 or t_ns - poses[-1][0] > MAX_PREDICTION_S * 1e9:
        return {}
    t1, T1 = poses[-1]
    # velocity over a baseline of VELOCITY_BASELINE_S (consecutive poses: their noise, amplified)
    older = [p for p in poses[:-1] if t1 - p[0] >= VELOCITY_BASELINE_S * 1e9]
    t0, T0 = older[-1] if older else poses[-2]
    T_body = interpolate_pose(T0, T1, (t_ns - t0) / (t1 - t0))
    T_cam = cam.T_world_cam(T_body)
    out = {}
    for c in codes:
        p = project_code_corners(cam, T_cam, c)
        if p is not None and np.all(np.isfinite(p)):
            out[c.payload] = (p, PREDICTION_SIGMA_PX, c.modules)
    return out


def run(scenario, frames, stamps, truths, centres_all, track: str):
    """Frame by frame in time order: detection (with the tracker: fed the codes that the pose
    extrapolated from the last two PnP poses puts in view), PnP, identity check."""
    cam = scenario.cameras["cam0"]
    world = scenario.layout.world
    codes = [c for c in scenario.codes() if c.is_floor]
    tracker = CodeTracker(cam) if track != "off" else None
    stats = CameraStats()
    out = dict(floor_frames=0, poses=0, wrong_ids=0, tracked=0, decoded=0, pos_err=[])
    poses: list[tuple[int, np.ndarray]] = []
    for k, (img, truth, ts, centres) in enumerate(zip(frames, truths, stamps, centres_all)):
        dets = detect_frames([img], "cam0", [ts], cam, "zxing", stats, None)[0]
        if tracker is not None:
            modules = [next((c.modules for c in codes if c.payload == d.payload), None) for d in dets]
            predicted = _predictions(cam, codes, poses, ts) if track == "pose" else None
            dets = dets + tracker.step(img, "cam0", ts, dets, modules, predicted)
        for d in dets:
            # wrong identity: the code it names is not in view, or another code's true centre is
            # nearer to its centre than that code's
            own = centres.get(d.payload)
            c = d.corners_px.mean(axis=0)
            if own is None or any(
                np.linalg.norm(c - o) < np.linalg.norm(c - own) for p, o in centres.items() if p != d.payload
            ):
                out["wrong_ids"] += 1
            out["tracked" if d.tracked else "decoded"] += 1
        fc = classify(dets, world)
        res = estimate_floor_pose(fc.floor, cam) if fc.floor else None
        if res is not None:
            poses.append((ts, res.T_world_body))
        if not truth or k < SEED_FRAMES:
            continue
        out["floor_frames"] += 1
        if res is not None:
            out["poses"] += 1
            T_true = scenario.trajectory.state(np.array([ts * 1e-9])).T_world_body[0]
            out["pos_err"].append(float(np.linalg.norm(res.T_world_body[:3, 3] - T_true[:3, 3])))
    return out


def downscale_cost(frames) -> tuple[int, int, float, float]:
    """Codes read and ms per frame with fusion's zxing options and with try_downscale on."""
    res = []
    for down in (False, True):
        opts = dict(ZXING_OPTIONS)
        opts["try_downscale"] = down
        t = time.process_time()
        n = sum(len(zxingcpp.read_barcodes(f, formats=ZXING_FORMATS, **opts)) for f in frames)
        res.append((n, 1e3 * (time.process_time() - t) / len(frames)))
    return res[0][0], res[1][0], res[0][1], res[1][1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=5.0)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    scenario = build_scenario("default")
    print(
        "| condition | tracking | floor frames | frames with a pose | decoded | tracked | wrong ids "
        "| median / max position error cm |"
    )
    print("|---|---|---|---|---|---|---|---|")
    down_rows = []
    for condition in ("blur", "occlusion"):
        tot: dict = {mode: None for mode in TRACK_MODES}
        for seed in range(args.seeds):
            frames, stamps, truths, centres = render(scenario, seed, args.seconds, condition)
            down_rows.append((condition, seed) + downscale_cost(frames[SEED_FRAMES:]))
            for track in TRACK_MODES:
                r = run(scenario, frames, stamps, truths, centres, track)
                if tot[track] is None:
                    tot[track] = r
                else:
                    for k in r:
                        tot[track][k] += r[k]
        for track in TRACK_MODES:
            r = tot[track]
            e = 100 * np.array(r["pos_err"]) if r["pos_err"] else np.array([np.nan])
            print(
                f"| {condition} ({BLUR_PX:g} px)"
                if condition == "blur"
                else f"| occlusion {OCCLUDED_FRACTION:.0%}",
                end="",
            )
            print(
                f" | {track} | {r['floor_frames']} | {r['poses']} "
                f"({100 * r['poses'] / max(r['floor_frames'], 1):.0f} %) | {r['decoded']} | {r['tracked']} "
                f"| {r['wrong_ids']} | {np.median(e):.2f} / {np.max(e):.2f} |"
            )
    print()
    print("| condition | seed | codes read (fusion options) | with try_downscale | ms/frame | with it |")
    print("|---|---|---|---|---|---|")
    for c, s, n0, n1, t0, t1 in down_rows:
        print(f"| {c} | {s} | {n0} | {n1} | {t0:.2f} | {t1:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
