"""The floor camera's mount check over floor codes laid off their payloads (trust): flights with
no mount error whose floor codes are misplaced (`fusion simulate --placement-error-m / -deg`,
world.yaml stating the same sigma), each run by `fusion run`; per flight the check's estimate w,
its sigma, |w| / sigma and whether it warned (`extrinsic_rotation_bias`).  A mount check whose
sigma is honest has a mean square of |w| / sigma near 1 per axis and warns on no flight (the
truth is 0).  The check weighs its poses with their placement share inflated
(pipeline.placement_inflated); run on the code before it for the poses taken as independent.

    python3 scripts/bench_mount_placement.py WORK [--seeds 130 131 ...] [--duration 10]

Flights are simulated once into WORK/flights/NAME and reused; runs go to WORK/runs/NAME.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

PLACEMENTS = ((0.02, 2.0), (0.01, 1.0))
"""(m, deg) of the floor codes' placement errors, each flown on every seed."""


def fusion(*args: str) -> None:
    done = subprocess.run([sys.executable, "-m", "fusion.cli", *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"fusion {' '.join(args)} failed: {done.stderr.strip()[-400:]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("work", type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[130, 131, 132, 133])
    ap.add_argument("--duration", type=float, default=10.0)
    args = ap.parse_args()
    rows, zs = [], []
    for m, deg in PLACEMENTS:
        for seed in args.seeds:
            name = f"place{m * 100:g}cm_{deg:g}deg_s{seed}"
            log, out = args.work / "flights" / name, args.work / "runs" / name
            if not (log / "manifest.json").exists():
                placement = ("--placement-error-m", str(m), "--placement-error-deg", str(deg))
                timing = ("--seed", str(seed), "--duration", str(args.duration), "--fps", "60")
                fusion("simulate", str(log), "--force", "-q", *timing, *placement)
            fusion("run", str(log), "--out", str(out), "--force", "-q")
            metrics = json.loads((out / "metrics.json").read_text())
            e = metrics.get("extrinsics") or {}
            if e.get("source") != "estimated":
                rows.append(f"| {name} | not estimated: {e.get('note', '')} | | | |")
                continue
            w, s = np.array(e["rotvec_deg"]), np.array(e["sigma_deg"])
            zs.append(w / s)
            warned = [x for x in metrics.get("warnings", []) if x.get("name") == "extrinsic_rotation_bias"]
            rows.append(
                f"| {name} | {' / '.join(f'{v:+.3f}' for v in w)} | {' / '.join(f'{v:.3f}' for v in s)} | "
                f"{' / '.join(f'{v:+.1f}' for v in w / s)} | {'yes' if warned else 'no'} |"
            )
            print(rows[-1], flush=True)
    print("\n| flight | w x / y / z (deg) | sigma (deg) | w / sigma | warned |")
    print("|---|---|---|---|---|")
    print("\n".join(rows))
    if zs:
        each = " / ".join(f"{v:.2f}" for v in np.mean(np.square(zs), axis=0))
        print(f"\nmean square of w / sigma (x / y / z, {len(zs)} flights): {each}")


if __name__ == "__main__":
    main()
