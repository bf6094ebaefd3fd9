"""Calibration errors that the noise scaling absorbed in silence (thirty-second session's audit):
a variance factor far beyond any camera's noise is a named warning, and on the floor camera a
degraded health for every fused estimate (pipeline.misfit_warnings)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from fusion.cli import main
from fusion.fileio import dump_yaml, load_yaml
from fusion.pipeline import (
    FLOOR_CORNERS_MISFIT,
    FLOOR_POSES_MISFIT,
    LOAD_MISFIT,
    MISFIT_SCALE,
    misfit_warnings,
)

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"


def _scales(pnp=1.6, cam0=1.0, cam1=0.3) -> dict:
    return {
        "pnp": {"scale": pnp, "dof": 2870},
        "smoother": {"cameras": {"cam0": {"scale": cam0}, "cam1": {"scale": cam1}}},
    }


def test_misfit_warnings_name_each_factor_beyond_the_threshold():
    """The largest factors of 78 correctly configured flights (PnP 3.5, poses 1.2, loads 2.3)
    say nothing; the audit's calibration errors (8,231 on the floor corners for a code 3 %
    larger than stated, 25 on the poses for a time offset fixed 30 ms wrong, 1,390 on the loads
    for a load code 10 % off) each give their own warning, naming what to check."""
    assert misfit_warnings(_scales(3.5, 1.2, 2.3)) == []
    assert misfit_warnings({}) == [] and misfit_warnings({"pnp": {"scale": None}}) == []
    names = [w.name for w in misfit_warnings(_scales(pnp=8231.0))]
    assert names == [FLOOR_CORNERS_MISFIT]
    w = misfit_warnings(_scales(cam0=25.0))
    assert [x.name for x in w] == [FLOOR_POSES_MISFIT] and "time offset" in w[0].message
    w = misfit_warnings(_scales(cam1=1390.0))
    assert [x.name for x in w] == [LOAD_MISFIT] and "load_qr side_m" in w[0].message and w[0].count == 1
    assert len(misfit_warnings(_scales(MISFIT_SCALE * 1.01, MISFIT_SCALE * 1.01, MISFIT_SCALE * 1.01))) == 3
    assert misfit_warnings(_scales(MISFIT_SCALE, MISFIT_SCALE, MISFIT_SCALE)) == []


def _run(log_dir: Path, out: Path, *extra: str) -> tuple[int, dict]:
    args = ["run", str(log_dir), "--out", str(out), "--quiet", "--workers", "1", "--no-incremental"]
    rc = main([*args, *extra])
    return rc, json.loads((out / "metrics.json").read_text())


def test_a_floor_code_size_three_percent_off_is_said_and_not_trusted(tmp_path):
    """world.yaml's floor side_m 3 % too large (codes printed "fit to page"): the audit's flight
    read poses 4.7 cm off with every health ok and `--strict` exit 0, PnP's corner factor
    8,231 applied as if it were noise."""
    log_dir = tmp_path / "log"
    shutil.copytree(SAMPLE, log_dir)
    world = load_yaml(log_dir / "world.yaml")
    world["floor_qr"]["side_m"] = 0.206
    dump_yaml(world, log_dir / "world.yaml")
    rc, m = _run(log_dir, tmp_path / "out", "--strict")
    assert rc == 3  # not trusted
    assert FLOOR_CORNERS_MISFIT in [w["name"] for w in m["warnings"]]
    for name, h in m["health"].items():
        assert h["status"] != "ok" and "misfit" in h["reason"], name
    rc, m = _run(SAMPLE, tmp_path / "nominal")
    assert rc == 0 and not [w for w in m.get("warnings", []) if "misfit" in w["name"]]
    assert all(h["status"] == "ok" for h in m["health"].values())
