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
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import multiprocessing as mp
import os
import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from itertools import repeat
from multiprocessing import forkserver
from multiprocessing.context import BaseContext
from typing import Any, TypeVar

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


def _start_worker(context: Any) -> None:
    global _WORKER_CONTEXT
    _WORKER_CONTEXT = context
    cv2.setNumThreads(1)  # one process per core already
    keep_freed_memory()


def _call(fn: Callable[[Any, T], R], task: T) -> R:
    return fn(_WORKER_CONTEXT, task)


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
    tasks = list(tasks)
    if workers <= 1 or len(tasks) <= 1:
        for task in tasks:
            yield fn(context, task)
        return
    if mp.current_process().name != "MainProcess":
        raise ParallelError(
            "parallel work started inside a worker process; guard the calling "
            "script with `if __name__ == '__main__':` or use one worker"
        )
    ctx = _forkserver_context(preload) or mp.get_context("spawn")
    n = min(workers, len(tasks))
    logger.debug(
        "parallel_map %s: %d tasks on %d %s workers",
        getattr(fn, "__name__", fn),
        len(tasks),
        n,
        ctx.get_start_method(),
    )
    try:
        with ProcessPoolExecutor(n, mp_context=ctx, initializer=_start_worker, initargs=(context,)) as pool:
            yield from pool.map(_call, repeat(fn), tasks)
    except BrokenProcessPool:
        raise ParallelError(
            "a worker process died; when calling fusion with several workers from a script, "
            "run it under `if __name__ == '__main__':` (the workers import the main module), "
            "or use one worker"
        ) from None
