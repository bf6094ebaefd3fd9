"""Which flights a batch runs, under which output names, and what became of each (the fleet
state file `OUT/fleet.json`).

    expand_flights(["a/", "list.txt"])     -> [Path]   a flight, or a text file listing flights
    output_names(paths, previous)          -> {Path: name}   distinct, stable across resumes
    read_state / write_state               OUT/fleet.json: per flight path, status and reason
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

from fusion.errors import FleetError, LogError
from fusion.fileio import LOCK_NAME, atomic_open, is_regular_file, open_regular
from fusion.log.sources import detect_format

STATE_NAME = "fleet.json"
STATE_FORMAT = "fusion-fleet/1"
NAME_HASH_CHARS = 8  # hex digits of sha256(resolved path) appended to a shared folder name
LIST_COMMENT = "#"
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


class FlightStatus:
    """A flight's state in fleet.json (plain strings: the file is read by people and scripts)."""

    OK = "ok"
    FAILED = "failed"


@dataclass
class FlightRecord:
    """One flight of the batch, as fleet.json keeps it."""

    name: str  # output folder OUT/<name>
    path: str  # resolved log path
    status: str = ""  # FlightStatus, "" before it ran
    reason: str = ""  # failures: one line
    error_type: str = ""
    attempts: int = 0  # graph submissions (a worker death costs one)
    duration_s: float | None = None  # the flight's length
    n_frames: int | None = None  # every camera's frames
    compute_s: float | None = None  # task seconds summed over the flight's tasks
    wall_s: float | None = None  # from the flight's first task to its report
    timings_s: dict[str, float] = field(default_factory=dict)  # the report task's stages
    task_s: dict[str, float] = field(default_factory=dict)  # task seconds by kind (tasks.FlightDone)


def expand_flights(args: list[Path]) -> list[Path]:
    """Flights named by `args`: each is a flight log (anything fusion.log.open_flight reads) or
    a text file listing flights, one a line (blank lines and lines starting with `#` ignored, relative
    paths relative to the list).  Paths are resolved and given once each, in order; a path that
    does not exist stays in the list (it fails as a flight).  FleetError: an unreadable list, or
    one that lists no flight (a batch of nothing is a mistake, not a success)."""
    out: list[Path] = []
    for arg in args:
        arg = Path(arg)
        if _is_list_file(arg):
            out += _read_list(arg)
        else:
            out.append(arg)
    seen: set[Path] = set()
    unique = []
    for p in out:
        r = Path(os.path.realpath(p))
        if r not in seen:
            seen.add(r)
            unique.append(r)
    return unique


def _is_list_file(path: Path) -> bool:
    if not is_regular_file(path):
        return False
    try:
        detect_format(path)
    except LogError:
        return True  # a regular file of no log type: a list
    return False


def _read_list(path: Path) -> list[Path]:
    try:
        with open_regular(path, FleetError, newline=None) as f:
            lines = f.read().splitlines()
    except UnicodeDecodeError:
        raise FleetError(f"{path}: neither a flight log nor a text list of flights") from None
    out = []
    for line in lines:
        text = line.strip()
        if text and not text.startswith(LIST_COMMENT):
            p = Path(text)
            out.append(p if p.is_absolute() else path.parent / p)
    if not out:
        raise FleetError(f"{path}: lists no flight (only blank lines and # comments)")
    return out


def output_names(paths: list[Path], previous: dict[str, FlightRecord] | None = None) -> dict[Path, str]:
    """An output folder name per flight: the log's file or folder name (characters outside
    [A-Za-z0-9._-] replaced), with `-<sha256 of the resolved path, 8 hex>` when two flights of
    the batch share it.  A flight named in `previous` (fleet.json) keeps that name, so a resumed
    batch finds its outputs."""
    previous = previous or {}
    by_path = {rec.path: rec.name for rec in previous.values()}
    names: dict[Path, str] = {}
    base = {p: _base_name(p) for p in paths if str(p) not in by_path}
    counts: dict[str, int] = {}
    for p in paths:
        b = by_path.get(str(p)) or base[p]
        counts[b] = counts.get(b, 0) + 1
    taken = set(by_path.values())
    for p in paths:
        if str(p) in by_path:
            names[p] = by_path[str(p)]
            continue
        name = base[p]
        if counts[name] > 1 or name in taken:
            name = f"{name}-{hashlib.sha256(str(p).encode()).hexdigest()[:NAME_HASH_CHARS]}"
        taken.add(name)
        names[p] = name
    return names


RESERVED_NAMES = (STATE_NAME, "fleet.csv", "fleet.md", "fleet_time.png", "fleet_ate.png", LOCK_NAME)
"""Files of the fleet folder itself (summary.py's names): never a flight's folder name."""


def _base_name(path: Path) -> str:
    name = _UNSAFE.sub("_", path.name).strip("._") or "flight"
    return name if name not in RESERVED_NAMES else f"flight-{name}"


# ============================================================================ fleet.json


def read_state(out: Path) -> dict[str, FlightRecord]:
    """{name: FlightRecord} of OUT/fleet.json ({} without one); FleetError when malformed."""
    path = Path(out) / STATE_NAME
    if not os.path.lexists(path):
        return {}
    try:
        with open_regular(path, FleetError, newline=None) as f:
            data = json.load(f)
        if not (isinstance(data, dict) and data.get("format") == STATE_FORMAT):
            raise ValueError("unexpected layout")
        fields = set(FlightRecord.__dataclass_fields__)
        return {
            str(name): FlightRecord(**{k: v for k, v in rec.items() if k in fields})
            for name, rec in data["flights"].items()
        }
    except (ValueError, TypeError, KeyError, AttributeError, UnicodeDecodeError) as e:
        raise FleetError(
            f"{path}: not a fusion fleet state ({type(e).__name__}); move it away to start the batch afresh"
        ) from None


def write_state(out: Path, records: dict[str, FlightRecord]) -> None:
    """Write OUT/fleet.json atomically."""
    data = {"format": STATE_FORMAT, "flights": {n: asdict(r) for n, r in sorted(records.items())}}
    with atomic_open(Path(out) / STATE_NAME) as f:
        json.dump(data, f, indent=1, allow_nan=False)
        f.write("\n")
