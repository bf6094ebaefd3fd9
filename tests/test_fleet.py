"""`fusion batch` (fusion.fleet) on a real multi-process dask LocalCluster and tiny simulated
flights: the outputs equal `fusion run`'s, resume, --retry-failed, a bad flight among good
ones, same-name flights, the fleet lock, an unreachable scheduler, a worker that dies."""

import csv
import json
import os
import shutil
import socket
import sys
from pathlib import Path

import cloudpickle
import dask
import pytest
from distributed import Client, LocalCluster, WorkerPlugin

from fusion.cli import EXIT_FLIGHTS_FAILED, _run_config, build_parser, main
from fusion.errors import FleetError, LogError
from fusion.fileio import LOCK_NAME, read_manifest
from fusion.fleet import BatchConfig, FlightStatus, run_batch
from fusion.fleet.batch import connect
from fusion.fleet.flights import FlightRecord, expand_flights, output_names, read_state
from fusion.fleet.parts import PartFile, read_part, write_part
from fusion.fleet.summary import NO_HEALTH, flight_row
from fusion.pipeline import RunConfig, run
from fusion.sim.simulate import simulate

cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the worker plugin below

FLIGHT_S = 3.0
FPS = 10.0
CHUNK = 8  # frames per detection task: several tasks per flight even at 31 frames a camera


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """A flight and, under the same folder name elsewhere, a bad one (no log in it), listed."""
    root = tmp_path_factory.mktemp("fleet")
    simulate(
        root / "a" / "flight", duration_s=FLIGHT_S, seed=3, progress=False, workers=1, camera_rate_hz=FPS
    )
    (root / "b" / "flight").mkdir(parents=True)
    (root / "b" / "flight" / "readme.txt").write_text("not a flight\n")
    listing = root / "flights.txt"
    listing.write_text("# the morning's flights\na/flight\n\nb/flight\n")
    return root


def _names(flights: Path) -> tuple[str, str]:
    names = output_names(expand_flights([flights / "flights.txt"]))
    return names[(flights / "a/flight").resolve()], names[(flights / "b/flight").resolve()]


@pytest.fixture(scope="module")
def cluster():
    """2 single-threaded worker processes; a worker death fails its task at once, as the local
    cluster of `fusion batch` does (batch.LOCAL_ALLOWED_FAILURES)."""
    with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
        lc = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    client = Client(lc)
    yield lc, client
    client.close()
    lc.close()


def _cfg(cluster, **kw) -> BatchConfig:
    return BatchConfig(scheduler=cluster[0].scheduler_address, chunk_frames=CHUNK, **kw)


def _rows(out: Path) -> dict[str, dict]:
    with open(out / "fleet.csv", newline="") as f:
        return {r["flight"]: r for r in csv.DictReader(f)}


@pytest.fixture(scope="module")
def batch(flights, cluster, tmp_path_factory):
    """The listed flights, the good one's worker killed once as its report starts."""
    out = tmp_path_factory.mktemp("out") / "fleet"
    good, _ = _names(flights)
    marker = out.parent / "killed-once"
    cluster[1].register_plugin(_KillOnReport("", good, str(marker)), name="kill-once")
    try:
        res = run_batch([flights / "flights.txt"], out, _cfg(cluster))
    finally:
        cluster[1].unregister_worker_plugin("kill-once")
    assert marker.exists()
    return out, res


# ============================================================================ flights and names


def test_list_files_and_paths_expand_in_order_once(flights):
    got = expand_flights([flights / "flights.txt", flights / "a" / "flight"])
    assert got == [(flights / p).resolve() for p in ("a/flight", "b/flight")]


def test_a_list_of_no_flight_is_refused_naming_it(tmp_path):
    """An empty list (or one of comments only) was a batch of 0 flights, exit 0 (thirty-first
    session's audit)."""
    listing = tmp_path / "list.txt"
    listing.write_text("# nothing flown today\n\n")
    with pytest.raises(FleetError, match=r"list\.txt: lists no flight"):
        expand_flights([listing])


def test_same_folder_names_get_distinct_stable_names(tmp_path):
    a, b, c = tmp_path / "x" / "f", tmp_path / "y" / "f", tmp_path / "z" / "g"
    names = output_names([a, b, c])
    assert names[c] == "g"
    assert names[a] != names[b] and names[a].startswith("f-") and names[b].startswith("f-")
    assert output_names([b, a, c]) == names  # not by position
    # a flight fleet.json already knows keeps its name, whatever else is in the batch
    previous = {"f": FlightRecord("f", str(a))}
    assert output_names([b, a], previous)[a] == "f"
    assert output_names([b, a], previous)[b] != "f"
    # the fleet folder's own files are never a flight's folder
    for own in ("fleet.json", "fleet.md", "fusion.lock"):
        assert output_names([tmp_path / own])[tmp_path / own] == f"flight-{own}"


# ============================================================================ a batch


def test_batch_writes_each_flight_as_run_does_and_records_the_bad_one(batch, flights, tmp_path):
    out, res = batch
    a, bad = _names(flights)
    assert a != bad and a.startswith("flight-") and {a, bad} == {r.name for r in res.records}
    recs = {r.name: r for r in res.records}
    assert [r.name for r in res.failed] == [bad]
    assert "not a flight log" in recs[bad].reason and recs[bad].attempts == 1
    # its worker died once as the report started: the flight ran again, whole
    assert recs[a].status == FlightStatus.OK and recs[a].attempts == 2
    assert read_manifest(out / a)["status"] == "complete"
    assert not (out / bad).exists()
    assert not (out / ".parts").exists()  # the tasks' hand-over files are gone with the batch
    # the detect and localize tasks give what `fusion run`'s stages give, byte for byte
    ref = run(
        flights / "a" / "flight", tmp_path / "ref", RunConfig(workers=1, progress=False), until="localize"
    )
    for f in ("detections.csv", "trajectory_pnp.tum", "trajectory_paper.tum", "load_observations_pnp.csv"):
        assert (out / a / f).read_bytes() == (ref.out_dir / f).read_bytes(), f
    for f in (
        "metrics.json",
        "report.md",
        "trajectory_smoother.tum",
        "trajectory_ekf.tum",
        "loads_smoother.csv",
    ):
        assert (out / a / f).is_file()
    rows = _rows(out)
    assert rows[bad]["status"] == "failed" and "not a flight log" in rows[bad]["failure"]
    metrics = json.loads((out / a / "metrics.json").read_text())
    assert rows[a]["status"] == "ok"
    assert rows[a]["health"] == max(
        (h["status"] for h in metrics["health"].values()), key=["ok", "degraded", "diverged"].index
    )
    assert float(rows[a]["ate_rmse_m"]) == pytest.approx(metrics["trajectories"]["smoother"]["ate_rmse_m"])
    assert float(rows[a]["coverage"]) == pytest.approx(  # of every floor frame, not only those read
        metrics["estimator_stats"]["pnp"]["n_posed"] / metrics["detection"]["floor_frames"], abs=1e-6
    )
    assert float(rows[a]["compute_s"]) > 0 and int(rows[a]["frames"]) == 2 * (1 + int(FLIGHT_S * FPS))
    md = (out / "fleet.md").read_text()
    assert f"[{a}]({a}/report.md)" in md and "fleet_time.png" in md and (out / "fleet_time.png").is_file()


def test_a_second_batch_skips_completed_and_failed_flights(batch, flights, cluster):
    out, first = batch
    before = {
        r.name: (out / r.name / "manifest.json").stat().st_mtime_ns for r in first.records if r.status == "ok"
    }
    again = run_batch([flights / "b" / "flight", flights / "flights.txt"], out, _cfg(cluster))
    assert again.ran == [] and len(again.skipped) == 2
    assert {
        r.name: (out / r.name / "manifest.json").stat().st_mtime_ns for r in again.records if r.status == "ok"
    } == before
    assert [r.name for r in again.failed] == [_names(flights)[1]]


def test_retry_failed_runs_only_the_failed_flights(batch, flights, cluster):
    out, _ = batch
    res = run_batch([flights / "flights.txt"], out, _cfg(cluster, retry_failed=True))
    bad = _names(flights)[1]
    assert res.ran == [bad] and len(res.skipped) == 1
    assert read_state(out)[bad].status == FlightStatus.FAILED


# ============================================================================ bad input


def _malloc_env() -> tuple:
    return os.environ.get("MALLOC_ARENA_MAX"), os.environ.get("MALLOC_TRIM_THRESHOLD_")


def _profiler(dask_worker) -> tuple:
    import dask

    return dask.config.get("distributed.worker.profile.enabled"), "profile" in dask_worker.periodic_callbacks


def test_local_workers_start_with_one_malloc_arena_and_no_profiler(capfd):
    """batch.LOCAL_MALLOC_ARENAS reaches the local cluster's worker processes (glibc reads it
    when the process starts); Dask's own trim threshold stays; the statistical profiler is off
    (batch.LOCAL_PROFILER).  A bad flight's error is the batch's to report (fleet.md, its
    FAILED line): the worker prints no "Compute Failed" traceback of it on stderr."""
    with connect(BatchConfig(workers=1)) as client:
        assert client.submit(_malloc_env, pure=False).result() == ("1", "65536")
        assert list(client.run(_profiler).values()) == [(False, False)]
        with pytest.raises(LogError, match="not a flight"):
            client.submit(_bad_flight, pure=False).result()
    err = capfd.readouterr().err
    assert "Compute Failed" not in err and "Traceback" not in err


def _bad_flight() -> None:
    raise LogError("/x: not a flight log")


def test_a_second_batch_on_the_same_folder_is_refused(flights, tmp_path):
    out = tmp_path / "fleet"
    out.mkdir()
    (out / LOCK_NAME).write_text(f"{os.getpid()}\n{os.uname().nodename}\n")  # a live batch holds it
    with pytest.raises(FleetError, match="in use"):
        run_batch([flights / "a" / "flight"], out, BatchConfig(workers=1))
    assert not (out / "fleet.json").exists()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_an_unreachable_scheduler_is_one_line(flights, tmp_path, capsys):
    address = f"tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    rc = main(
        ["batch", str(flights / "a" / "flight"), "--out", str(tmp_path / "o"), "--scheduler", address, "-q"]
    )
    err = capsys.readouterr().err
    assert rc == 1
    line = [ln for ln in err.splitlines() if ln.startswith("fusion: error:")]
    assert len(line) == 1 and "cannot reach the dask scheduler" in line[0] and address in line[0]
    assert "Traceback" not in err


class _KillOnReport(WorkerPlugin):
    """Ends its worker process when a flight's report task starts: always for flight `always`,
    the first time only for flight `once` (a marker file remembers it across worker restarts)."""

    def __init__(self, always: str, once: str, marker: str):
        self.always, self.once, self.marker = always, once, marker

    def transition(self, key, start, finish, **kwargs):
        if finish != "executing":
            return
        if self.always and str(key).startswith(f"report-{self.always}-"):
            os._exit(1)
        if self.once and str(key).startswith(f"report-{self.once}-") and not os.path.exists(self.marker):
            open(self.marker, "w").close()
            os._exit(1)


def test_the_merge_and_front_context_run_beside_the_report_not_on_its_worker(flights, cluster, tmp_path):
    """The report task runs where the flight's log is, the floor merge and the front context on
    the other worker (batch._Driver._placement: the heap they free stays in their process)."""
    import time

    client = cluster[1]
    client.get_task_stream()  # the scheduler records task placement from now on
    t0 = time.time()
    res = run_batch([flights / "a" / "flight"], tmp_path / "out", _cfg(cluster))
    assert res.failed == []
    where = {str(r["key"]).split("-", 1)[0]: r["worker"] for r in client.get_task_stream(start=t0)}
    assert where["report"] == where["open"]
    assert where["merge"] != where["report"] and where["frontctx"] != where["report"]


def test_a_worker_dying_twice_fails_the_flight(flights, cluster, tmp_path):
    shutil.copytree(flights / "a" / "flight", tmp_path / "dies")
    cluster[1].register_plugin(_KillOnReport("dies", "", ""), name="kill")
    try:
        res = run_batch([tmp_path / "dies"], tmp_path / "out", _cfg(cluster))
    finally:
        cluster[1].unregister_worker_plugin("kill")
    dies = res.records[0]
    assert dies.status == FlightStatus.FAILED and dies.attempts == 2
    assert "worker died" in dies.reason and dies.error_type == "KilledWorker"
    assert not (tmp_path / "out" / "dies" / "manifest.json").exists()


def test_cli_batch_exit_code_says_flights_failed(flights, cluster, tmp_path, capsys):
    rc = main(
        [
            "batch",
            str(flights / "b" / "flight"),
            "--out",
            str(tmp_path / "o"),
            "-q",
            "--scheduler",
            cluster[0].scheduler_address,
        ]
    )
    assert rc == EXIT_FLIGHTS_FAILED
    assert "FAILED flight: " in capsys.readouterr().out


class _BreakParts(WorkerPlugin):
    """As task `prefix-<flight>-…` starts, makes OUT/.parts unusable: `how` "file" puts a file
    where the folder is (nothing can be written under it), "gone" removes it."""

    def __init__(self, prefix: str, out: str, how: str):
        self.prefix, self.out, self.how = prefix, out, how

    def transition(self, key, start, finish, **kwargs):
        if finish != "executing" or not str(key).startswith(self.prefix):
            return
        parts = Path(self.out) / ".parts"
        shutil.rmtree(parts, ignore_errors=True)
        if self.how == "file":
            parts.write_text("in the way\n")


@pytest.mark.parametrize(
    ("prefix", "how", "message"),
    [
        ("detect0000-", "file", "cannot write a task's result"),
        ("report-", "gone", "cannot read a task's result (No such file or directory)"),
    ],
)
def test_a_hand_over_file_that_cannot_be_written_or_read_fails_the_flight_in_one_line(
    flights, cluster, tmp_path, prefix, how, message
):
    out = tmp_path / "out"
    cluster[1].register_plugin(_BreakParts(prefix, str(out), how), name="break-parts")
    try:
        res = run_batch([flights / "a" / "flight"], out, _cfg(cluster))
    finally:
        cluster[1].unregister_worker_plugin("break-parts")
    rec = res.records[0]
    assert rec.status == FlightStatus.FAILED and rec.error_type == "FleetError" and rec.attempts == 1
    assert "\n" not in rec.reason and message in rec.reason
    assert f"{out}/.parts/{rec.name}-a1/" in rec.reason and ".pkl" in rec.reason  # names the file
    assert not (out / rec.name / "manifest.json").exists()
    assert not (out / ".parts").exists()


def test_write_part_round_trips_and_a_full_disk_is_one_line_naming_the_file(tmp_path, monkeypatch):
    value = {"a": [1, 2.5, "x"], "b": (None, b"\x00")}
    part = write_part(tmp_path / "p", "one", value)
    assert read_part(part) == value and part.nbytes == (tmp_path / "p" / "one.pkl").stat().st_size

    def full(obj, f, protocol=None):
        f.write(b"partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("fusion.fleet.parts.pickle.dump", full)
    with pytest.raises(FleetError) as e:
        write_part(tmp_path / "p", "two", value)
    assert (
        str(e.value)
        == f"{tmp_path / 'p' / 'two.pkl'}: cannot write a task's result (No space left on device)"
    )
    assert sorted(p.name for p in (tmp_path / "p").iterdir()) == ["one.pkl"]  # no partial file left
    (tmp_path / "p" / "bad.pkl").write_bytes(b"\x80\x05not a pickle")
    with pytest.raises(FleetError, match="bad.pkl: a task's result is damaged"):
        read_part(PartFile(str(tmp_path / "p" / "bad.pkl"), 0))


def test_batch_takes_the_run_options_every_flight_shares():
    """--map, --time-offset-ms and --calibrate-readout reach each flight's RunConfig."""
    args = build_parser().parse_args(
        ["batch", "a", "b", "--out", "o", "--map", "m", "--time-offset-ms", "cam1=-3", "--calibrate-readout"]
    )
    cfg = _run_config(args)
    assert cfg.floor_map == Path("m")
    assert cfg.time_offsets_s == pytest.approx({"cam1": -0.003})
    assert cfg.calibrate_readout
    assert _run_config(build_parser().parse_args(["batch", "a", "--out", "o"])).floor_map is None


def test_a_flight_without_a_fused_estimate_says_why_in_the_summary(tmp_path):
    """No floor pose, no health: the summary's detail names the log's warnings (it was empty)."""
    (tmp_path / "f").mkdir()
    warning = {
        "name": "no_floor_pose",
        "count": 241,
        "message": "none of the 241 floor-camera frames gave a pose",
    }
    (tmp_path / "f" / "metrics.json").write_text(json.dumps({"health": {}, "warnings": [warning]}))
    row = flight_row(tmp_path, FlightRecord("f", "/logs/f", status=FlightStatus.OK))
    assert row.health == NO_HEALTH and row.health_detail == "no_floor_pose x241"


def test_the_summary_lists_each_flights_warnings(tmp_path):
    """A fleet operator sees which flights warned of what (a jittering camera clock here), in
    fleet.csv's `warnings` column and fleet.md's Warnings section."""
    from fusion.fleet.summary import write_summary

    for name, warnings in (("a", [{"name": "floor_stamp_jitter", "count": 1, "message": "..."}]), ("b", [])):
        (tmp_path / name).mkdir()
        (tmp_path / name / "metrics.json").write_text(
            json.dumps({"health": {"smoother": {"status": "ok"}}, "warnings": warnings})
        )
    records = [FlightRecord(n, f"/logs/{n}", status=FlightStatus.OK) for n in ("a", "b")]
    write_summary(tmp_path, records)
    rows = _rows(tmp_path)
    assert rows["a"]["warnings"] == "floor_stamp_jitter x1" and rows["b"]["warnings"] == ""
    md = (tmp_path / "fleet.md").read_text()
    assert "## Warnings" in md and "- a: floor_stamp_jitter x1" in md and "- b:" not in md


def test_an_unreadable_metrics_file_is_not_an_ok_row(tmp_path):
    """A finished flight whose metrics.json cannot be read (truncated, hand-edited): its row said
    nothing (health empty, so fleet.md listed it with the good ones); now health "unknown" with
    the reason, and fleet.md lists it under "Health below ok"."""
    from fusion.fleet.summary import UNREAD_HEALTH, write_summary

    (tmp_path / "f").mkdir()
    (tmp_path / "f" / "metrics.json").write_text('{"health": {"smoother": ')
    rec = FlightRecord("f", "/logs/f", status=FlightStatus.OK)
    row = flight_row(tmp_path, rec)
    assert row.health == UNREAD_HEALTH and "metrics.json not read" in row.health_detail
    write_summary(tmp_path, [rec])
    md = (tmp_path / "fleet.md").read_text()
    assert "## Health below ok" in md and "metrics.json not read" in md


def test_coverage_is_of_every_floor_frame(tmp_path):
    """PnP's n_frames counts only the frames with a detection: coverage is n_posed over every
    floor frame of the log (a flight that read its codes in half its frames read 100 %)."""
    (tmp_path / "f").mkdir()
    metrics = {
        "health": {"smoother": {"status": "ok"}},
        "estimator_stats": {"pnp": {"n_frames": 645, "n_posed": 640}},
        "detection": {"floor_frames": 1351},
    }
    (tmp_path / "f" / "metrics.json").write_text(json.dumps(metrics))
    row = flight_row(tmp_path, FlightRecord("f", "/logs/f", status=FlightStatus.OK))
    assert row.coverage == pytest.approx(640 / 1351)
