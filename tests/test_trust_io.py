"""Trust (issue #8): output folders (manifest, --force, lock, roll-back on a full or read-only
disk), simulate / demo never deleting what they did not create, the detection cache keyed on the
images, log warnings in the summary and metrics.json, and untrusted ids in CSV and Markdown."""

import csv
import errno
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from fusion.cli import main
from fusion.errors import OutputError
from fusion.fileio import LOCK_NAME, MANIFEST_NAME, RECOVERED_KEEP, OutputFolder, recovered_copy_path
from fusion.log import read_flight

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"


def _copy_sample(tmp_path, name="log"):
    log = tmp_path / name
    shutil.copytree(SAMPLE, log)
    return log


def _manifest(out):
    return json.loads((out / MANIFEST_NAME).read_text())


def _one_error_line(capsys):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


# ---------------------------------------------------------------- output folder of a run


def test_manifest_and_force_keep_user_files(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["localize", str(SAMPLE), "--out", str(out), "--quiet", "--workers", "1"]) == 0
    m = _manifest(out)
    listed = {e["path"] for e in m["files"]}
    assert m["status"] == "complete" and m["log"] == str(SAMPLE)
    assert {"detections.csv", "trajectory_pnp.tum", "loads_pnp.csv"} <= listed
    assert listed == {p.name for p in out.iterdir()} - {MANIFEST_NAME}
    for e in m["files"]:
        assert e["bytes"] == (out / e["path"]).stat().st_size and len(e["sha256"]) == 64
    # the user's file, and a leftover of another flight's run recorded in the manifest
    (out / "notes.txt").write_text("mine")
    (out / "metrics.json").write_text("{}")
    m["files"].append({"path": "metrics.json"})
    (out / MANIFEST_NAME).write_text(json.dumps(m))
    assert main(["localize", str(SAMPLE), "--out", str(out), "--quiet"]) == 1
    assert "use --force" in _one_error_line(capsys)
    assert main(["detect", str(SAMPLE), "--out", str(out), "--quiet", "--force"]) == 0
    names = {p.name for p in out.iterdir()}
    assert names == {"notes.txt", "detections.csv", MANIFEST_NAME}  # previous run gone
    assert (out / "notes.txt").read_text() == "mine"
    m2 = _manifest(out)
    assert [e["path"] for e in m2["files"]] == ["detections.csv"]
    assert m2["files"][0].get("reused") is True  # the cache checked itself
    assert "detections reused" in capsys.readouterr().out


def test_force_after_a_run_that_died(tmp_path):
    """A run killed before finishing leaves a "running" manifest listing what was there before
    it: --force removes only what appeared after."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(KeyboardInterrupt):
        with OutputFolder(out, force=True):
            (out / "trajectory_pnp.tum").write_text("x")
            raise KeyboardInterrupt  # rolled back: like a clean interruption
    assert {p.name for p in out.iterdir()} == {"notes.txt"}
    # a hard kill leaves the running manifest: simulate it
    folder = OutputFolder(out, force=True)
    folder.__enter__()
    (out / "trajectory_pnp.tum").write_text("x")
    folder.lock.release()  # the process is gone; its lock is stale
    assert _manifest(out)["status"] == "running"
    with OutputFolder(out, force=True) as again:
        assert again.removed_previous == ["trajectory_pnp.tum"]
    assert {p.name for p in out.iterdir()} == {"notes.txt", MANIFEST_NAME}


def test_hostile_manifest_cannot_delete_outside(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (out / MANIFEST_NAME).write_text(
        json.dumps(
            {
                "format": "fusion-outputs/1",
                "status": "complete",
                "files": [{"path": "../victim.txt"}, {"path": str(victim)}],
            }
        )
    )
    with OutputFolder(out, force=True):
        pass
    assert victim.read_text() == "keep"
    (out / MANIFEST_NAME).write_text("[1, 2]")
    with pytest.raises(OutputError, match="not a fusion manifest"):
        with OutputFolder(out, force=True):
            pass


def test_lock_refuses_a_second_run_and_takes_over_a_stale_one(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).write_text(f"{os.getpid()}\n{os.uname().nodename}\n")  # alive: this process
    assert main(["detect", str(SAMPLE), "--out", str(out), "--quiet", "--force"]) == 1
    line = _one_error_line(capsys)
    assert "in use by another fusion run" in line and f"pid {os.getpid()}" in line
    assert not (out / "detections.csv").exists()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (out / LOCK_NAME).write_text(f"{dead.pid}\n{os.uname().nodename}\n")
    assert main(["detect", str(SAMPLE), "--out", str(out), "--quiet", "--workers", "1"]) == 0
    assert (out / "detections.csv").exists() and not (out / LOCK_NAME).exists()


def test_lock_is_exclusive_while_a_run_holds_it(tmp_path):
    out = tmp_path / "out"
    with OutputFolder(out):
        assert (out / LOCK_NAME).read_text().split()[0] == str(os.getpid())
        with pytest.raises(OutputError, match="in use by another fusion run"):
            with OutputFolder(out, force=True):
                pass
    assert not (out / LOCK_NAME).exists()


@pytest.mark.parametrize("code", [errno.EACCES, errno.EROFS])
def test_unwritable_output_folder_is_one_clean_error(tmp_path, capsys, monkeypatch, code):
    """A folder the user may not write (or a read-only file system: as root, chmod cannot make
    one, so the refusal of the first write is simulated)."""
    import fusion.fileio as fileio

    def refuse(path, text):
        raise OSError(code, os.strerror(code), str(path))

    monkeypatch.setattr(fileio, "_create_exclusive", refuse)
    out = tmp_path / "ro"
    assert main(["detect", str(SAMPLE), "--out", str(out), "--quiet"]) == 1
    line = _one_error_line(capsys)
    assert f"{out}: cannot write here ({os.strerror(code)})" in line
    assert not out.exists()  # the folder the run made is gone again


def test_full_disk_mid_run_leaves_no_half_output(tmp_path, capsys, monkeypatch):
    """ENOSPC on the first trajectory file, after the cache and the load observations were
    written: one error line, and only the user's file is left."""
    import fusion.log.files as files

    real = files.atomic_open

    def full(path, *a, **k):
        if str(path).endswith(".tum"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(files, "atomic_open", full)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["localize", str(SAMPLE), "--out", str(out), "--quiet", "--workers", "1", "--force"]) == 1
    line = _one_error_line(capsys)
    assert "No space left on device" in line and "partial outputs were removed" in line
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    out2 = tmp_path / "new"
    assert main(["localize", str(SAMPLE), "--out", str(out2), "--quiet", "--workers", "1"]) == 1
    assert not out2.exists()


def _tree(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


def test_force_never_deletes_a_flight_log(tmp_path, capsys):
    """--force removes only what a manifest of its own kind lists: a flight log written by
    `fusion simulate` / `import` (whose manifest lists every file of the flight), a log without
    a manifest and the log being read are refused, with or without --force."""
    flight = tmp_path / "flight"
    assert _simulate(flight) == 0
    capsys.readouterr()
    before = _tree(flight)
    for force in ([], ["--force"]):
        assert main(["detect", str(SAMPLE), "--out", str(flight), "--quiet", *force]) == 1
        assert f"{flight}: is a flight log (written by `fusion simulate`)" in _one_error_line(capsys)
    assert _tree(flight) == before
    # the log being read as OUT, around OUT or inside it; a log that fusion did not write
    log = _copy_sample(tmp_path, "real")
    before = _tree(log)
    for out, how in [(log, "is"), (tmp_path, "holds"), (log / "results", "lies inside")]:
        assert main(["detect", str(log), "--out", str(out), "--quiet", "--force"]) == 1
        assert f"{out}: {how} the flight log being read" in _one_error_line(capsys)
    assert main(["detect", str(flight), "--out", str(log), "--quiet", "--force"]) == 1
    assert f"{log}: is a flight log (mav0/)" in _one_error_line(capsys)
    assert _tree(log) == before


def test_simulate_force_does_not_delete_a_run(tmp_path, capsys):
    """The reverse: a run's manifest lists the run's outputs; `simulate --force` refuses them."""
    out = tmp_path / "out"
    assert main(["detect", str(SAMPLE), "--out", str(out), "--quiet", "--workers", "1"]) == 0
    assert _manifest(out)["written_by"] == "fusion run"
    capsys.readouterr()
    before = _tree(out)
    assert _simulate(out, "--force") == 1
    assert f"{out}: holds the outputs of `fusion run`" in _one_error_line(capsys)
    assert _tree(out) == before and not (tmp_path / "out.partial").exists()


def test_import_says_import_and_map_merge_refuses_a_flight_log(tmp_path, capsys):
    copy = tmp_path / "copy"
    assert main(["import", str(SAMPLE), str(copy), "--quiet"]) == 0
    assert _manifest(copy)["written_by"] == "fusion import"
    capsys.readouterr()
    before = _tree(copy)
    # map merge writes world.yaml: refused before the runs are read
    assert main(["map", "merge", str(tmp_path / "r1"), "--out", str(copy), "--force", "--quiet"]) == 1
    assert f"{copy}: is a flight log (written by `fusion import`)" in _one_error_line(capsys)
    assert _tree(copy) == before


@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP"])
def test_sigterm_cleans_up_like_ctrl_c(tmp_path, capsys, monkeypatch, name):
    """SIGTERM (timeout, Slurm, docker stop, systemd) and SIGHUP stop a run as Ctrl-C does: no
    outputs, lock or "running" manifest left, one line, exit 128 + the signal's number."""
    import signal

    import fusion.pipeline as pipeline

    signum = getattr(signal, name)

    def killed_mid_run(log, out_dir, *args, **kwargs):
        (out_dir / "detections.csv").write_text("half")
        os.kill(os.getpid(), signum)
        raise AssertionError(f"{name} did not stop the run")

    monkeypatch.setattr(pipeline, "_run_into", killed_mid_run)
    seen = []

    def guard(signum, frame):  # without fusion's handler, the signal would end the test runner
        seen.append(signum)

    previous = signal.signal(signum, guard)
    try:
        out = tmp_path / "out"
        assert main(["run", str(SAMPLE), "--out", str(out), "--quiet"]) == 128 + signum
        assert signal.getsignal(signum) is guard  # restored
    finally:
        signal.signal(signum, previous)
    assert _one_error_line(capsys) == f"fusion: stopped by {name}"
    assert not seen and not out.exists()


def test_stop_signals_leave_an_ignored_hangup_ignored():
    """`nohup fusion run ...`: SIGHUP stays ignored while the command runs."""
    import signal

    from fusion.cli import _stop_on_signals

    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        with _stop_on_signals():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) not in (signal.SIG_IGN, signal.SIG_DFL)
    finally:
        signal.signal(signal.SIGHUP, previous)


# ---------------------------------------------------------------- simulate and demo


def _simulate(out, *extra):
    return main(["simulate", str(out), "--duration", "0.3", "--quiet", "--workers", "1", *extra])


def test_simulate_force_keeps_the_users_files(tmp_path, capsys):
    d = tmp_path / "flight"
    assert _simulate(d) == 0
    first = {e["path"] for e in _manifest(d)["files"]}
    assert "world.yaml" in first and any(p.startswith("mav0/cam0/data/") for p in first)
    (d / "notes.txt").write_text("mine")
    (d / "mine").mkdir()
    (d / "mine" / "x.txt").write_text("mine too")
    assert _simulate(d, "--force", "--seed", "1") == 0
    assert (d / "notes.txt").read_text() == "mine" and (d / "mine" / "x.txt").exists()
    log = read_flight(d)
    assert len(log.floor) == sum(p.startswith("mav0/cam0/data/") for p in first) > 0
    on_disk = {p.relative_to(d).as_posix() for p in d.rglob("*") if p.is_file()}
    assert on_disk == {e["path"] for e in _manifest(d)["files"]} | {MANIFEST_NAME, "notes.txt", "mine/x.txt"}


def test_simulate_refuses_a_folder_holding_a_log_it_did_not_write(tmp_path, capsys):
    d = _copy_sample(tmp_path)
    before = sorted(p.relative_to(d) for p in d.rglob("*"))
    assert _simulate(d, "--force") == 1
    line = _one_error_line(capsys)
    assert "that fusion did not write" in line and "refusing to overwrite" in line
    assert sorted(p.relative_to(d) for p in d.rglob("*")) == before
    assert not (tmp_path / "log.partial").exists()


def test_simulate_refuses_a_foreign_partial_folder(tmp_path, capsys):
    d = tmp_path / "flight2"
    partial = tmp_path / "flight2.partial"
    partial.mkdir()
    (partial / "thesis.tex").write_text("years of work")
    assert _simulate(d) == 1
    line = _one_error_line(capsys)
    assert "flight2.partial: exists and was not made by fusion" in line
    assert (partial / "thesis.tex").read_text() == "years of work" and not d.exists()
    # a leftover of a fusion writer that died is ours to replace
    shutil.rmtree(partial)
    partial.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (partial / ".fusion-partial").write_text(f"{dead.pid}\n")
    assert _simulate(d) == 0 and not partial.exists() and (d / "world.yaml").exists()


def test_demo_keeps_the_users_files(tmp_path):
    d = tmp_path / "demo"
    (d / "log").mkdir(parents=True)
    (d / "log" / "README.txt").write_text("mine")
    (d / "out").mkdir()
    (d / "out" / "notes.txt").write_text("mine")
    assert main(["demo", "--dir", str(d), "--duration", "2", "--quiet"]) == 0
    assert (d / "log" / "README.txt").read_text() == "mine"
    assert (d / "out" / "notes.txt").read_text() == "mine"
    assert (d / "out" / "report.md").exists() and (d / "log" / "world.yaml").exists()


# ---------------------------------------------------------------- detection cache


def test_detection_cache_is_keyed_on_the_images(tmp_path, caplog):
    import logging

    from fusion.qr.detect import detect_flight

    log_dir = _copy_sample(tmp_path)
    cache = tmp_path / "detections.csv"
    first = detect_flight(read_flight(log_dir), cache, workers=1, progress=False)
    assert first.cache_status == "written" and not first.from_cache
    with caplog.at_level(logging.INFO, logger="fusion.qr.detect"):
        again = detect_flight(read_flight(log_dir), cache, workers=1, progress=False)
    assert again.cache_status == "reused" and again.from_cache
    assert "detections reused from" in caplog.text
    # replace one floor image by a blank one: same data.csv, other content
    import cv2

    img_path = sorted((log_dir / "mav0" / "cam0" / "data").iterdir())[0]
    img = cv2.imread(str(img_path), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(img_path), np.full_like(img, 255))
    t0 = int(img_path.name.split(".")[0])
    assert any(d.timestamp_ns == t0 and d.camera == "cam0" for d in first.detections)
    fresh = detect_flight(read_flight(log_dir), cache, workers=1, progress=False)
    assert fresh.cache_status == "recomputed"
    assert not any(d.timestamp_ns == t0 and d.camera == "cam0" for d in fresh.detections)


def test_cache_round_trips_hostile_payloads(tmp_path):
    from fusion.qr.detect import DetectionResult, read_cache, write_cache
    from fusion.types import QRDetection

    payloads = ["=cmd|' /C calc'!A0", "1/+SUM(1)", "'x", "-1", "0/1/2"]
    dets = [
        QRDetection("cam1", 10 + i, p, np.zeros((4, 2)), np.zeros((4, 2)), 1.0)
        for i, p in enumerate(payloads)
    ]
    write_cache(DetectionResult(dets, {}), tmp_path / "d.csv", "f")
    rows = list(csv.reader((tmp_path / "d.csv").read_text().splitlines()[3:]))
    assert all(not r[2].startswith(("=", "+", "-", "@")) for r in rows)
    assert [d.payload for d in read_cache(tmp_path / "d.csv").detections] == payloads


# ---------------------------------------------------------------- warnings reach the user


def test_log_warnings_reach_summary_and_metrics(tmp_path, capsys):
    """Ground truth 0.6 s late and quaternions scaled by 2: named, counted warnings in the
    terminal summary and metrics.json; the run still completes."""
    log_dir = _copy_sample(tmp_path)
    gt = log_dir / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    lines = gt.read_text().splitlines()
    out_lines = [lines[0]]
    for l in lines[1:]:
        parts = l.split(",")
        parts[0] = str(int(parts[0]) + 600_000_000)
        parts[4:8] = [repr(2 * float(v)) for v in parts[4:8]]
        out_lines.append(",".join(parts))
    gt.write_text("\n".join(out_lines) + "\n")
    out = tmp_path / "out"
    assert (
        main(["run", str(log_dir), "--out", str(out), "--quiet", "--workers", "1", "--no-incremental"]) == 0
    )
    text = capsys.readouterr().out
    assert "warning: [clock_offset] x1: groundtruth starts and ends 0.6 s later than cam0" in text
    assert "warning: [groundtruth_quaternion_not_unit]" in text
    metrics = json.loads((out / "metrics.json").read_text())
    names = {w["name"]: w for w in metrics["warnings"]}
    assert set(names) == {"clock_offset", "groundtruth_quaternion_not_unit"}
    assert names["groundtruth_quaternion_not_unit"]["count"] == len(lines) - 1
    assert "\\[clock\\_offset\\] x1" in (out / "report.md").read_text()  # Markdown-escaped


@pytest.mark.parametrize("rel", ["world.yaml", "mav0/imu0/data.csv", "mav0/cam0/sensor.yaml"])
def test_named_pipe_inputs_are_refused_not_hung(tmp_path, rel):
    log_dir = _copy_sample(tmp_path)
    (log_dir / rel).unlink()
    os.mkfifo(log_dir / rel)
    # in a subprocess with a hang-guard only (a reader blocked on a pipe never returns); the
    # expected run takes about a second
    proc = subprocess.run(
        [sys.executable, "-m", "fusion.cli", "run", str(log_dir), "--out", str(tmp_path / "out"), "--quiet"],
        capture_output=True,
        text=True,
        check=False,
        timeout=300,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).parents[1])},
    )
    assert proc.returncode == 1
    assert proc.stderr.strip().splitlines() == [
        f"fusion: error: {log_dir / rel}: is a named pipe, expected a regular file"
    ]


# ---------------------------------------------------------------- untrusted ids in outputs


def test_load_ids_are_neutralised_in_csv_and_escaped_in_markdown(tmp_path):
    from fusion.evaluate.report import write_report
    from fusion.pipeline import write_load_observations_csv
    from fusion.types import LoadEstimate, LoadMap, LoadObservation, Trajectory

    hostile = "=cmd|' /C calc'!A0"
    obs = [LoadObservation(5, hostile, np.array([1.0, 2, 3]), np.eye(3) * 1e-4)]
    write_load_observations_csv(tmp_path / "obs.csv", obs)
    row = list(csv.reader((tmp_path / "obs.csv").read_text().splitlines()))[1]
    assert row[1] == "'" + hostile
    lm = LoadMap(
        "pnp",
        [
            LoadEstimate(hostile, np.array([1.0, 2, 3]), None, 2),
            LoadEstimate("a`b|c", np.array([1.0, 2, 3]), None, 2),
        ],
    )
    traj = Trajectory("pnp", np.array([0, 10**9], dtype=np.int64), np.tile(np.eye(4), (2, 1, 1)))
    report = write_report(tmp_path / "rep", None, {"pnp": traj}, {"pnp": lm}, dpi=40)
    rows = [l for l in report.read_text().splitlines() if l.startswith("| pnp |") and "`" in l]
    assert len(rows) == 2
    for l in rows:  # GFM: a cell boundary is an unescaped |
        cells = re.split(r"(?<!\\)\|", l)[1:-1]
        assert len(cells) == 9, l
    assert any("`` a`b\\|c ``" in l for l in rows)


def test_simulate_on_a_full_disk_is_one_error_and_leaves_nothing(tmp_path, capsys, monkeypatch):
    import fusion.log.euroc as euroc

    real = euroc.atomic_open

    def full(path, *a, **k):
        if str(path).endswith("data.csv"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(euroc, "atomic_open", full)
    assert _simulate(tmp_path / "f") == 1
    line = _one_error_line(capsys)
    assert "cannot write the flight log: No space left on device" in line
    assert list(tmp_path.iterdir()) == []


def test_front_camera_clock_offset_is_a_named_warning_not_an_empty_map(tmp_path, capsys):
    """cam1's clock 1000 s off, fixed at 0 by hand, puts every load sighting outside the floor
    frames' span: the back ends cannot place them (from the pose interpolated at their stamps,
    fusion.estimate.common.retime_load_obs), the fused load maps lose them, and the run must say
    so (issue #8, 'silently wrong').  (A 15 ms offset no longer loses them:
    tests/test_timeoffset.py, tests/test_load_retime.py.)"""
    log = _copy_sample(tmp_path)
    csv_path = log / "mav0" / "cam1" / "data.csv"
    lines = csv_path.read_text().splitlines()
    shifted = [lines[0]] + [
        f"{int(t) + 1_000_000_000_000},{name}" for t, name in (line.split(",") for line in lines[1:])
    ]
    csv_path.write_text("\n".join(shifted) + "\n")
    out = tmp_path / "out"
    args = ["run", str(log), "--out", str(out), "--quiet", "--workers", "1", "--time-offset-ms", "0"]
    assert main(args) == 0
    text = capsys.readouterr().out
    assert "load_sightings_unsynchronised" in text
    names = [w["name"] for w in json.loads((out / "metrics.json").read_text())["warnings"]]
    assert "load_sightings_unsynchronised" in names


def test_a_floor_camera_that_decodes_no_code_is_a_warning_and_not_trusted(tmp_path, capsys):
    """Every floor frame readable but without a decodable code (a lens or resolution whose view
    never holds a whole code: 1280x720 or focal x1.5 on the default scenario) leaves nothing to
    localise from.  Before, only a note said so: no warning under --quiet, none in metrics.json,
    and --strict exited 0 with no fused estimate at all."""
    import cv2

    log = _copy_sample(tmp_path)
    for png in (log / "mav0" / "cam0" / "data").glob("*.png"):
        img = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
        assert cv2.imwrite(str(png), np.full_like(img, 128))
    out = tmp_path / "out"
    args = ["run", str(log), "--out", str(out), "--quiet", "--workers", "1"]
    assert main(args + ["--strict"]) == 3
    text = capsys.readouterr()
    assert "warning: [no_floor_pose]" in text.out and "no floor code decoded" in text.out
    assert "--strict" in text.err
    metrics = json.loads((out / "metrics.json").read_text())
    assert [w["name"] for w in metrics["warnings"]] == ["no_floor_pose"]
    assert metrics["warnings"][0]["count"] == len(list((log / "mav0" / "cam0" / "data").glob("*.png")))
    assert "no_floor_pose" in (out / "report.md").read_text().split("## Summary")[0]
    # per-frame stage only: nothing was to be fused, so nothing is untrusted
    assert main(["localize", str(log), "--out", str(tmp_path / "loc"), "--quiet", "--workers", "1"]) == 0
    assert "no_floor_pose" in capsys.readouterr().out


def test_swapped_cameras_are_named_as_such(tmp_path):
    """The two cameras' images logged under each other's names: the floor camera reads load codes
    and the front camera floor codes.  no_floor_pose advised the floor camera's focus and exposure
    (third audit); it now says the cameras look swapped."""
    log = _copy_sample(tmp_path)
    mav = log / "mav0"
    for name in ("data", "data.csv"):
        (mav / "cam0" / name).rename(mav / f"swap_{name}")
        (mav / "cam1" / name).rename(mav / "cam0" / name)
        (mav / f"swap_{name}").rename(mav / "cam1" / name)
    out = tmp_path / "out"
    assert main(["run", str(log), "--out", str(out), "--quiet", "--workers", "1", "--no-incremental"]) == 0
    (w,) = [
        w for w in json.loads((out / "metrics.json").read_text())["warnings"] if w["name"] == "no_floor_pose"
    ]
    assert "the two cameras look swapped" in w["message"] and "focus" not in w["message"]


def test_unplaced_load_sightings_at_the_flights_ends_are_not_blamed_on_a_clock_offset():
    """A sighting stamped within a frame of the floor camera's first or last frame (cameras
    started a frame apart, or a jittered stamp) is counted without the clock-offset hint; one
    far outside keeps it."""
    from types import SimpleNamespace

    from fusion.pipeline import _unsynchronised_load_sightings

    floor_t = np.arange(10, 110, dtype=np.int64) * 33_333_333
    log = SimpleNamespace(front=object(), floor=SimpleNamespace(timestamps_ns=floor_t))

    def warn(stamps):
        obs = [SimpleNamespace(timestamp_ns=int(s)) for s in stamps]
        return _unsynchronised_load_sightings(log, SimpleNamespace(camera_frame_observations=obs))

    inside = list(floor_t[20:30])
    assert warn(inside) is None
    edge = warn(inside + [floor_t[0] - 20_000_000])  # 20 ms before the first floor frame
    assert edge is not None and edge.count == 1 and "started or stopped apart" in edge.message
    far = warn(inside + [floor_t[-1] + 5_000_000_000])
    assert far is not None and "clock offset on cam1" in far.message


def test_recovered_bag_copies_are_a_bounded_cache(tmp_path, monkeypatch):
    """Each damaged bag ever read left a full-size copy in the temp folder (second audit): the
    folder keeps the RECOVERED_KEEP most recently used copies."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    folder = tmp_path / "fusion-recovered-bags"

    def copy(i):
        p = recovered_copy_path(f"bag{i}", f"/logs/bag{i}|1|{i}", ".bag")
        if not p.exists():
            p.write_bytes(b"copy")
            os.utime(p, ns=(i * 10**9, i * 10**9))
        return p

    made = [copy(i) for i in range(RECOVERED_KEEP)]
    assert all(p.exists() for p in made)
    assert copy(0) == made[0]  # used again: now the most recent
    (folder / ".recover-x").mkdir()  # another reader's work folder, not a copy
    for i in range(RECOVERED_KEEP, RECOVERED_KEEP + 3):
        copy(i)
    left = {p.name for p in folder.iterdir() if p.is_file()}
    assert len(left) == RECOVERED_KEEP
    assert made[0].name in left and not {p.name for p in made[1:4]} & left
    assert (folder / ".recover-x").is_dir()
