"""The one way `fusion` runs work on several processes (simulate, detect, localize).

`parallel_map(fn, tasks, workers, context)` yields `fn(context, task)` for every task, in task
order.  `context` (cameras, world, configuration: whatever every task needs) is sent once to each
worker process; the tasks carry only their own slice of the work.  Workers start with
multiprocessing's "forkserver" method (else "spawn"), never "fork": forking a process that runs
threads (OpenCV, BLAS, a test runner) can deadlock a child on a lock copied in the held state.
So `fn` must be a module-level function, and a script that calls this with workers > 1 needs the
usual `if __name__ == "__main__":` guard.  With workers <= 1 (or a single task) everything runs
in this process, which is what the tests compare the parallel path against.

The forkserver starts once per process, with the first call's `preload`, and imports those
modules once; every worker forks from it.  It also imports every `fusion` module this process
has imported by then (`_preload_modules`): a worker re-runs the main module (multiprocessing's
`__mp_main__`, e.g. the `fusion` script or a bench script) and unpickles its context and
function, and without them in the forkserver each worker imported them again (measured: ~2.5 CPU
s a worker for `fusion.pipeline`, 6 workers a `fusion run`; BENCHMARKS.md).

`call_each(calls, workers)` runs a few different calls at once (the back ends of `fuse_stage`)
and gives back each one's value or exception, so that one failing does not cost the others.
A function that cannot be sent to a worker (a test's or a bench's wrapper: a closure) makes the
batch run in this process instead (`sendable`).

A worker's log records reach this process's loggers (a queue, `_forward_logs`): warnings and
notes logged inside a worker are handled (printed, captured by a test) as if logged here.  The
CPU seconds of the work done in workers are summed in `worker_usage()` (this process's
`time.process_time` does not see them), with the largest worker's peak RSS and, per pool, its
busiest worker's CPU (`WorkerUsage.longest_cpu_s`).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import logging
import logging.handlers
import multiprocessing as mp
import os
import pickle
import resource
import sys
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from itertools import repeat
from multiprocessing import forkserver
from multiprocessing.context import BaseContext
from typing import Any, Generic, TypeVar

import cv2
import numpy as np

from fusion.errors import FusionError

logger = logging.getLogger(__name__)

T = TypeVar("T")
R = TypeVar("R")


class ParallelError(FusionError):
    """A worker process died or could not start."""


_WORKER_CONTEXT: Any = None  # set in each worker process by _start_worker, read by _call only

# glibc's malloc returns the top of its heap to the system whenever more than M_TRIM_THRESHOLD
# (128 KiB by default) is free there, and serves blocks above M_MMAP_THRESHOLD (128 KiB, then
# adapting) with fresh mappings: numpy's temporaries of a few hundred KiB (refinement's arrays,
# a decoded 640x480 frame) were then given back and faulted in again on every operation.
# Measured (scripts/bench_frontend_speed.py, BENCHMARKS.md): refinement ~35 % less CPU
# with the two thresholds raised.  The cost: up to MALLOC_TRIM_THRESHOLD_BYTES of freed memory
# stays with the process.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc <malloc.h> mallopt parameters
MALLOC_TRIM_THRESHOLD_BYTES = 128 << 20
MALLOC_MMAP_THRESHOLD_BYTES = 32 << 20  # glibc's largest accepted value on 64-bit systems
_MALLOC_TUNED: bool | None = None


def keep_freed_memory() -> bool:
    """Raise this process's glibc malloc trim and mmap thresholds (comment above), once; True
    when they are set, False where there is no glibc `mallopt` (macOS, musl: nothing changes)."""
    global _MALLOC_TUNED
    if _MALLOC_TUNED is None:
        _MALLOC_TUNED = False
        try:
            mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt
        except (OSError, AttributeError, TypeError):
            return False
        mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
        _MALLOC_TUNED = bool(
            mallopt(_M_MMAP_THRESHOLD, MALLOC_MMAP_THRESHOLD_BYTES)
            and mallopt(_M_TRIM_THRESHOLD, MALLOC_TRIM_THRESHOLD_BYTES)
        )
        logger.debug("malloc thresholds raised: %s", _MALLOC_TUNED)
    return _MALLOC_TUNED


@dataclass
class WorkerUsage:
    """What the work done in worker processes cost: CPU seconds (each worker's process time
    since it was forked: its start, unpickling its context, its calls), calls, and the largest
    peak RSS (MB, VmHWM: imports and context included) of any worker.
    `longest_cpu_s`: per pool, the CPU seconds of its busiest worker, summed over pools: the
    time this process waited for them on an idle machine, roughly (a loaded machine's wall time
    says little; the benches report both)."""

    cpu_s: float = 0.0
    calls: int = 0
    peak_rss_mb: float = 0.0
    longest_cpu_s: float = 0.0


_USAGE = WorkerUsage()


def worker_usage() -> WorkerUsage:
    """The workers' usage summed since this process started (a copy: subtract two readings)."""
    return replace(_USAGE)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


class _Dispatch(logging.Handler):
    """Hands a worker's record to this process's logger of the same name (its level was checked
    in the worker; this process's handlers, filters and propagation apply)."""

    def emit(self, record: logging.LogRecord) -> None:
        logging.getLogger(record.name).handle(record)


def _log_levels() -> dict[str, int]:
    """The effective levels of the root and package loggers here, for the workers to drop what
    this process would (records below them are not sent)."""
    root = __name__.split(".")[0]
    return {"": logging.getLogger().getEffectiveLevel(), root: logging.getLogger(root).getEffectiveLevel()}


def _forward_logs(queue: Any, levels: dict[str, int]) -> None:
    """In a worker: every record goes to `queue` (the main process's _Dispatch) and nowhere else."""
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(logging.handlers.QueueHandler(queue))
    for name, level in levels.items():
        logging.getLogger(name or None).setLevel(level)


def _start_worker(context: Any, log_queue: Any = None, levels: dict[str, int] | None = None) -> None:
    global _WORKER_CONTEXT
    _WORKER_CONTEXT = context
    if log_queue is not None:
        _forward_logs(log_queue, levels or {})
    cv2.setNumThreads(1)  # one process per core already
    keep_freed_memory()


def _call(fn: Callable[[Any, T], R], task: T) -> tuple[R, tuple[float, float, int]]:
    """fn(context, task) in a worker, with the worker's CPU seconds so far (since it was
    forked: its start, the context's unpickling and every call), its peak RSS and process id."""
    out = fn(_WORKER_CONTEXT, task)
    return out, (time.process_time(), _peak_rss_mb(), os.getpid())


class _Tally:
    """The workers' usage of one pool, added to _USAGE as each call's result arrives."""

    def __init__(self) -> None:
        self.by_worker: dict[int, float] = {}

    def add(self, usage: tuple[float, float, int]) -> None:
        cpu_s, peak_mb, pid = usage  # the worker's CPU so far
        _USAGE.cpu_s += cpu_s - self.by_worker.get(pid, 0.0)
        _USAGE.calls += 1
        _USAGE.peak_rss_mb = max(_USAGE.peak_rss_mb, peak_mb)
        before = max(self.by_worker.values(), default=0.0)
        self.by_worker[pid] = cpu_s
        _USAGE.longest_cpu_s += max(self.by_worker.values()) - before


def sendable(*objs: Any) -> bool:
    """True when every object pickles (a module-level function does; a closure, e.g. a test's
    monkeypatched wrapper, does not, and then the work stays in this process)."""
    try:
        for obj in objs:
            pickle.dumps(obj)
    except Exception:
        return False
    return True


def worker_count(requested: int | None) -> int:
    """`requested` processes, at least 1; None: one per core."""
    return (os.cpu_count() or 1) if requested is None else max(1, int(requested))


def chunk_bounds(n_items: int, n_chunks: int) -> list[tuple[int, int]]:
    """[start, stop) of `n_chunks` contiguous, nearly equal chunks covering range(n_items);
    empty chunks are left out."""
    bounds = np.linspace(0, n_items, max(1, n_chunks) + 1).astype(int)
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def _preload_modules(preload: Sequence[str]) -> list[str]:
    """`preload` and then every module of this package that this process has imported (what a
    worker would import again when it unpickles its function and context or re-runs the main
    module), for the forkserver to import once."""
    root = __name__.split(".")[0]
    imported = sorted(m for m in sys.modules if m == root or m.startswith(root + "."))
    return list(dict.fromkeys([*preload, *imported]))


def _forkserver_context(preload: Sequence[str]) -> BaseContext | None:
    if "forkserver" not in mp.get_all_start_methods():
        return None
    ctx = mp.get_context("forkserver")
    # (ignored once the forkserver runs: it started with an earlier call's modules)
    ctx.set_forkserver_preload(_preload_modules(preload))
    return ctx


def start_workers_early(preload: Sequence[str] = ()) -> None:
    """Start the forkserver now, so that it imports its modules (`parallel_map`'s `preload` and
    this package's imported modules: ~3 CPU s for the pipeline's) while this process goes on
    (e.g. reads the flight log) instead of when the first pool starts.  Nothing happens in a
    worker process or where there is no forkserver."""
    if mp.current_process().name != "MainProcess" or _forkserver_context(preload) is None:
        return
    forkserver.ensure_running()


def parallel_map(
    fn: Callable[[Any, T], R],
    tasks: Iterable[T],
    workers: int,
    context: Any = None,
    preload: Sequence[str] = (),
) -> Iterator[R]:
    """Yield fn(context, task) for each task, in order, on `workers` processes.

    `preload`: modules the forkserver imports once, so that workers fork from it ready to run
    (with the package's modules already imported here; module docstring).
    Raises ParallelError when called with workers > 1 inside a worker process (an unguarded
    main script being re-imported) or when a worker dies."""
    if workers <= 1:  # one task at a time, each made when it is reached
        for task in tasks:
            yield fn(context, task)
        return
    tasks = list(tasks)
    if len(tasks) <= 1:
        for task in tasks:
            yield fn(context, task)
        return
    if mp.current_process().name != "MainProcess":
        raise ParallelError(
            "parallel work started inside a worker process; guard the calling "
            "script with `if __name__ == '__main__':` or use one worker"
        )
    n = min(workers, len(tasks))
    logger.debug("parallel_map %s: %d tasks on %d workers", getattr(fn, "__name__", fn), len(tasks), n)
    tally = _Tally()
    with _pool(n, context, preload) as pool:
        try:
            for out, usage in pool.map(_call, repeat(fn), tasks):
                tally.add(usage)
                yield out
        except BrokenProcessPool:
            raise _died() from None


def _died() -> ParallelError:
    return ParallelError(
        "a worker process died; when calling fusion with several workers from a script, "
        "run it under `if __name__ == '__main__':` (the workers import the main module), "
        "or use one worker"
    )


@contextlib.contextmanager
def _pool(n: int, context: Any, preload: Sequence[str]) -> Iterator[ProcessPoolExecutor]:
    """A pool of `n` forkserver (else spawn) workers holding `context`, their log records
    forwarded here while it is open (the listener stops after the workers have exited, so
    none is lost)."""
    ctx = _forkserver_context(preload) or mp.get_context("spawn")
    queue = ctx.Queue()
    listener = logging.handlers.QueueListener(queue, _Dispatch())
    listener.start()
    try:
        with ProcessPoolExecutor(
            n, mp_context=ctx, initializer=_start_worker, initargs=(context, queue, _log_levels())
        ) as pool:
            yield pool
    finally:
        listener.stop()
        queue.close()
        queue.join_thread()


class Started(Generic[R]):
    """A `start_map`: its results, in task order, when `results()` is called; use as a context
    manager (leaving it, e.g. on an error in between, stops the workers)."""

    def __init__(self, values: list[R] | None = None) -> None:
        self._values = values
        self._futures: list = []
        self._stack = contextlib.ExitStack()

    def results(self) -> list[R]:
        if self._values is None:
            try:
                values = []
                tally = _Tally()
                for f in self._futures:
                    try:
                        out, usage = f.result()
                    except BrokenProcessPool:
                        raise _died() from None
                    tally.add(usage)
                    values.append(out)
                self._values = values
            finally:
                self.close()
        return self._values

    def close(self) -> None:
        for f in self._futures:
            f.cancel()
        self._stack.close()

    def __enter__(self) -> Started[R]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def start_map(
    fn: Callable[[Any, T], R],
    tasks: Iterable[T],
    workers: int,
    context: Any = None,
    preload: Sequence[str] = (),
) -> Started[R]:
    """`parallel_map` started in the background: the tasks run on the workers while this process
    does something else, until `results()` of the returned Started collects them.  With
    workers <= 1 or a single task they run here, now (in order, before this returns)."""
    tasks = list(tasks)
    if workers <= 1 or len(tasks) <= 1:
        return Started([fn(context, task) for task in tasks])
    if mp.current_process().name != "MainProcess":
        raise ParallelError("parallel work started inside a worker process; use one worker")
    started: Started[R] = Started()
    try:
        pool = started._stack.enter_context(_pool(min(workers, len(tasks)), context, preload))
        started._futures = [pool.submit(_call, fn, task) for task in tasks]
    except BaseException:
        started.close()
        raise
    return started


@dataclass
class Outcome(Generic[R]):
    """One call's value, or the exception it raised (re-raised by `get`)."""

    value: R | None = None
    error: BaseException | None = None

    def get(self) -> R:
        if self.error is not None:
            raise self.error
        return self.value  # type: ignore[return-value]


def _call_one(context: Any, call: tuple[Callable[..., R], tuple, dict]) -> R:
    fn, args, kwargs = call
    return fn(*args, **kwargs)


def call_each(
    calls: Sequence[tuple[Callable[..., Any], tuple, dict]], workers: int, preload: Sequence[str] = ()
) -> list[Outcome]:
    """fn(*args, **kwargs) of every (fn, args, kwargs) in `calls`, at once on up to `workers`
    processes; each call's Outcome in call order.  An exception (Exception, not BaseException)
    of one call is its Outcome's error (in a worker: pickled back, the worker's traceback as its
    __cause__) and does not stop the others.  Runs in this process, in order, with workers <= 1,
    a single call, or a function that cannot be sent (`sendable`)."""
    calls = list(calls)
    if workers > 1 and len(calls) > 1 and not sendable(*(fn for fn, _, _ in calls)):
        logger.debug("call_each: a function cannot be sent to a worker: running here")
        workers = 1
    if workers <= 1 or len(calls) <= 1:
        out: list[Outcome] = []
        for fn, args, kwargs in calls:
            try:
                out.append(Outcome(fn(*args, **kwargs)))
            except Exception as e:
                out.append(Outcome(error=e))
        return out
    if mp.current_process().name != "MainProcess":
        raise ParallelError("parallel work started inside a worker process; use one worker")
    outcomes: list[Outcome] = []
    tally = _Tally()
    with _pool(min(workers, len(calls)), None, preload) as pool:
        futures = [pool.submit(_call, _call_one, call) for call in calls]
        for f in futures:
            try:
                value, usage = f.result()
            except BrokenProcessPool:
                outcomes.append(Outcome(error=_died()))
            except Exception as e:
                outcomes.append(Outcome(error=e))
            else:
                tally.add(usage)
                outcomes.append(Outcome(value))
    return outcomes
