"""Task results handed to a flight's report task through files, not through Dask's memory.

Dask keeps a running task's arguments in its worker's data store for the task's whole duration,
so the report task could not let go of the detection chunks, the merged floor result and the
front parts it consumes (on a 30-minute flight: ~130,000 detections packed, 54,001 per-frame
poses with covariances twice).  The tasks that make them write each one to a file under
OUT/.parts/<flight>-a<attempt>/ and return a `PartFile`, a handle of a few hundred bytes; the
report task reads the parts one by one and drops each once it is merged.

The files are pickles written and read by this batch's own tasks (the same bytes Dask would have
sent between its workers); a file is written under a temporary name and renamed, so a reader
never sees half a file.  `run_batch` removes OUT/.parts when it starts (under the fleet lock: no
other batch can be using it) and when it ends; the report task removes its flight's folder as
soon as the flight's outputs are written.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fusion.errors import FleetError

PARTS_DIR = ".parts"


@dataclass(frozen=True)
class PartFile:
    """Where one task's result was written and its size in bytes."""

    path: str
    nbytes: int


def parts_root(out: Path) -> Path:
    """OUT/.parts: every flight's parts folder."""
    return Path(out) / PARTS_DIR


def parts_folder(out: Path, flight: str, attempt: int) -> Path:
    """The folder of one attempt of a flight: a task of an abandoned attempt that is still
    running when the flight runs again writes into its own attempt's folder, never into the
    new one's."""
    return parts_root(out) / f"{flight}-a{attempt}"


def write_part(folder: str | Path, name: str, value: Any) -> PartFile:
    """`value` pickled to folder/name.pkl (through a temporary file, renamed when complete).

    FleetError naming the file when it cannot be written (full disk, no permission)."""
    path = Path(folder) / f"{name}.pkl"
    tmp = path.with_name(f"{path.name}.tmp{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            pickle.dump(value, f, protocol=pickle.HIGHEST_PROTOCOL)
        os.replace(tmp, path)
        nbytes = path.stat().st_size
    except OSError as e:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise FleetError(f"{path}: cannot write a task's result ({e.strerror or e})") from None
    return PartFile(str(path), nbytes)


def read_part(part: PartFile) -> Any:
    """The value `write_part` wrote.  FleetError naming the file when it is gone or unreadable
    (removed while the batch ran, or a file system the workers do not share)."""
    try:
        with open(part.path, "rb") as f:
            return pickle.load(f)
    except OSError as e:
        raise FleetError(
            f"{part.path}: cannot read a task's result ({e.strerror or e}); "
            "do all workers see OUT at the same path?"
        ) from None
    except (pickle.UnpicklingError, EOFError) as e:
        raise FleetError(f"{part.path}: a task's result is damaged ({type(e).__name__})") from None


def remove_parts(folder: Path) -> None:
    """Remove a parts folder and what is in it (absent: nothing to do; a file in its place is
    removed too: the name is the batch's)."""
    if Path(folder).is_dir():
        shutil.rmtree(folder, ignore_errors=True)
    else:
        with contextlib.suppress(OSError):
            Path(folder).unlink(missing_ok=True)
