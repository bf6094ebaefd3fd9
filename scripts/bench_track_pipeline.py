"""The track pass end to end (fusion.qr.predict, issue 10 item 4): `fusion run` with and without
it on simulated flights (`fusion simulate --exposure / --occlusion ...`), checked against the
simulator's truth.

Per flight and mode (--track / --no-track), pipeline.run into OUT/<flight>-<mode>, then:

- floor frames: frames where at least one floor code lies entirely in the image at the true pose
  (the simulator's own projection, fusion.sim.render.project_code_corners, 2 px margin);
- frames with a PnP pose among them (trajectory "pnp");
- decoded and tracked floor sightings (detections.csv); a tracked sighting's identity is wrong
  when the code it names is not in front of the camera, or another code's true centre is nearer
  to its centre than that code's; its worst corner error against the true corners (px);
- ATE RMSE of pnp and smoother (metrics.json), the track pass's seconds and seconds per frame
  tried; how many of the tracked sightings were decoded with re-stamped finders
  (fusion.qr.restamp, metrics.json `detection.tracking.restamped`) and that step's seconds.

    PYTHONPATH=. python3 scripts/bench_track_pipeline.py FLIGHT... [--out DIR] [--modes track no-track]

Flights are made with e.g. `fusion simulate F --duration 40 --seed 1 --exposure 0.05`, or by
the bench itself: `--simulate KIND --seeds 0 1 2` makes (once) OUT/flights/KIND_sSEED, 40 s of
the default scenario, and runs on them: KIND blur20 (20 ms exposure, ~10 px of blur when
cruising), strip-L / strip-H (the simulator's 10 % strip occluder, floor codes at ECC L, the
simulator's default, or H, the `qr-sheet` default).

Every row gives the posed share over all floor frames (the issue's target) and over those
outside the simulator's blackouts (shadow, glare, torn: the codes made unreadable on purpose,
fusion.sim.render._apply_blackout; 108 of the 1125 floor frames of a 40 s flight).

`--occlude SRC DST --occluder strip|square|none [--fraction 0.1]`: DST = a copy of the flight SRC
whose floor images get, on every floor code in view at the true pose, the simulator's occluder
(render.occlusion_polygon's strip from a random side, fusion simulate --occlusion) or a square
of the same area at a random place inside the symbol, drawn anew every frame (a strap or a hand
that moves), with the simulator's grey (render.OCCLUDER_DN): the simulator's occluder measured
against a less adversarial one on the same flight (`occlusion_decode_rates` counts zxing's
decodes per kind on a flight's frames).

`--reasons`: no fusion; the per-frame stage and the track pass only (detections from OUT's
cache when there is one), and every floor frame without a PnP pose after the pass counted by why
(`loss_reasons`): inside a blackout, decoded but PnP found no pose, or the pass's outcome at the
frame (fusion.qr.predict.OUTCOMES); the re-stamped sightings' counts and wrong identities, the
pass's CPU seconds in this process (the whole pass with `--workers 1`), and the PnP poses'
position RMSE against the truth and how many are over 5 cm (the per-frame stage after the pass),
and the same over the frames posed with the pass's (tracked or re-stamped) sightings
(`pnp_with_pass_sightings`). `--no-fit`: the pass without its IMU-fit predictions
(fusion.qr.predict.USE_FIT = False; the predictions before it existed).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np

from fusion.geometry import interpolate_poses
from fusion.log import read_flight
from fusion.log.files import read_tum
from fusion.pipeline import RunConfig, localize_stage, run
from fusion.qr.detect import (
    CACHE_NAME,
    detect_flight,
    detect_image,
    flight_fingerprint,
    read_cache,
    write_cache,
)
from fusion.qr.predict import track_flight, without_tracked
from fusion.sim.render import OCCLUDER_DN, occlusion_polygon, project_code_corners
from fusion.sim.scenarios import build_scenario
from fusion.types import Estimator

OCCLUDE_SEED = 0
EDGE_MARGIN_PX = 2.0  # a code counts as in view when its corners are this far inside the image


def _truth_corners(camera, T_world_body: np.ndarray, codes) -> dict[str, np.ndarray]:
    """payload -> true corners (4, 2) px of the floor codes in front of the camera."""
    T_world_cam = camera.T_world_cam(T_world_body)
    out = {}
    for c in codes:
        uv = project_code_corners(camera, T_world_cam, c)  # NaN behind the camera
        if np.all(np.isfinite(uv)):
            out[c.payload] = uv
    return out


def _floor_frames(log) -> tuple[np.ndarray, np.ndarray, dict]:
    """(floor stamps (N,), floor-frame mask (N,): a floor code entirely in the image at the true
    pose, {stamp: true corners by payload})."""
    cam = log.floor.camera
    codes = [c for c in build_scenario("default").codes() if c.is_floor]
    gt = log.groundtruth
    stamps = np.asarray(log.floor.timestamps_ns, dtype=np.int64)
    T_true = interpolate_poses(gt.timestamps_ns.astype(float), gt.T_world_body, stamps.astype(float))
    w, h = cam.width, cam.height
    mask = np.zeros(len(stamps), bool)
    truth_by_t = {}
    for k, t in enumerate(stamps):
        truth = _truth_corners(cam, T_true[k], codes)
        truth_by_t[int(t)] = truth
        mask[k] = any(
            np.all((uv >= EDGE_MARGIN_PX) & (uv <= [w - 1 - EDGE_MARGIN_PX, h - 1 - EDGE_MARGIN_PX]))
            for uv in truth.values()
        )
    return stamps, mask, truth_by_t


def _tracked_error(d, truth: dict) -> float | None:
    """Worst corner error px of a tracked sighting `d`, or None when its identity is wrong: the
    named code is not in front of the camera, or another code's true centre is nearer."""
    centres = {p: uv.mean(axis=0) for p, uv in truth.items()}
    own = centres.get(d.payload)
    c = d.corners_px.mean(axis=0)
    if own is None or any(
        np.linalg.norm(c - o) < np.linalg.norm(c - own) for p, o in centres.items() if p != d.payload
    ):
        return None
    return float(np.max(np.linalg.norm(d.corners_px - truth[d.payload], axis=1)))


def _score_tracked(by_frame: dict, truth_by_t: dict) -> tuple[int, list[float]]:
    """(wrong identities, worst corner error px of each right one) of the tracked sightings."""
    wrong, errs = 0, []
    for t, dets in by_frame.items():
        truth = truth_by_t.get(int(t), {})
        for d in dets:
            if not d.tracked:
                continue
            err = _tracked_error(d, truth)
            if err is None:
                wrong += 1
            else:
                errs.append(err)
    return wrong, errs


def _position_errors(log, traj) -> np.ndarray:
    """(N,) position error (m) of each pose of `traj` against the flight's ground truth."""
    gt = log.groundtruth
    t = np.asarray(traj.timestamps_ns, dtype=np.int64)
    if len(t) == 0:
        return np.zeros(0)
    T_true = interpolate_poses(gt.timestamps_ns.astype(float), gt.T_world_body, t.astype(float))
    T_est = np.asarray(traj.T_world_body, dtype=float).reshape(-1, 4, 4)
    return np.linalg.norm(T_est[:, :3, 3] - T_true[:, :3, 3], axis=1)


def _error_summary(err_m: np.ndarray) -> dict:
    """Position errors (m) summarised in cm: count, RMSE, median, p99, max, how many over 5 cm."""
    if len(err_m) == 0:
        return dict(n=0)
    return dict(
        n=len(err_m),
        rmse_cm=100 * float(np.sqrt(np.mean(err_m**2))),
        median_cm=100 * float(np.median(err_m)),
        p99_cm=100 * float(np.percentile(err_m, 99)),
        max_cm=100 * float(np.max(err_m)),
        over_5cm=int(np.sum(err_m > 0.05)),
    )


def _in_blackout(t_ns: int, blackouts) -> bool:
    """True inside one of the simulator's floor-camera blackouts [(start_ns, end_ns, kind)]:
    every floor code in view made unreadable on purpose (fusion.sim.render._apply_blackout:
    shadow, contrast below the noise; glare, clipped white; torn, the top half with two of the
    three finders replaced by floor), not merely blurred."""
    return any(a <= t_ns <= b for a, b, _ in blackouts)


def _is_restamped(d, rep) -> bool:
    """A pass sighting decoded with re-stamped finders (not tracked from a prediction)."""
    return (d.timestamp_ns, d.payload) in rep.restamped_keys


def loss_reasons(flight: Path, out_dir: Path, workers: int | None = None) -> dict:
    """Floor frames, posed before / after the track pass, and the unposed ones after it counted
    by reason (module docstring, `--reasons`); no fusion."""
    log = read_flight(flight)
    cfg = RunConfig(progress=False, workers=workers)
    det = read_cache(out_dir / CACHE_NAME) if (out_dir / CACHE_NAME).is_file() else None
    if det is None:
        det = detect_flight(log, workers=workers or 1)
        out_dir.mkdir(parents=True, exist_ok=True)
        write_cache(det, out_dir / CACHE_NAME, flight_fingerprint(log, det.backend))  # for the next run
    det = without_tracked(det)
    loc = localize_stage(log, det, cfg)
    pnp = str(Estimator.PNP)
    first = set(int(t) for t in loc.trajectories[pnp].timestamps_ns)
    cpu0 = time.process_time()
    tracked, rep = track_flight(log, det, loc.trajectories[pnp], cfg.corner_sigma_px, workers or 1)
    cpu_s = time.process_time() - cpu0  # this process only: with --workers 1, the whole pass
    final_traj = localize_stage(log, tracked, cfg).trajectories[pnp]
    final = set(int(t) for t in final_traj.timestamps_ns)
    pnp_err_m = _position_errors(log, final_traj)
    passed = {int(t) for t, ds in tracked.by_frame("cam0").items() if any(d.tracked for d in ds)}
    with_pass = np.array([int(t) in passed for t in final_traj.timestamps_ns], bool)
    stamps, mask, truth_by_t = _floor_frames(log)
    blackouts = log.blackouts or []
    decoded = {t for t, ds in det.by_frame("cam0").items() if ds}
    reasons: dict[str, int] = {}
    for t, is_floor in zip(stamps, mask):
        t = int(t)
        if not is_floor or t in final:
            continue
        if _in_blackout(t, blackouts):
            why = "blackout"
        elif t in decoded and t not in first:
            why = "decoded_no_pnp"
        else:
            why = rep.frame_outcomes.get(t, "not_looked_at")
            if why == "posed":  # the pass's pose, refused by the per-frame stage's checks
                why = "posed_in_pass_refused_later"
        reasons[why] = reasons.get(why, 0) + 1
    wrong, errs = _score_tracked(tracked.by_frame("cam0"), truth_by_t)
    floor_t = [int(t) for t in stamps[mask]]
    outside = [t for t in floor_t if not _in_blackout(t, blackouts)]
    posed_final = sum(t in final for t in floor_t)
    posed_outside = sum(t in final for t in outside)
    # re-stamped sightings (fusion.qr.restamp): corners_raw_px is their fitted quadrilateral, not a
    # prediction; scored on their own
    restamped = {
        t: [d for d in ds if d.tracked and _is_restamped(d, rep)]
        for t, ds in tracked.by_frame("cam0").items()
    }
    wrong_restamped, _ = _score_tracked(restamped, truth_by_t)
    return dict(
        floor_frames=int(mask.sum()),
        wrong_ids=wrong,
        tracked_err_px_median_max=[float(np.median(errs)), float(np.max(errs))] if errs else [],
        posed_first=sum(int(t) in first for t in stamps[mask]),
        posed_final=posed_final,
        in_blackouts=len(floor_t) - len(outside),
        posed_share=posed_final / max(len(floor_t), 1),
        posed_share_outside_blackouts=posed_outside / max(len(outside), 1),
        tracked=rep.stats.tracked,
        restamped=rep.restamped,
        frames_with_restamped=rep.frames_with_restamped,
        frames_restamp_tried=rep.frames_restamp_tried,
        restamp_poses=rep.restamp_poses,
        wrong_ids_restamped=wrong_restamped,
        tracker={k: int(v) for k, v in vars(rep.stats).items()},
        pnp_rmse_cm=100 * float(np.sqrt(np.mean(pnp_err_m**2))) if len(pnp_err_m) else float("nan"),
        pnp_over_5cm=int(np.sum(pnp_err_m > 0.05)),
        pnp_with_pass_sightings=_error_summary(pnp_err_m[with_pass]),
        reasons=dict(sorted(reasons.items(), key=lambda kv: -kv[1])),
        seconds=rep.seconds,
        restamp_seconds=rep.restamp_seconds,
        cpu_s=cpu_s,
        cpu_ms_per_floor_frame=1000 * cpu_s / max(len(stamps), 1),
    )


def occluder_polygon(quad: np.ndarray, fraction: float, kind: str, rng) -> np.ndarray | None:
    """Image polygon (n, 2) hiding `fraction` of the symbol with image corners `quad` (4, 2):
    "strip" from a random side (the simulator's), "square" of that area at a random place inside
    the symbol; None for "none"."""
    if kind == "none":
        return None
    if kind == "strip":
        return occlusion_polygon(quad, fraction, int(rng.integers(0, 4)))
    a = float(np.sqrt(fraction))
    u0, v0 = rng.uniform(0.0, 1.0 - a, 2)
    unit = np.array([[u0, v0], [u0 + a, v0], [u0 + a, v0 + a], [u0, v0 + a]], np.float32)
    H = cv2.getPerspectiveTransform(
        np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32), np.asarray(quad, np.float32)
    )
    return cv2.perspectiveTransform(unit[None], H)[0]


def _occlude(img: np.ndarray, quads, fraction: float, kind: str, rng) -> np.ndarray:
    out = img.astype(np.float32)
    for quad in quads:
        poly = occluder_polygon(quad, fraction, kind, rng)
        if poly is None:
            continue
        mask = np.zeros(img.shape, np.uint8)
        cv2.fillConvexPoly(mask, np.round(poly * 16).astype(np.int32), 255, cv2.LINE_AA, 4)
        a = mask.astype(np.float32) / 255.0
        out = out * (1.0 - a) + a * OCCLUDER_DN
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def occlude_flight(src: Path, dst: Path, fraction: float, kind: str) -> None:
    """DST: a copy of flight SRC with its floor codes occluded in every floor image (module
    docstring, `--occlude`)."""
    shutil.copytree(src, dst, dirs_exist_ok=False)
    log = read_flight(dst)
    stamps, _, truth = _floor_frames(log)
    rng = np.random.default_rng(OCCLUDE_SEED)
    for k, t in enumerate(stamps):
        quads = [uv for uv in truth[int(t)].values()]
        img = log.floor.load_image(k)
        path = dst / "mav0" / "cam0" / "data" / f"{int(t)}.png"
        cv2.imwrite(str(path), _occlude(img, quads, fraction, kind, rng))


def occlusion_decode_rates(flight: Path, fraction: float, every: int = 10) -> dict:
    """{kind: share of floor codes in view (every `every`-th frame) that zxing decodes} with each
    occluder kind drawn on the same frames."""
    log = read_flight(flight)
    stamps, mask, truth = _floor_frames(log)
    rng = np.random.default_rng(OCCLUDE_SEED)
    out = {}
    for kind in ("none", "square", "strip"):
        seen = decoded = 0
        for k in range(0, len(stamps), every):
            if not mask[k]:
                continue
            w, h = log.floor.camera.width, log.floor.camera.height
            codes = {
                p: uv
                for p, uv in truth[int(stamps[k])].items()
                if np.all((uv >= EDGE_MARGIN_PX) & (uv <= [w - 1 - EDGE_MARGIN_PX, h - 1 - EDGE_MARGIN_PX]))
            }
            img = _occlude(log.floor.load_image(k), list(codes.values()), fraction, kind, rng)
            got = {d.payload for d in detect_image(img, "zxing")}
            seen += len(codes)
            decoded += len(got & set(codes))
        out[kind] = decoded / max(seen, 1)
    return out


def evaluate_flight(flight: Path, out_dir: Path, track: bool, rerun: bool = True) -> dict:
    """Run the pipeline (unless `rerun` is False and OUT holds a finished run) and score it."""
    if rerun or not (out_dir / "metrics.json").is_file():
        run(flight, out_dir, RunConfig(progress=False, force=True, track=track))
    metrics = json.loads((out_dir / "metrics.json").read_text())
    log = read_flight(flight)
    cam = log.floor.camera
    codes = [c for c in build_scenario("default").codes() if c.is_floor]
    gt = log.groundtruth
    stamps = np.asarray(log.floor.timestamps_ns, dtype=np.int64)
    T_true = interpolate_poses(gt.timestamps_ns.astype(float), gt.T_world_body, stamps.astype(float))
    det = read_cache(out_dir / CACHE_NAME)
    assert det is not None
    by_frame = det.by_frame("cam0")
    pnp_t = set(int(t) for t in read_tum(out_dir / "trajectory_pnp.tum").timestamps_ns)
    w, h = cam.width, cam.height
    out = dict(floor_frames=0, posed=0, decoded=0, tracked=0, wrong_ids=0, tracked_err_px=[])
    out.update(floor_frames_outside_blackouts=0, posed_outside_blackouts=0)
    blackouts = log.blackouts or []
    for k, t in enumerate(stamps):
        truth = _truth_corners(cam, T_true[k], codes)
        in_view = [
            p
            for p, uv in truth.items()
            if np.all((uv >= EDGE_MARGIN_PX) & (uv <= [w - 1 - EDGE_MARGIN_PX, h - 1 - EDGE_MARGIN_PX]))
        ]
        if in_view:
            out["floor_frames"] += 1
            out["posed"] += int(t) in pnp_t
            if not _in_blackout(int(t), blackouts):
                out["floor_frames_outside_blackouts"] += 1
                out["posed_outside_blackouts"] += int(t) in pnp_t
        for d in by_frame.get(int(t), []):
            out["tracked" if d.tracked else "decoded"] += 1
            if not d.tracked:
                continue
            err = _tracked_error(d, truth)
            if err is None:
                out["wrong_ids"] += 1
            else:
                out["tracked_err_px"].append(err)
    traj = metrics.get("trajectories", {})
    out["ate_pnp_cm"] = 100 * traj.get("pnp", {}).get("ate_rmse_m", float("nan"))
    out["ate_smoother_cm"] = 100 * traj.get("smoother", {}).get("ate_rmse_m", float("nan"))
    tracking = (metrics.get("detection") or {}).get("tracking", {})
    out["track_s"] = tracking.get("seconds", 0.0)
    out["frames_tried"] = tracking.get("frames_tried", 0)
    out["s_per_frame_tried"] = tracking.get("seconds_per_frame_tried", 0.0)
    out["gated"] = tracking.get("tracker_gated", 0)
    out["restamped"] = tracking.get("restamped", 0)  # of `tracked`: decoded with re-stamped finders
    out["restamp_s"] = tracking.get("restamp_seconds", 0.0)
    return out


SIM_KINDS = ("blur20", "strip-L", "strip-H")
SIM_DURATION_S = 40.0


def make_flight(kind: str, seed: int, root: Path) -> Path:
    """ROOT/KIND_sSEED: SIM_DURATION_S of the default scenario with KIND's camera effects (module
    docstring), simulated unless it is already there."""
    from fusion.sim.scenarios import CameraOptions
    from fusion.sim.simulate import simulate

    path = root / f"{kind}_s{seed}"
    if (path / "world.yaml").exists():
        return path
    scenario = build_scenario("default")
    if kind == "blur20":
        options = CameraOptions(exposure_s=0.02)
    else:
        options = CameraOptions(occlusion_fraction=0.1)
        scenario.floor_ecc = kind.split("-")[1]
    simulate(
        path,
        scenario,
        duration_s=SIM_DURATION_S,
        seed=seed,
        overwrite=True,
        progress=False,
        workers=1,
        camera_options=options,
    )
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flights", type=Path, nargs="*")
    ap.add_argument("--simulate", choices=SIM_KINDS, default=None, help="make and use KIND_sSEED flights")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_track_pipeline"))
    ap.add_argument("--modes", nargs="+", default=["no-track", "track"], choices=["no-track", "track"])
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--reuse", action="store_true", help="score finished runs in OUT without running")
    ap.add_argument("--reasons", action="store_true", help="no fusion: why floor frames have no pose")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument(
        "--no-fit",
        action="store_true",
        help="the track pass without its IMU-fit predictions (predict.USE_FIT; a module switch: --workers 1)",
    )
    ap.add_argument("--occlude", action="store_true", help="FLIGHTS = SRC DST: make DST (module docstring)")
    ap.add_argument("--occluder", choices=["strip", "square", "none"], default="square")
    ap.add_argument("--fraction", type=float, default=0.1)
    ap.add_argument("--decode-rates", action="store_true", help="zxing's decode share per occluder kind")
    args = ap.parse_args(argv)
    if args.no_fit:
        import fusion.qr.predict

        fusion.qr.predict.USE_FIT = False
    if args.simulate is not None:
        args.flights += [make_flight(args.simulate, seed, args.out / "flights") for seed in args.seeds]
    if not args.flights:
        ap.error("give flights or --simulate")
    if args.occlude:
        occlude_flight(args.flights[0], args.flights[1], args.fraction, args.occluder)
        return 0
    if args.decode_rates:
        for flight in args.flights:
            print(flight.name, json.dumps(occlusion_decode_rates(flight, args.fraction)), flush=True)
        return 0
    if args.reasons:
        for flight in args.flights:
            out = args.out / f"{flight.name}-{args.modes[0]}"
            r = loss_reasons(flight, out, args.workers)
            (out / "reasons.json").write_text(json.dumps(r, indent=1))
            print(flight.name, json.dumps(r), flush=True)
        return 0
    rows = []
    print(
        "| flight | mode | floor frames | with a PnP pose | outside blackouts | decoded | tracked "
        "| wrong ids "
        "| tracked corner err px median / max | ATE pnp cm | ATE smoother cm "
        "| track pass s (s / frame tried) |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for flight in args.flights:
        for mode in args.modes:
            # the first mode's detections (its cache is the flight's) spare the second its detection
            first = args.out / f"{flight.name}-{args.modes[0]}" / CACHE_NAME
            out = args.out / f"{flight.name}-{mode}"
            if mode != args.modes[0] and first.is_file() and not (out / CACHE_NAME).exists():
                out.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(first, out / CACHE_NAME)
            r = evaluate_flight(flight, args.out / f"{flight.name}-{mode}", mode == "track", not args.reuse)
            r.update(flight=flight.name, mode=mode)
            rows.append(r)
            e = np.array(r["tracked_err_px"]) if r["tracked_err_px"] else np.array([np.nan])
            print(
                f"| {flight.name} | {mode} | {r['floor_frames']} | {r['posed']} "
                f"({100 * r['posed'] / max(r['floor_frames'], 1):.1f} %) "
                f"| {r['posed_outside_blackouts']} / {r['floor_frames_outside_blackouts']} "
                f"({100 * r['posed_outside_blackouts'] / max(r['floor_frames_outside_blackouts'], 1):.1f} %) "
                f"| {r['decoded']} | {r['tracked']} "
                f"| {r['wrong_ids']} | {np.median(e):.2f} / {np.max(e):.2f} | {r['ate_pnp_cm']:.2f} "
                f"| {r['ate_smoother_cm']:.2f} | {r['track_s']:.1f} ({r['s_per_frame_tried']:.3f}) |",
                flush=True,
            )
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
