"""Benchmark of the camera-IMU time-offset estimation (fusion.estimate.timeoffset), issue 11 item 4.

Targets:
  1. simulated offsets from -30 to +30 ms on both cameras recovered within 1 ms;
  2. fused like-for-like RMSE (the smoother's ATE on the PnP frames) with an unknown 20 ms offset
     on both cameras within 1.2x of the run with no offset;
  3. load maps unaffected (same loads mapped, MAE within 1 mm of the no-offset run).

Part A (back end, fast): synthetic flights as in tests/test_timeoffset.py (random survey, 200 Hz
IMU with noise and biases, PnP-like poses 2 mm / 0.05 deg, load sightings 2/2/4 mm), offsets
(cam0, cam1) swept over -30..+30 ms, `resolve_time_offsets` on each.
Part B (end to end): one rendered flight of the default scenario (`fusion simulate`), the
20 ms case rendered with `simulate(time_offset_ms=...)`, the sweep as copies of the zero-offset
log with the cameras' data.csv re-stamped (t_cam = t_true - offset, same images); `fusion run`
on each (no incremental smoother, to keep a shared 2-core machine usable).

    PYTHONPATH=$PWD python3 scripts/bench_time_offset.py [--quick] [--duration 15] [--out DIR]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from fusion.estimate.timeoffset import resolve_time_offsets  # noqa: E402
from fusion.pipeline import RunConfig, run  # noqa: E402
from fusion.sim.simulate import simulate  # noqa: E402

SWEEP_MS = [(-30, 30), (-20, -10), (-10, 20), (0, 0), (10, -30), (20, -20), (30, 10)]
TOL_MS = 1.0
RMSE_RATIO = 1.2
LOAD_MAE_TOL_M = 0.001


def part_a(duration_s: float, seeds: list[int]) -> list[dict]:
    from test_timeoffset import _flight, _log

    rows = []
    for seed in seeds:
        for c0, c1 in SWEEP_MS:
            fl = _flight(duration_s, seed, c0 * 1e-3, c1 * 1e-3)
            t = time.perf_counter()
            off = resolve_time_offsets(_log(fl), fl["raw"], fl["obs"])
            rows.append(
                dict(
                    seed=seed,
                    true_ms=(c0, c1),
                    est_ms=tuple(off.cameras[c].offset_s * 1e3 for c in ("cam0", "cam1")),
                    sigma_ms=tuple((off.cameras[c].sigma_s or float("nan")) * 1e3 for c in ("cam0", "cam1")),
                    time_s=time.perf_counter() - t,
                )
            )
            r = rows[-1]
            print(
                f"A seed {seed} true {c0:+4d}/{c1:+4d} ms -> "
                f"{r['est_ms'][0]:+8.3f} ± {r['sigma_ms'][0]:.3f} / "
                f"{r['est_ms'][1]:+8.3f} ± {r['sigma_ms'][1]:.3f}"
                f"  ({r['time_s']:.1f} s)",
                flush=True,
            )
    return rows


def restamp(src: Path, dst: Path, offsets_ms: tuple[float, float]) -> Path:
    """A copy of EuRoC log `src` (images hard-linked) whose cameras' stamps are true - offset."""
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(src, dst, copy_function=os.link)
    for cam, ms in zip(("cam0", "cam1"), offsets_ms):
        csv = dst / "mav0" / cam / "data.csv"
        lines = csv.read_text().splitlines()
        shift = int(round(ms * 1e6))
        rows = [f"{int(t) - shift},{f}" for t, f in (line.split(",") for line in lines[1:])]
        csv.unlink()  # a hard link: do not write through to the source
        csv.write_text("\n".join([lines[0], *rows]) + "\n")
    return dst


def run_case(log_dir: Path, out: Path) -> dict:
    t = time.perf_counter()
    res = run(log_dir, out, RunConfig(workers=2, progress=False, force=True, incremental=False))
    m = res.metrics or {}
    tr = m.get("trajectories", {})
    lm = m.get("load_maps", {})
    return dict(
        offsets=m.get("time_offsets", {}),
        ate_ref_mm={
            k: 1e3 * tr[k]["ate_rmse_on_reference_frames_m"] for k in ("pnp", "smoother", "ekf") if k in tr
        },
        ate_mm={k: 1e3 * tr[k]["ate_rmse_m"] for k in ("pnp", "smoother", "ekf") if k in tr},
        loads={k: (len(res.load_maps[k].loads), lm.get(k, {}).get("mae_xyz_m")) for k in res.load_maps},
        time_s=time.perf_counter() - t,
    )


def part_b(work: Path, duration_s: float, start_s: float) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    base = work / "log0"
    if not (base / "world.yaml").exists():
        simulate(
            base, "default", duration_s=duration_s, start_s=start_s, seed=0, overwrite=True, progress=False
        )
    sim20 = work / "log20"
    if not (sim20 / "world.yaml").exists():
        simulate(
            sim20,
            "default",
            duration_s=duration_s,
            start_s=start_s,
            seed=0,
            overwrite=True,
            progress=False,
            time_offset_ms=20.0,
        )
    cases = {"0/0": run_case(base, work / "out0"), "20/20 (simulated)": run_case(sim20, work / "out20")}
    for c0, c1 in SWEEP_MS:
        if (c0, c1) == (0, 0):
            continue
        d = restamp(base, work / "logx", (c0, c1))
        cases[f"{c0}/{c1}"] = run_case(d, work / f"out_{c0}_{c1}")
    for name, c in cases.items():
        o = c["offsets"]
        print(
            f"B {name:>18}: "
            + ", ".join(
                f"{k} {v['offset_ms']:+.3f} ± {v['sigma_ms'] or float('nan'):.3f} ms" for k, v in o.items()
            )
            + f"; smoother ATE@pnp {c['ate_ref_mm'].get('smoother', float('nan')):.3f} mm; loads "
            + ", ".join(f"{k} {n}" for k, (n, _) in c["loads"].items())
            + f" ({c['time_s']:.0f} s)",
            flush=True,
        )
    return cases


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="part A only, one seed")
    ap.add_argument("--duration", type=float, default=15.0, help="rendered flight length, s")
    ap.add_argument("--start", type=float, default=5.0, help="skip the scenario's first S seconds")
    ap.add_argument("--out", type=Path, default=Path("/tmp/bench_time_offset"))
    args = ap.parse_args(argv)
    print(f"# bench_time_offset {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC")
    a = part_a(20.0, [1] if args.quick else [1, 2])
    err = np.array([[abs(e - t) for e, t in zip(r["est_ms"], r["true_ms"])] for r in a])
    print(f"A: max |error| {err.max():.3f} ms, mean {err.mean():.3f} ms over {err.size} estimates")
    print(f"A: target within {TOL_MS} ms: {'met' if err.max() <= TOL_MS else 'MISSED'}")
    if args.quick:
        return 0
    b = part_b(args.out, args.duration, args.start)
    errs = []
    for name, c in b.items():
        if name.startswith("20/20"):
            true = (20.0, 20.0)
        else:
            true = tuple(float(v) for v in name.split("/"))
        errs += [abs(c["offsets"][k]["offset_ms"] - t) for k, t in zip(("cam0", "cam1"), true)]
    verdict = "met" if max(errs) <= TOL_MS else "MISSED"
    print(f"B: max |error| {max(errs):.3f} ms over {len(errs)} estimates: {verdict}")
    for est in ("smoother", "ekf"):
        ratio = b["20/20 (simulated)"]["ate_ref_mm"][est] / b["0/0"]["ate_ref_mm"][est]
        verdict = "met" if ratio <= RMSE_RATIO else "MISSED"
        print(f"B: {est} ATE@pnp ratio, unknown 20 ms / none: {ratio:.3f} ({verdict})")
    ref = b["0/0"]["loads"]
    ok = True
    for c in b.values():
        for k, (n, mae) in c["loads"].items():
            n0, mae0 = ref.get(k, (None, None))
            close = mae is None or mae0 is None or max(abs(np.subtract(mae, mae0))) <= LOAD_MAE_TOL_M
            ok &= bool(n == n0 and close)
    verdict = "met" if ok else "MISSED"
    print(f"B: load maps unaffected (same count, MAE within {LOAD_MAE_TOL_M * 1e3:.0f} mm): {verdict}")
    (args.out / "bench.json").write_text(json.dumps({"a": a, "b": b}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
