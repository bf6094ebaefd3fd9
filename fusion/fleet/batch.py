"""`run_batch(flights, out, cfg)`: many flights on a dask.distributed cluster, each into
`OUT/<flight>/` exactly as `fusion run` writes it, then the fleet summary (fleet.csv, fleet.md).

Each flight is a task graph (fusion.fleet.tasks):

    open -> plan -> detect chunk x N (frame ranges of each camera, spread over the cluster)
                        |-- cam0 chunk -> floor estimators (paper, pnp) -> merge --|
                        |-- cam1 chunk -> load observations (needs the merge) -----|--> report
                                                     (fusion, metrics, report: pipeline.run)

so a long flight's detection and per-frame estimation use every worker, and flights overlap
(earlier flights first: each flight's tasks carry its priority).  The driver (this process)
only submits tasks and watches them; the flight data stays on the cluster, which therefore
needs the logs and OUT at the same paths on every worker (a shared file system).  The detection
chunks, the merged floor result and the front parts reach the report task as files under
OUT/.parts/<flight>-a<attempt>/ (fusion.fleet.parts), so that Dask does not hold them as the
report task's arguments while it runs; OUT/.parts is removed when a batch starts and ends.

Resumable: a flight whose OUT/<flight>/manifest.json says complete is skipped; a flight that
failed (fleet.json) is skipped unless `retry_failed`.  A failing flight is recorded with its
reason and never stops the others.  A worker that dies while running a flight's task costs that
flight one retry (the whole graph again); a second death marks it failed.  The local cluster's
scheduler is started with `allowed-failures` 0, so the retry is ours; an external scheduler
first re-runs the task on its own, up to its `distributed.scheduler.allowed-failures` (3 by
default), before we see the worker death.  (Dask's `retries=` applies to tasks that raise,
not to worker deaths, and our tasks' exceptions are deterministic: bad input stays bad.)
"""

from __future__ import annotations

import contextlib
import logging
import time
import traceback
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import dask
from distributed import Client, Future, LocalCluster, as_completed
from distributed.scheduler import KilledWorker

from fusion.errors import FleetError, FusionError, OutputError, first_line
from fusion.fileio import RUN_WRITER, DirLock, manifest_writer, read_manifest
from fusion.fleet import tasks
from fusion.fleet.flights import (
    FlightRecord,
    FlightStatus,
    expand_flights,
    output_names,
    read_state,
    write_state,
)
from fusion.fleet.parts import parts_folder, parts_root, remove_parts
from fusion.fleet.summary import write_summary
from fusion.parallel import worker_count
from fusion.pipeline import RunConfig

logger = logging.getLogger(__name__)

DEFAULT_CHUNK_FRAMES = 256
"""Frames of one camera per detection task: ~2 s of work at ~7 ms a frame, long enough that
dask's per-task cost (~1 ms) is noise, short enough that a 2-minute flight spreads over ~28 tasks."""
CONNECT_TIMEOUT_S = 5.0
MAX_ATTEMPTS = 2  # a worker death retries the flight once
LOCAL_ALLOWED_FAILURES = 0  # local scheduler: a worker death fails the task at once, we retry
LOCAL_MALLOC_ARENAS = 1
"""glibc malloc arenas of a local worker (MALLOC_ARENA_MAX): the tasks run on the worker's
executor thread, whose own arena (64 MiB heaps, trimmed only at their tops) is where the report
task's freed memory stayed resident (measured: BENCHMARKS.md, tenth session, `batchmem`)."""

LOCAL_PROFILER = False
"""Dask's statistical profiler in local workers (`distributed.worker.profile.enabled`): off, as
its sampled stacks of the flight's long report task cost ~54 MiB of that worker's peak."""


@dataclass
class BatchConfig:
    """Choices of a batch; defaults are what `fusion batch` uses."""

    scheduler: str | None = None  # address of a running dask scheduler; None: a LocalCluster
    workers: int | None = None  # LocalCluster processes (None: one per core)
    retry_failed: bool = False  # run again the flights fleet.json records as failed
    chunk_frames: int = DEFAULT_CHUNK_FRAMES
    connect_timeout_s: float = CONNECT_TIMEOUT_S
    max_attempts: int = MAX_ATTEMPTS
    run: RunConfig = field(default_factory=RunConfig)  # per flight; workers/progress/force are set here


@dataclass
class BatchResult:
    """Every flight of OUT (this batch's and earlier ones'), the summary's paths, and what this
    batch ran and skipped."""

    out_dir: Path
    records: list[FlightRecord]
    ran: list[str]
    skipped: list[str]
    summary_paths: list[Path]
    wall_s: float

    @property
    def failed(self) -> list[FlightRecord]:
        return [r for r in self.records if r.status == FlightStatus.FAILED]

    def summary(self) -> str:
        ok = sum(r.status == FlightStatus.OK for r in self.records)
        lines = [
            f"fleet: {len(self.records)} flights in {self.out_dir}: {ok} ok, {len(self.failed)} failed; "
            f"this batch ran {len(self.ran)} and skipped {len(self.skipped)} (finished or failed before) "
            f"in {self.wall_s:.1f} s"
        ]
        lines += [f"FAILED {r.name}: {r.reason}" for r in self.failed]
        lines += [f"summary: {p}" for p in self.summary_paths]
        return "\n".join(lines)


def run_batch(flights: list[Path], out: Path, cfg: BatchConfig | None = None) -> BatchResult:
    """Run `flights` (logs, or text files listing them) into `out` on a dask cluster.

    FleetError: OUT locked by another batch, an unreachable scheduler, an unreadable list or
    fleet.json.  A flight's own failure is recorded, not raised."""
    cfg = cfg or BatchConfig()
    t0 = time.perf_counter()
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise FleetError(f"{out}: cannot create the fleet folder ({e.strerror})") from None
    lock = DirLock(out, FleetError)
    lock.acquire()
    try:
        state = read_state(out)
        paths = expand_flights(flights)
        names = output_names(paths, state)
        todo: list[FlightRecord] = []
        skipped: list[str] = []
        for p in paths:
            name = names[p]
            rec = state.setdefault(name, FlightRecord(name, str(p)))
            if _complete(out / name):
                rec.status, rec.reason, rec.error_type = FlightStatus.OK, "", ""
                skipped.append(name)
            elif rec.status == FlightStatus.FAILED and not cfg.retry_failed:
                skipped.append(name)
            else:
                rec.status, rec.reason, rec.error_type, rec.attempts = "", "", "", 0
                todo.append(rec)
        write_state(out, state)
        for name in skipped:
            logger.info("%s: skipped (%s before)", name, state[name].status)
        if todo:
            # task results of an earlier batch that stopped (the lock says none is running)
            remove_parts(parts_root(out))
            try:
                with connect(cfg) as client:
                    _Driver(client, out, cfg, state, todo).run()
            finally:
                remove_parts(parts_root(out))
        wall = time.perf_counter() - t0
        summary_paths = write_summary(out, list(state.values()))
        return BatchResult(out, list(state.values()), [r.name for r in todo], skipped, summary_paths, wall)
    finally:
        lock.release()


def _complete(folder: Path) -> bool:
    """True when `folder` holds a finished `fusion run` (its manifest says complete; a flight
    log's complete manifest is not a run: that flight runs, and its run refuses the folder)."""
    try:
        manifest = read_manifest(folder, OutputError)
    except OutputError:
        return False
    return (
        manifest is not None
        and manifest_writer(manifest) == RUN_WRITER
        and manifest.get("status") == "complete"
    )


# ============================================================================ cluster


@contextlib.contextmanager
def connect(cfg: BatchConfig) -> Iterator[Client]:
    """A client of the scheduler at `cfg.scheduler`, or of a LocalCluster of `cfg.workers`
    single-threaded processes (GTSAM and zxing hold the GIL for parts of their work, so
    processes, not threads).  FleetError within `connect_timeout_s` when the scheduler does not
    answer."""
    if cfg.scheduler:
        if cfg.workers is not None:
            logger.warning("--workers sizes a local cluster; ignored with a scheduler (%s)", cfg.scheduler)
        try:
            client = Client(cfg.scheduler, timeout=cfg.connect_timeout_s, set_as_default=False)
        except (OSError, TimeoutError, ValueError, TypeError) as e:
            raise FleetError(
                f"cannot reach the dask scheduler at {cfg.scheduler} within {cfg.connect_timeout_s:g} s "
                f"({type(e).__name__}); is `dask scheduler` running there, and the port open?"
            ) from None
        logger.info("connected to %s (%d workers)", cfg.scheduler, len(client.scheduler_info()["workers"]))
        try:
            yield client
        finally:
            client.close()
        return
    n = worker_count(cfg.workers)
    with dask.config.set(
        {
            "distributed.scheduler.allowed-failures": LOCAL_ALLOWED_FAILURES,
            "distributed.nanny.pre-spawn-environ.MALLOC_ARENA_MAX": LOCAL_MALLOC_ARENAS,
            # the statistical profiler's samples of a long report task: ~54 MiB of its worker's
            # peak (BENCHMARKS.md, twelfth session, batchmem3); the dashboard loses its profile
            "distributed.worker.profile.enabled": LOCAL_PROFILER,
        }
    ):
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=_dashboard_address(),
            # a failed flight is the batch's to report (fleet.md, its FAILED line): no worker
            # "Compute Failed" traceback of a FusionError on stderr
            silence_logs=logging.CRITICAL,
        )
    try:
        client = Client(cluster, set_as_default=False)
        logger.info("local dask cluster: %d worker processes%s", n, _dashboard_note(client))
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def _dashboard_address() -> str | None:
    """A free port for the dashboard when bokeh is installed (it serves the dashboard), else none."""
    try:
        import bokeh  # noqa: F401
    except ImportError:
        return None
    return ":0"


def _dashboard_note(client: Client) -> str:
    link = getattr(client, "dashboard_link", None) if _dashboard_address() else None
    return f"; dashboard {link}" if link else ""


# ============================================================================ driver


@dataclass
class _Flight:
    """The driver's view of one flight being run."""

    rec: FlightRecord
    priority: int
    # the log's, the plan's and the report's: the cluster keeps the other tasks' results only
    # while a task that needs them waits (a floor part until the merge, the front context
    # until the last front chunk)
    futures: list[Future] = field(default_factory=list)
    report: Future | None = None
    chunk_frames: dict[Any, int] = field(default_factory=dict)  # detect task key -> frames
    frames_done: int = 0
    n_frames: int = 0
    t_start: float = 0.0


class _Driver:
    """Submits each flight's graph, watches its tasks complete, records outcomes."""

    def __init__(self, client: Client, out: Path, cfg: BatchConfig, state: dict, todo: list[FlightRecord]):
        self.client = client
        self.out = out
        self.cfg = cfg
        self.state = state
        self.run_cfg = replace(cfg.run, workers=1, progress=False, force=True)
        self.flights = [_Flight(rec, len(todo) - i) for i, rec in enumerate(todo)]
        self.by_key: dict[Any, tuple[_Flight, str]] = {}  # watched future key -> (flight, role)
        self.ac = as_completed(loop=client.loop)
        self.frames_total = 0
        self.frames_done = 0
        self.done = 0

    def run(self) -> None:
        for fl in self.flights:
            self._submit_plan(fl)
        for fut in self.ac:
            owner = self.by_key.pop(fut.key, None)
            if owner is None:  # a task of an abandoned attempt
                continue
            fl, role = owner
            if fut.status == "finished":
                getattr(self, f"_on_{role}")(fl, fut)
            elif fut.status == "error":
                if role != "detect":  # a detect error reaches the report task too
                    self._on_error(fl, fut)
            # "cancelled": only ours, when a flight is retried or given up

    # ------------------------------------------------------------------ submitting

    def _key(self, fl: _Flight, what: str) -> str:
        return f"{what}-{fl.rec.name}-a{fl.rec.attempts}"

    def _submit(
        self, fl: _Flight, key: str, fn, *args, hold: bool = False, workers: list[str] | None = None
    ) -> Future:
        """`fn(*args)` on the cluster; with `hold`, the flight keeps its future (see _Flight);
        `workers`: where to run it if one of them can (others may take it)."""
        where: dict[str, Any] = {"workers": workers, "allow_other_workers": True} if workers else {}
        fut = self.client.submit(fn, *args, key=key, priority=fl.priority, pure=False, retries=0, **where)
        if hold:
            fl.futures.append(fut)
        return fut

    def _watch(self, fl: _Flight, fut: Future, role: str) -> None:
        self.by_key[fut.key] = (fl, role)
        self.ac.add(fut)

    def _submit_plan(self, fl: _Flight) -> None:
        fl.rec.attempts += 1
        fl.t_start = time.perf_counter()
        log = self._submit(fl, self._key(fl, "open"), tasks.open_flight_task, fl.rec.path, hold=True)
        plan = self._submit(fl, self._key(fl, "plan"), tasks.plan_task, log, self.cfg.chunk_frames, hold=True)
        self._watch(fl, plan, "plan")

    def _on_plan(self, fl: _Flight, fut: Future) -> None:
        plan: tasks.FlightPlan = fut.result()
        fl.rec.duration_s, fl.rec.n_frames = plan.duration_s, plan.n_frames
        if fl.n_frames == 0:
            fl.n_frames = plan.n_frames
            self.frames_total += plan.n_frames
        log = fl.futures[0]
        cfg = self.run_cfg
        report_at, merge_at = self._placement(log)
        parts = str(parts_folder(self.out, fl.rec.name, fl.rec.attempts))
        detected, floor, front = [], [], []
        for i, chunk in enumerate(plan.chunks):
            d = self._submit(
                fl,
                self._key(fl, f"detect{i:04d}"),
                tasks.detect_task,
                log,
                chunk,
                cfg.backend,
                parts,
                i,
            )
            fl.chunk_frames[d.key] = chunk[2] - chunk[1]
            self._watch(fl, d, "detect")
            detected.append((chunk[0], d))
        for i, (camera, d) in enumerate(detected):
            if camera == tasks.FLOOR:
                floor.append(self._submit(fl, self._key(fl, f"floor{i:04d}"), tasks.floor_task, log, d, cfg))
        merged = self._submit(
            fl, self._key(fl, "merge"), tasks.merge_floor_task, cfg, parts, *floor, workers=merge_at
        )
        if any(camera == tasks.FRONT for camera, _ in detected):
            context = self._submit(
                fl, self._key(fl, "frontctx"), tasks.front_context_task, log, merged, cfg, workers=merge_at
            )
            for i, (camera, d) in enumerate(detected):
                if camera == tasks.FRONT:
                    front.append(
                        self._submit(
                            fl, self._key(fl, f"front{i:04d}"), tasks.front_task, context, d, parts, i
                        )
                    )
        report = self._submit(
            fl,
            self._key(fl, "report"),
            tasks.report_task,
            log,
            str(self.out / fl.rec.name),
            parts,
            cfg,
            len(detected),
            *(d for _, d in detected),
            merged,
            *front,
            hold=True,
            workers=report_at,
        )
        fl.report = report
        self._watch(fl, report, "report")
        logger.info(
            "%s: %d frames, %.1f s of flight, %d detection tasks",
            fl.rec.name,
            plan.n_frames,
            plan.duration_s,
            len(plan.chunks),
        )

    def _placement(self, log: Future) -> tuple[list[str] | None, list[str] | None]:
        """(where the report task should run, where the merge and the front context should):
        the report on a worker holding the flight's log (Dask would put it there for the log's
        bytes anyway), the merge and the front context on the others.  Those two hold every
        floor chunk's result and the merged one at once, and the heap they free stays with
        their worker's process (glibc): on the report's worker it lay under the report task's
        own peak (BENCHMARKS.md, mem14).  (None, None) with one worker or when the log's
        place is not known: Dask's own choice."""
        try:
            holders = list(self.client.who_has([log]).get(log.key, ()))
            workers = list(self.client.scheduler_info()["workers"])
        except (OSError, TimeoutError, KeyError):
            return None, None
        others = [w for w in workers if w not in holders]
        if not holders or not others:
            return None, None
        return holders[:1], others

    # ------------------------------------------------------------------ outcomes

    def _on_detect(self, fl: _Flight, fut: Future) -> None:
        n = fl.chunk_frames.get(fut.key, 0)
        fl.frames_done += n
        self.frames_done += n
        logger.info(
            "%s: %d/%d frames detected | fleet: %d/%d frames, %d/%d flights done",
            fl.rec.name,
            min(fl.frames_done, fl.n_frames),
            fl.n_frames,
            min(self.frames_done, self.frames_total),
            self.frames_total,
            self.done,
            len(self.flights),
        )

    def _on_report(self, fl: _Flight, fut: Future) -> None:
        done: tasks.FlightDone = fut.result()
        rec = fl.rec
        rec.status, rec.reason, rec.error_type = FlightStatus.OK, "", ""
        rec.compute_s = done.compute_s
        rec.timings_s = done.timings_s
        rec.task_s = done.task_s
        rec.wall_s = time.perf_counter() - fl.t_start
        self._finish(fl, f"ok in {rec.wall_s:.1f} s ({rec.compute_s:.1f} task-s)")

    def _on_error(self, fl: _Flight, fut: Future) -> None:
        exc = fut.exception()
        rec = fl.rec
        if isinstance(exc, KilledWorker) and rec.attempts < self.cfg.max_attempts:
            logger.warning("%s: a worker died running %s; running the flight again", rec.name, _task(exc))
            self._abandon(fl, retry=True)
            self._submit_plan(fl)
            return
        rec.status, rec.error_type = FlightStatus.FAILED, type(exc).__name__
        rec.reason = _reason(exc, rec.attempts)
        if not isinstance(exc, (FusionError, KilledWorker)):
            logger.debug("%s: traceback\n%s", rec.name, "".join(_traceback(fut)))
        self._abandon(fl, retry=False)
        self._finish(fl, f"FAILED: {rec.reason}")

    def _abandon(self, fl: _Flight, retry: bool) -> None:
        """Cancel the flight's tasks (and forget its detected frames when it runs again).

        Only keys every task depending on which is wanted can be cancelled (distributed's
        `stimulus_cancel` walks the dependents and asserts that each has a client): before the
        plan, the log's and the plan's; after it, the report's, a leaf, and the rest are let go
        (nothing wants them any more, so the scheduler releases them; a detection task
        already running finishes, as_completed holding it until then)."""
        for key in [k for k, (f, _) in self.by_key.items() if f is fl]:
            del self.by_key[key]
        self.client.cancel(fl.futures if fl.report is None else [fl.report])
        fl.futures.clear()
        fl.report = None
        fl.chunk_frames.clear()
        # a task of this attempt still running may write here again: run_batch removes OUT/.parts at its end
        remove_parts(parts_folder(self.out, fl.rec.name, fl.rec.attempts))
        if retry:
            self.frames_done -= fl.frames_done
            fl.frames_done = 0

    def _finish(self, fl: _Flight, what: str) -> None:
        self.done += 1
        if fl.rec.status == FlightStatus.OK:
            fl.futures.clear()  # the cluster may drop this flight's data
            fl.report = None
        write_state(self.out, self.state)
        log = logger.info if fl.rec.status == FlightStatus.OK else logger.warning
        log("%s: %s | fleet: %d/%d flights done", fl.rec.name, what, self.done, len(self.flights))


def _task(exc: KilledWorker) -> str:
    return str(getattr(exc, "task", "a task"))


def _reason(exc: BaseException, attempts: int) -> str:
    """One line: a known error's message; else what happened."""
    if isinstance(exc, KilledWorker):
        return f"a worker died running {_task(exc)} on each of {attempts} attempts"
    if isinstance(exc, FusionError):
        return first_line(exc) if str(exc).strip() else ""
    return f"internal error: {type(exc).__name__}: {first_line(exc)}"


def _traceback(fut: Future) -> list[str]:
    tb: Any = fut.traceback()
    return traceback.format_tb(tb) if tb is not None else []
