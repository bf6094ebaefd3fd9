"""The back end on several processes (fusion.parallel.call_each, the windowed solves):
workers=2 must write exactly the files workers=1 writes, and what workers log or raise
must reach the main process."""

import json
import logging
import re
from pathlib import Path

import pytest

from fusion import pipeline
from fusion.errors import EstimationError
from fusion.estimate.window import WindowConfig
from fusion.parallel import ParallelError, call_each, parallel_map, sendable, start_map, worker_usage

SAMPLE = Path(__file__).resolve().parents[1] / "data" / "sample-flight"


def _divide(a: float, b: float) -> float:
    if b == 0:
        raise EstimationError(f"cannot divide {a} by zero")
    return a / b


def _warn(context, task: int) -> int:
    logging.getLogger("fusion.test_worker").warning("worker warning %d", task)
    logging.getLogger("fusion.test_worker").debug("worker debug %d", task)
    return task


@pytest.mark.parametrize("workers", [1, 2])
def test_call_each_returns_each_value_or_error_in_order(workers):
    out = call_each(
        [(_divide, (1.0, 2.0), {}), (_divide, (1.0,), {"b": 0}), (_divide, (9.0, 3.0), {})], workers
    )
    assert [o.error is None for o in out] == [True, False, True]
    assert out[0].get() == 0.5 and out[2].get() == 3.0
    with pytest.raises(EstimationError, match="cannot divide 1.0 by zero"):
        out[1].get()


def test_call_each_runs_a_closure_here():
    def closure(x):  # cannot be pickled: the batch stays in this process
        return x + 1

    assert not sendable(closure) and sendable(_divide)
    before = worker_usage().calls
    out = call_each([(closure, (1,), {}), (_divide, (4.0, 2.0), {})], 2)
    assert [o.get() for o in out] == [2, 2.0]
    assert worker_usage().calls == before  # nothing ran in a worker


def test_worker_records_reach_this_process_and_cpu_is_counted(caplog):
    before = worker_usage()
    with caplog.at_level(logging.INFO, logger="fusion"):
        assert list(parallel_map(_warn, [1, 2, 3], 2)) == [1, 2, 3]
    got = sorted(r.getMessage() for r in caplog.records if r.name == "fusion.test_worker")
    assert got == ["worker warning 1", "worker warning 2", "worker warning 3"]  # not the debug ones
    after = worker_usage()
    assert after.calls == before.calls + 3 and after.cpu_s >= before.cpu_s and after.peak_rss_mb > 0


def test_a_worker_error_reaches_the_caller():
    with pytest.raises(EstimationError, match="cannot divide 2 by zero"):
        list(parallel_map(_divide_task, [(1, 1), (2, 0)], 2))


def _divide_task(context, task):
    return _divide(*task)


@pytest.mark.parametrize("workers", [1, 2])
def test_start_map_collects_in_task_order_later(workers):
    with start_map(_divide_task, [(1, 2), (9, 3), (8, 4)], workers) as started:
        here = sum(range(10))  # this process goes on meanwhile
        assert started.results() == [0.5, 3.0, 2.0] and here == 45
    assert started.results() == [0.5, 3.0, 2.0]  # kept after the workers have stopped


def test_start_map_raises_a_worker_error_when_collected():
    started = start_map(_divide_task, [(1, 1), (3, 0)], 2)
    with pytest.raises(EstimationError, match="cannot divide 3 by zero"):
        started.results()


def test_nested_parallel_work_is_refused_in_a_worker():
    with pytest.raises(ParallelError):
        list(parallel_map(_nested, [0, 1], 2))


def _nested(context, task):
    return call_each([(_divide, (1.0, 1.0), {}), (_divide, (2.0, 1.0), {})], 2)


_UUID = re.compile(rb"[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}")


def _outputs(out: Path) -> dict[str, bytes]:
    """Every output file's bytes; metrics.json without its run times and the PnP mean
    reprojection RMS (a mean over localize's chunks: its last digit depends on their number,
    test_parallel), report.html without plotly's random element ids, no manifest (it hashes
    both)."""
    files = {}
    for p in sorted(out.iterdir()):
        if p.name in ("manifest.json", ".lock") or not p.is_file():
            continue
        data = p.read_bytes()
        if p.name == "metrics.json":
            m = _without_times(json.loads(data))
            m["estimator_stats"]["pnp"]["mean_reprojection_rms_px"] = round(
                m["estimator_stats"]["pnp"]["mean_reprojection_rms_px"], 12
            )
            data = json.dumps(m, sort_keys=True).encode()
        if p.name == "report.html":
            data = _UUID.sub(b"", data)
        files[p.name] = data
    return files


def _without_times(x):
    if isinstance(x, dict):
        return {
            k: _without_times(v)
            for k, v in x.items()
            if not (k.startswith("time_") or k in ("time_s", "realtime_factor"))
        }
    if isinstance(x, list):
        return [_without_times(v) for v in x]
    return x


def test_run_on_two_workers_writes_the_files_of_one_worker(tmp_path, monkeypatch):
    """The sample flight with the back ends, the windowed solves (smoother and mount: three
    small windows, as in test_window) on two processes (the figures are drawn in this one)."""
    monkeypatch.setattr(pipeline, "BACKEND_MIN_FRAMES", 0)
    monkeypatch.setattr(
        pipeline,
        "WindowConfig",
        lambda window_s: WindowConfig(window_s=window_s, overlap_s=0.3, min_flight_s=0.0),
    )
    runs = {}
    for workers in (1, 2):
        before = worker_usage().calls
        cfg = pipeline.RunConfig(workers=workers, progress=False, smoother_window_s=0.8)
        out = tmp_path / str(workers) / "out"  # the same folder name: report.html shows it
        res = pipeline.run(SAMPLE, out, cfg)
        assert not res.failures
        assert len(res.metrics["estimator_stats"]["smoother"]["windows"]) >= 2
        runs[workers] = (_outputs(out), worker_usage().calls - before)
    one, two = runs[1][0], runs[2][0]
    assert runs[1][1] == 0 and runs[2][1] >= 2 + 2 + 4  # smoother and mount windows, back ends
    assert one.keys() == two.keys() and any(name.endswith(".png") for name in one)
    assert [n for n in one if one[n] != two[n]] == []


def _sigterm_is_default(context, task: int) -> bool:
    import signal

    return signal.getsignal(signal.SIGTERM) == signal.SIG_DFL


def test_the_clis_signal_handler_does_not_reach_the_workers():
    """`fusion`'s SIGTERM handler (raise in the main thread) is this process's only: workers are
    fresh interpreters, so a SIGTERM sent to them still ends them."""
    from fusion.cli import _stop_on_signals

    with _stop_on_signals():
        assert list(parallel_map(_sigterm_is_default, [0, 1], 2)) == [True, True]
