"""Write the committed sample flight `data/sample-flight/` (used by other tests; keep the path).

A 5 s slice (t = 6 .. 11 s) of the "default" scenario: floor + front camera at 10 fps, 640x480,
IMU 200 Hz, velocity 30 Hz, ground truth, loads, and the 0.5 s shadow blackout at t = 9.0 s.
Low sensor noise (0.4 DN) and PNG level 9 keep it small.

    /work/venv/bin/python scripts/make_sample_flight.py [--out data/sample-flight]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fusion.sim.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "data" / "sample-flight")
    args = ap.parse_args()
    r = simulate(
        args.out,
        "default",
        duration_s=5.0,
        start_s=6.0,
        seed=0,
        overwrite=True,
        camera_rate_hz=10.0,
        noise_sigma_dn=0.4,
        png_compression=9,
        check_readable=True,
    )
    size = sum(p.stat().st_size for p in args.out.rglob("*") if p.is_file())
    print(
        f"{r.root}: {r.n_frames} frames per camera, {r.n_imu} IMU samples, blackouts "
        f"{r.blackouts}, readable floor fraction {r.readable_floor_fraction:.2f}, "
        f"{size / 1e6:.1f} MB"
    )


if __name__ == "__main__":
    main()
