"""Smoke tests: every `fusion` command end to end on the committed sample flight (as evo's
CLI smoke tests do), and the run-level bad inputs (no front camera, no IMU, no ground truth,
an existing output folder)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from fusion.cli import main
from fusion.log.files import read_loads_csv, read_tum

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"
ESTIMATORS = ("paper", "pnp", "smoother", "incremental", "ekf")


@pytest.fixture(scope="module")
def run_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "out"
    assert main(["run", str(SAMPLE), "--out", str(out), "--quiet", "--workers", "1"]) == 0
    return out


def test_run_writes_every_output(run_out):
    for name in ESTIMATORS:
        traj = read_tum(run_out / f"trajectory_{name}.tum")
        assert len(traj) > 0
        loads = read_loads_csv(run_out / f"loads_{name}.csv")
        assert len(loads.loads) > 0
    for name in ("pnp", "smoother", "incremental", "ekf"):
        assert (run_out / f"sigmas_{name}.csv").exists()
    metrics = json.loads((run_out / "metrics.json").read_text())
    assert metrics["has_groundtruth"]
    fused = metrics["trajectories"]["smoother"]
    raw = metrics["trajectories"]["pnp"]
    assert fused["ate_rmse_m"] < raw["ate_rmse_m"]
    # evo's -a beside the unaligned ATE (a rigid fit can only lower it)
    assert 0 < fused["ate_aligned"]["ate_rmse_m"] <= fused["ate_rmse_m"]
    report = (run_out / "report.md").read_text()
    assert report.startswith("# fusion report")
    row = next(
        r
        for r in report.split("### Absolute and relative errors")[1].splitlines()
        if r.startswith("| smoother")
    )
    assert row.split("|")[5].strip() not in ("", "–")  # the SE(3)-aligned column
    for png in ("trajectories.png", "position_errors.png", "error_boxplots.png", "load_map.png"):
        assert (run_out / png).stat().st_size > 10_000
    assert not list(run_out.glob("*.part")) and not list(run_out.glob(".*"))


def test_existing_output_is_refused_then_forced_with_cache(run_out, capsys):
    assert main(["run", str(SAMPLE), "--out", str(run_out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "use --force" in err[0]
    assert main(["detect", str(SAMPLE), "--out", str(run_out), "--quiet", "--force"]) == 0
    from fusion.pipeline import RunConfig, run

    again = run(SAMPLE, run_out, RunConfig(progress=False, force=True), until="detect")
    assert again.detection_stats["from_cache"]


@pytest.mark.parametrize(
    "stage, expect, absent",
    [
        ("detect", ["detections.csv"], ["trajectory_pnp.tum"]),
        (
            "localize",
            ["trajectory_paper.tum", "trajectory_pnp.tum", "loads_pnp.csv", "load_observations_pnp.csv"],
            ["trajectory_smoother.tum"],
        ),
        (
            "smooth",
            [
                "trajectory_smoother.tum",
                "trajectory_incremental.tum",
                "trajectory_ekf.tum",
                "sigmas_smoother.csv",
                "loads_smoother.csv",
                "loads_ekf.csv",
            ],
            ["report.md"],
        ),
    ],
)
def test_stage_commands(tmp_path, stage, expect, absent):
    out = tmp_path / stage
    assert main([stage, str(SAMPLE), "--out", str(out), "--quiet", "--workers", "1"]) == 0
    for f in expect:
        assert (out / f).exists(), f
    for f in absent:
        assert not (out / f).exists(), f


def _copy_sample(tmp_path, drop):
    log = tmp_path / "log"
    shutil.copytree(SAMPLE, log)
    for rel in drop:
        p = log / rel
        shutil.rmtree(p) if p.is_dir() else p.unlink()
    return log


def test_run_without_front_camera_imu_or_groundtruth(tmp_path, capsys):
    log = _copy_sample(
        tmp_path, ["mav0/cam1", "mav0/imu0", "mav0/state_groundtruth_estimate0", "loads_groundtruth.csv"]
    )
    out = tmp_path / "out"
    assert main(["run", str(log), "--out", str(out), "--quiet", "--workers", "1"]) == 0
    text = capsys.readouterr().out
    assert "no front camera" in text and "velocity only" in text and "no ground truth" in text
    assert not list(out.glob("loads_*.csv"))
    # metrics.json holds health, failures and warnings even without ground truth
    health = json.loads((out / "metrics.json").read_text())["health"]
    assert health["smoother"]["status"] in ("ok", "degraded", "diverged")
    assert (out / "trajectory_smoother.tum").exists()
    assert "No ground truth" in (out / "report.md").read_text()


def test_run_with_neither_imu_nor_velocity_gives_raw_only(tmp_path, capsys):
    log = _copy_sample(tmp_path, ["mav0/imu0", "mav0/vel0"])
    out = tmp_path / "out"
    assert main(["run", str(log), "--out", str(out), "--quiet", "--workers", "1"]) == 0
    assert "raw per-frame estimates only" in capsys.readouterr().out
    assert (out / "trajectory_pnp.tum").exists() and not (out / "trajectory_smoother.tum").exists()


def test_bad_log_is_one_line_and_exit_1(tmp_path, capsys):
    log = _copy_sample(tmp_path, [])
    imu = log / "mav0" / "imu0" / "data.csv"
    lines = imu.read_text().splitlines()
    lines[5] = lines[5].rsplit(",", 1)[0] + ",nan"
    imu.write_text("\n".join(lines) + "\n")
    assert main(["run", str(log), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "imu0/data.csv:6: NaN" in err[0]
    assert main(["run", str(tmp_path / "nope"), "--out", str(tmp_path / "o2")]) == 1


def test_non_utf8_paths_are_refused_before_any_work(tmp_path, capsys, monkeypatch):
    """A folder name with a Latin-1 byte (0xE9) as LOG, as OUT, or as the current folder of
    relative paths: one line naming the path with the byte escaped, before the pipeline runs
    (it used to run to the end, then the report writer or plotly raised)."""
    latin1 = os.fsdecode(b"vol\xe9")  # what Python makes of the bytes: a lone surrogate
    (tmp_path / latin1).mkdir()
    log = tmp_path / latin1 / "flight"
    log.symlink_to(SAMPLE)
    for args, bad in [
        ([str(log), "--out", str(tmp_path / "out")], f"{tmp_path}/vol\\xe9/flight"),
        ([str(SAMPLE), "--out", str(tmp_path / "sortie" / latin1)], f"{tmp_path}/sortie/vol\\xe9"),
    ]:
        assert main(["detect", *args, "--quiet", "--workers", "1"]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [
            f"fusion: error: {bad}: the path is not valid UTF-8; rename it (e.g. with convmv) or use another"
        ]
    monkeypatch.chdir(tmp_path / latin1)
    assert main(["detect", "flight", "--out", "out", "--quiet", "--workers", "1"]) == 1
    assert "vol\\xe9/flight: the path is not valid UTF-8" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == [latin1]  # nothing written
    assert [p.name for p in (tmp_path / latin1).iterdir()] == ["flight"]


def test_simulate_and_demo(tmp_path):
    assert (
        main(
            [
                "simulate",
                str(tmp_path / "sim"),
                "--duration",
                "1.0",
                "--seed",
                "3",
                "--quiet",
                "--workers",
                "1",
            ]
        )
        == 0
    )
    assert (tmp_path / "sim" / "mav0" / "cam0" / "data.csv").exists()
    assert main(["simulate", str(tmp_path / "sim"), "--duration", "1.0", "--quiet"]) == 1
    assert main(["simulate", str(tmp_path / "x"), "--scenario", "nope", "--quiet"]) == 1
    assert main(["demo", "--dir", str(tmp_path / "demo"), "--duration", "3", "--quiet"]) == 0
    assert (tmp_path / "demo" / "out" / "report.md").exists()


def test_qr_sheet(tmp_path):
    out = tmp_path / "sheet.pdf"
    assert main(["qr-sheet", str(out), "--grid", "2x1", "--loads", "P-01"]) == 0
    assert out.read_bytes().startswith(b"%PDF")
    assert main(["qr-sheet", str(tmp_path / "bad.pdf"), "--loads", "bad\x07id"]) == 1
    assert not (tmp_path / "bad.pdf").exists()


def test_console_script_version():
    exe = shutil.which("fusion") or str(Path(sys.executable).with_name("fusion"))
    out = subprocess.run([exe, "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.startswith("fusion ")


def test_smooth_tight_coupling(tmp_path):
    out = tmp_path / "tight"
    assert (
        main(
            [
                "smooth",
                str(SAMPLE),
                "--out",
                str(out),
                "--quiet",
                "--workers",
                "1",
                "--tight",
                "--no-incremental",
            ]
        )
        == 0
    )
    tight = read_tum(out / "trajectory_smoother.tum")
    raw = read_tum(out / "trajectory_pnp.tum")
    assert len(tight) > len(raw) > 0


def test_strict_exits_3_when_an_estimate_is_not_ok(tmp_path, capsys, monkeypatch):
    from fusion import pipeline
    from fusion.estimate import Health, Status

    out = tmp_path / "out"
    args = ["run", str(SAMPLE), "--out", str(out), "--quiet", "--workers", "1", "--strict"]
    assert main(args) == 0  # the sample flight is healthy
    monkeypatch.setattr(
        pipeline, "assess_result", lambda res, raw, **kw: Health(Status.DEGRADED, ["test: made degraded"])
    )
    assert main(args + ["--force"]) == 3
    text = capsys.readouterr()
    assert "health: smoother degraded: test: made degraded" in text.out
    assert "--strict" in text.err
    assert main(args[:-1] + ["--force"]) == 0  # without --strict the run still succeeds
    assert "degraded" in (out / "report.md").read_text().split("## Summary")[0]


@pytest.mark.parametrize(
    "command", [["run", "log", "--out", "out"], ["simulate", "f"], ["batch", "f", "--out", "o"]]
)
@pytest.mark.parametrize("value", ["0", "-3", "two"])
def test_a_worker_count_below_one_is_refused(command, value, capsys):
    """--workers 0 / -3 were taken as 1, silently (thirty-first session's audit)."""
    from fusion.cli import build_parser

    with pytest.raises(SystemExit):
        build_parser().parse_args([*command, "--workers", value])
    err = capsys.readouterr().err
    assert "--workers" in err and err.strip().splitlines()[-1].startswith("fusion")
    assert build_parser().parse_args([*command, "--workers", "2"]).workers == 2
