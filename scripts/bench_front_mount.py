"""Mount errors of either camera, end to end: `fusion simulate` flights whose floor (cam0) or
front (cam1) camera is rendered with a turned mount while sensor.yaml keeps the nominal one,
each run by `fusion run` without and with --calibrate-extrinsics; per run the floor and front
mount estimates, the pose NEES (6-dof, ideal 6) of PnP / smoother / EKF, the load maps' 3-dof
NEES and the health.  The floor check alone cannot see a floor roll the IMU reads as a bias, nor
any front error (BENCHMARKS.md, twenty-third session).

    PYTHONPATH=$PWD python3 scripts/bench_front_mount.py --dir /tmp/front_mount [--only NAME ...]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from fusion.cli import main as fusion

# name: (the simulator's mount errors {camera: (rx, ry, rz) deg}, extra simulate arguments)
FLIGHTS = {
    "floor_roll": ({"cam0": (0.5, 0.0, 0.0)}, []),
    "front_roll": ({"cam1": (0.5, 0.0, 0.0)}, []),
    "front_pitch_yaw": ({"cam1": (0.0, 0.5, 0.3)}, []),
    "floor_all": ({"cam0": (0.5, -0.3, 0.2)}, []),
    "floor_all_offset6": ({"cam0": (0.5, -0.3, 0.2)}, ["--time-offset-ms", "6"]),
    "front_roll_small": ({"cam1": (0.05, 0.0, 0.0)}, []),  # below the floor camera's 0.1 deg floor
}
ESTIMATORS = ("pnp", "smoother", "incremental", "ekf")


def _simulate(path: Path, errors: dict, extra: list[str]) -> None:
    if path.exists():
        return
    if list(errors) == ["cam0"]:
        rx, ry, rz = errors["cam0"]
        args = ["--extrinsic-error-deg", str(rx), str(ry), str(rz)]
        assert fusion(["simulate", str(path), "--duration", "15", "--seed", "49", "-q", *args, *extra]) == 0
    else:  # the CLI turns cam0 only: the library takes any camera
        from fusion.sim.simulate import simulate

        simulate(path, duration_s=15, seed=49, progress=False, extrinsic_error_deg=errors)


def _row(name: str, out: Path) -> str:
    m = json.loads((out / "metrics.json").read_text())
    t, lm = m["trajectories"], m["load_maps"]

    def mount(key: str) -> str:
        e = m.get(key) or {}
        if e.get("rotvec_deg") is None:
            return "-"
        w = "/".join(f"{v:+.3f}" for v in e["rotvec_deg"])
        s = max(e["sigma_deg"])
        used = "applied" if e["applied"] else ("significant" if e["significant_axes"] else "-")
        return f"{w} (σ ≤ {s:.3f}; {used} {''.join(e['significant_axes'])})"

    pose = " / ".join(
        f"{t[k]['nees_pose_6dof']['nees_mean']:.1f}" if k in t and t[k].get("nees_pose_6dof") else "-"
        for k in ESTIMATORS
    )
    loads = " / ".join(
        f"{lm[k]['nees_3dof']['nees_mean']:.1f}" if k in lm and lm[k].get("nees_3dof") else "-"
        for k in ESTIMATORS
    )
    health = " / ".join(str((m.get("health") or {}).get(k, {}).get("status", "-")) for k in ESTIMATORS[1:])
    return f"| {name} | {mount('extrinsics')} | {mount('front_extrinsics')} | {pose} | {loads} | {health} |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", type=Path, required=True)
    ap.add_argument("--only", nargs="*", default=None)
    args = ap.parse_args()
    args.dir.mkdir(parents=True, exist_ok=True)
    print(
        "| run | floor mount (deg) | front mount (deg) | pose NEES PnP / smoother / incremental / EKF "
        "| load NEES | health smoother / incremental / EKF |"
    )
    print("|---|---|---|---|---|---|")
    for name, (errors, extra) in FLIGHTS.items():
        if args.only and name not in args.only:
            continue
        log = args.dir / name
        _simulate(log, errors, extra)
        for tag, flags in (("check", []), ("calibrated", ["--calibrate-extrinsics"])):
            out = args.dir / f"out_{name}_{tag}"
            assert (
                fusion(["run", str(log), "--out", str(out), "--workers", "1", "-q", "--force", *flags]) == 0
            )
            print(_row(f"{name}, {tag}", out), flush=True)


if __name__ == "__main__":
    main()
