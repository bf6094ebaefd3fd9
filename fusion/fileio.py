"""Small file helpers shared by every module: safe input opening, strict YAML numbers, atomic
writes, spreadsheet-safe CSV cells, and the output folder of a run (lock, manifest, roll-back).

Outputs are written to a temporary file in the same folder and renamed into place, so an
interrupted run never leaves a half-written file that looks complete.  Inputs are opened only
when they are regular files: a named pipe or a device would hang the reader or never end."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any, BinaryIO, Literal, TextIO, overload

import yaml

from fusion.errors import FusionError, OutputError

# ============================================================================ input


@overload
def open_regular(
    path: Path,
    error: type[FusionError] = ...,
    binary: Literal[False] = ...,
    encoding: str = ...,
    newline: str | None = ...,
) -> TextIO: ...


@overload
def open_regular(
    path: Path,
    error: type[FusionError] = ...,
    *,
    binary: Literal[True],
    encoding: str = ...,
    newline: str | None = ...,
) -> BinaryIO: ...


def open_regular(
    path: Path,
    error: type[FusionError] = FusionError,
    binary: bool = False,
    encoding: str = "utf-8-sig",
    newline: str | None = "",
) -> IO[Any]:
    """Open `path` for reading only if it is a regular file (symlinks followed).  Text is UTF-8;
    a byte-order mark (spreadsheet programs write one) is skipped, not read as the first field.

    The file is opened non-blocking and checked with fstat on the open descriptor, so a named
    pipe, a socket or a device is refused without blocking (and without a check-then-open race).
    Raises `error` naming the file for a missing, unreadable or non-regular path."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise error(f"{path}: file not found") from None
    except IsADirectoryError:
        raise error(f"{path}: is a folder, expected a file") from None
    except OSError as e:
        raise error(f"{path}: cannot open ({e.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = (
                "a named pipe"
                if stat.S_ISFIFO(st.st_mode)
                else "a folder"
                if stat.S_ISDIR(st.st_mode)
                else "a device"
                if stat.S_ISCHR(st.st_mode) or stat.S_ISBLK(st.st_mode)
                else "a socket"
                if stat.S_ISSOCK(st.st_mode)
                else "not a regular file"
            )
            raise error(f"{path}: is {kind}, expected a regular file")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        if binary:
            return os.fdopen(fd, "rb")
        return os.fdopen(fd, "r", encoding=encoding, newline=newline)
    except BaseException:
        os.close(fd)
        raise


def is_regular_file(path: Path) -> bool:
    """True if `path` exists and is a regular file (symlinks followed), without opening it."""
    try:
        return stat.S_ISREG(os.stat(path).st_mode)
    except OSError:
        return False


class _Yaml12Floats(yaml.SafeLoader):
    """PyYAML's safe loader with YAML 1.2's floats: an exponent without a decimal point (`2e-4`,
    `-1E+3`) is a number, as yaml-cpp (ROS, Kalibr's tools) and YAML 1.2 read it; PyYAML's YAML
    1.1 resolver reads it as the string '2e-4', and a hand-written imu.yaml or sensor.yaml that
    says `gyroscope_noise_density: 2e-4` was refused ("expected a number, got str").

    A key given twice in one mapping is an error at its second line (YAML 1.2 requires unique
    keys; PyYAML kept the last silently: a new calibration pasted below the old one read as
    either, unsaid).  Keys merged in by `<<` may be overridden, as YAML merge keys intend."""

    def construct_mapping(self, node: yaml.Node, deep: bool = False) -> dict:
        if isinstance(node, yaml.MappingNode):
            seen: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    first = seen.get(key)
                except TypeError:  # unhashable: the base class says so
                    continue
                if first is not None:
                    raise yaml.constructor.ConstructorError(
                        None,
                        None,
                        f"key {str(key)[:60]!r} given twice (first on line {first}): which one holds?",
                        key_node.start_mark,
                    )
                seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep)


_Yaml12Floats.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?[0-9][0-9_]*[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def load_yaml(path: Path, error: type[FusionError] = FusionError) -> dict:
    """Read a YAML mapping (YAML 1.2's floats: `_Yaml12Floats`); a missing, non-regular or
    malformed file raises `error` naming the file (and line)."""
    path = Path(path)
    try:
        with open_regular(path, error, newline=None) as f:
            data = yaml.load(f, Loader=_Yaml12Floats)  # a SafeLoader: no arbitrary objects
    except yaml.MarkedYAMLError as e:
        line = e.problem_mark.line + 1 if e.problem_mark else "?"
        raise error(f"{path}:{line}: not valid YAML ({e.problem})") from None
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise error(f"{path}: not valid YAML ({e.__class__.__name__})") from None
    if not isinstance(data, dict):
        raise error(f"{path}: expected a mapping at top level")
    return data


@overload
def strict_float(
    value,
    where: str,
    error: type[FusionError] = ...,
    *,
    positive: bool = ...,
    allow_none: Literal[False] = ...,
) -> float: ...


@overload
def strict_float(
    value,
    where: str,
    error: type[FusionError] = ...,
    *,
    positive: bool = ...,
    allow_none: bool,
) -> float | None: ...


def strict_float(
    value,
    where: str,
    error: type[FusionError] = FusionError,
    *,
    positive: bool = False,
    allow_none: bool = False,
) -> float | None:
    """A YAML value as a finite float.  Only int and float are numbers: a bool (`true` would
    otherwise read as 1.0), a string ("fast", "0.2") or a list raises `error` naming `where`."""
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise error(f"{where}: expected a number, got {_show(value)}")
    v = float(value)
    if not math.isfinite(v):
        raise error(f"{where}: expected a finite number, got {value!r}")
    if positive and v <= 0:
        raise error(f"{where}: must be positive, got {value!r}")
    return v


def strict_floats(value, n: int | None, where: str, error: type[FusionError] = FusionError) -> list[float]:
    """A YAML list of `n` numbers (any length when n is None), each checked by strict_float."""
    if not isinstance(value, (list, tuple)):
        raise error(f"{where}: expected a list of {n or 'some'} numbers, got {_show(value)}")
    if n is not None and len(value) != n:
        raise error(f"{where}: expected {n} numbers, found {len(value)}")
    return [strict_float(v, f"{where}[{i}]", error) for i, v in enumerate(value)]


def _show(value) -> str:
    text = repr(value)
    return f"{type(value).__name__} {text[:40]}"


# ============================================================================ CSV cells

CSV_FORMULA_PREFIXES = ("=", "+", "-", "@", "\t", "\r")
"""Leading characters that make a spreadsheet evaluate a cell (OWASP, "CSV Injection")."""
CSV_QUOTE = "'"


def csv_safe(text: str) -> str:
    """A CSV cell a spreadsheet shows as text: a `'` before a leading = + - @ tab or CR (the
    OWASP CSV-injection rule).  A leading `'` is doubled too, so `csv_unsafe` inverts this
    exactly (ids starting with a quote survive a round trip)."""
    text = str(text)
    if text.startswith(CSV_FORMULA_PREFIXES) or text.startswith(CSV_QUOTE):
        return CSV_QUOTE + text
    return text


def csv_unsafe(cell: str) -> str:
    """Inverse of `csv_safe` (for our own CSVs read back)."""
    return cell[1:] if cell.startswith(CSV_QUOTE) else cell


# ============================================================================ output


@contextlib.contextmanager
def atomic_open(path: Path, mode: str = "w", encoding: str | None = "utf-8") -> Iterator[IO[Any]]:
    """Open a temporary sibling of `path` for writing; rename it onto `path` only on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
    try:
        f: IO[Any] = (
            os.fdopen(fd, mode) if "b" in mode else os.fdopen(fd, mode, encoding=encoding, newline="")
        )
        with f:
            yield f
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def dump_yaml(data: dict, path: Path) -> None:
    """Write a YAML mapping atomically, keys in the given order."""
    with atomic_open(path) as f:
        yaml.safe_dump(data, f, sort_keys=False, default_flow_style=None)


# ============================================================================ output folders

RECOVERED_DIR = "fusion-recovered-bags"
RECOVERED_KEEP = 8
"""Readable copies of damaged bags kept in the temp folder: the most recently used ones."""


def recovered_copy_path(stem: str, source_id: str, suffix: str) -> Path:
    """Where the readable copy of a damaged log goes: the temp folder's fusion-recovered-bags,
    named by `stem` and a hash of `source_id` (the source's path, size and mtime), so that a copy
    is found again while its source is unchanged.  The folder is a cache: a copy's mtime is
    touched when it is handed out, and beyond RECOVERED_KEEP copies the least recently used
    ones are removed (it grew by one full-size copy per damaged bag ever read)."""
    folder = Path(tempfile.gettempdir()) / RECOVERED_DIR
    folder.mkdir(exist_ok=True)
    key = hashlib.sha256(source_id.encode()).hexdigest()[:16]
    dst = folder / f"{stem}-{key}{suffix}"
    with contextlib.suppress(OSError):
        os.utime(dst)
    copies = []
    for p in folder.iterdir():
        with contextlib.suppress(OSError):
            if p != dst and p.suffix != ".partial" and not p.name.startswith(".") and p.is_file():
                copies.append((p.stat().st_mtime_ns, p))
    for _, old in sorted(copies, reverse=True)[RECOVERED_KEEP - 1 :]:
        with contextlib.suppress(OSError):
            old.unlink()  # a reader that has it open keeps reading it
    return dst


MANIFEST_NAME = "manifest.json"
MANIFEST_FORMAT = "fusion-outputs/1"
LOCK_NAME = "fusion.lock"
RUN_WRITER = "fusion run"
"""`written_by` of the manifest of a run's output folder (`OutputFolder`: every pipeline stage
command, `batch`'s flights and `demo`'s run write the same kind of folder)."""
FLIGHT_LOG_WRITERS = ("fusion simulate", "fusion import")
"""`written_by` of a flight log's manifest (`log.euroc.FlightLogWriter`): one kind, a log."""
_HASH_CHUNK = 1 << 20


def pid_alive(pid: int) -> bool:
    """True if a process `pid` exists on this machine (one we may not signal counts as alive)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    return True


def _hostname() -> str:
    return os.uname().nodename if hasattr(os, "uname") else ""


def _create_exclusive(path: Path, text: str) -> None:
    """Create `path` with O_EXCL (fails with FileExistsError if it exists) holding `text`."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    try:
        os.write(fd, text.encode())
    except BaseException:
        os.close(fd)
        with contextlib.suppress(OSError):
            os.unlink(path)
        raise
    os.close(fd)


def _read_lock(path: Path) -> tuple[int | None, str]:
    """(pid, host) of a lock file; pid None when it cannot be read (e.g. being written)."""
    try:
        with open_regular(path, OutputError, newline=None) as f:
            lines = f.read(200).splitlines()
        return int(lines[0]), (lines[1] if len(lines) > 1 else "")
    except (FusionError, OSError, ValueError, IndexError):
        return None, ""


class DirLock:
    """An exclusive lock on a folder: the file `LOCK_NAME` created with O_EXCL, holding the
    owner's pid and host.  A lock whose pid is dead on this host is stale and taken over."""

    def __init__(self, folder: Path, error: type[FusionError] = OutputError):
        self.path = Path(folder) / LOCK_NAME
        self.error = error
        self.held = False

    def acquire(self) -> None:
        me = f"{os.getpid()}\n{_hostname()}\n"
        for _ in range(3):
            try:
                _create_exclusive(self.path, me)
                self.held = True
                return
            except FileExistsError:
                pid, host = _read_lock(self.path)
                if pid is None or (host and host != _hostname()) or pid_alive(pid):
                    who = f"pid {pid}" if pid is not None else "a process starting up"
                    raise self.error(
                        f"{self.path.parent}: in use by another fusion run ({who}"
                        f"{' on ' + host if host and host != _hostname() else ''}; lock file "
                        f"{self.path}); wait for it to finish, or delete the lock file if that "
                        "run is gone"
                    ) from None
                # stale: its owner died; take it over unless someone else just did
                if _read_lock(self.path) == (pid, host):
                    with contextlib.suppress(FileNotFoundError):
                        os.unlink(self.path)
            except OSError as e:
                raise self.error(f"{self.path.parent}: cannot write here ({e.strerror})") from None
        raise self.error(f"{self.path.parent}: could not take the lock {self.path}")

    def release(self) -> None:
        if self.held and _read_lock(self.path)[0] == os.getpid():
            with contextlib.suppress(OSError):
                os.unlink(self.path)
        self.held = False


def _snapshot(folder: Path) -> dict[str, tuple[int, int, int]]:
    """{relative path: (inode, mtime_ns, size)} of every file under `folder` (links not followed),
    without our lock and manifest."""
    out = {}
    for dirpath, _dirnames, filenames in os.walk(folder):
        for name in filenames:
            p = Path(dirpath) / name
            rel = p.relative_to(folder).as_posix()
            if rel in (LOCK_NAME, MANIFEST_NAME):
                continue
            try:
                st = os.lstat(p)
            except FileNotFoundError:
                continue
            out[rel] = (st.st_ino, st.st_mtime_ns, st.st_size)
    return out


def _dirs(folder: Path) -> set[str]:
    return {
        (Path(d) / n).relative_to(folder).as_posix() for d, dirnames, _ in os.walk(folder) for n in dirnames
    }


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(_HASH_CHUNK), b""):
            h.update(block)
    return h.hexdigest()


def read_manifest(folder: Path, error: type[FusionError] = OutputError) -> dict | None:
    """The manifest of `folder` (None if there is none); a malformed one raises `error`."""
    path = Path(folder) / MANIFEST_NAME
    if not os.path.lexists(path):
        return None
    try:
        with open_regular(path, error, newline=None) as f:
            data = json.load(f)
        if not (
            isinstance(data, dict)
            and data.get("format") == MANIFEST_FORMAT
            and isinstance(data.get("files"), list)
            and all(isinstance(e, dict) and isinstance(e.get("path"), str) for e in data["files"])
            and isinstance(data.get("preexisting", []), list)
        ):
            raise ValueError("unexpected layout")
    except (ValueError, UnicodeDecodeError) as e:
        raise error(
            f"{path}: not a fusion manifest ({e.__class__.__name__}); remove the previous outputs by hand"
        ) from None
    return data


def manifest_writer(manifest: dict) -> str:
    """The command that wrote `manifest` (its `written_by`).  A manifest without one is a run's:
    flight logs always said who wrote them, and only a run's output folder did not."""
    writer = manifest.get("written_by", RUN_WRITER)
    return writer if isinstance(writer, str) else repr(writer)


def flight_log_mark(folder: Path, manifest: dict | None = None) -> str | None:
    """What shows that `folder` is a flight log ("written by `fusion simulate`", "mav0/"), or
    None.  `manifest`: the folder's, when already read.  A flight log is input: no command
    writes its outputs into one, with or without --force."""
    manifest = read_manifest(folder) if manifest is None else manifest
    if manifest is not None and manifest_writer(manifest) in FLIGHT_LOG_WRITERS:
        return f"written by `{manifest_writer(manifest)}`"
    if (Path(folder) / "mav0").is_dir():
        return "mav0/"
    return None


def path_overlap(out: Path, src: Path) -> str | None:
    """How an output path meets an input, symbolic links resolved: "is", "holds" (the input lies
    inside it) or "lies inside" (the input holds it); None when they are apart.  Writing, or
    --force's clean-up, at such an output touches the input."""
    real_out, real_src = Path(os.path.realpath(out)), Path(os.path.realpath(src))
    if real_out == real_src:
        return "is"
    if real_src.is_relative_to(real_out):
        return "holds"
    if real_out.is_relative_to(real_src):
        return "lies inside"
    return None


def _inside(folder: Path, rel: str) -> Path | None:
    """`folder / rel` if it stays inside `folder` (a manifest is input too), else None."""
    p = Path(folder) / rel
    try:
        if (
            Path(os.path.realpath(p.parent)).is_relative_to(os.path.realpath(folder))
            and not Path(rel).is_absolute()
            and ".." not in Path(rel).parts
        ):
            return p
    except (OSError, ValueError):
        pass
    return None


def previous_outputs(folder: Path, error: type[FusionError] = OutputError) -> list[str]:
    """Relative paths of the files a previous run wrote into `folder`, from its manifest: the
    listed files of a complete run; for a run that died before finishing ("running"), every
    file that was not there when it started."""
    manifest = read_manifest(folder, error)
    if manifest is None:
        return []
    if manifest.get("status") == "running":
        before = set(str(p) for p in manifest.get("preexisting", []))
        return sorted(set(_snapshot(folder)) - before)
    return [e["path"] for e in manifest["files"]]


def remove_listed(folder: Path, rels, keep: tuple[str, ...] = ()) -> list[str]:
    """Delete the regular files `rels` (relative to `folder`) except `keep`, then the folders they
    leave empty; paths outside `folder` are ignored.  Returns what was deleted."""
    removed = []
    parents: set[Path] = set()
    for rel in rels:
        if rel in keep or rel in (LOCK_NAME,):
            continue
        p = _inside(folder, rel)
        if p is None or not os.path.lexists(p) or (p.is_dir() and not p.is_symlink()):
            continue
        os.unlink(p)
        removed.append(rel)
        parents.update(Path(rel).parents)
    for d in sorted((str(d) for d in parents if str(d) != "."), key=len, reverse=True):
        with contextlib.suppress(OSError):
            (Path(folder) / d).rmdir()  # only if empty
    return removed


class OutputFolder:
    """The output folder of one run, used as a context manager:

        with OutputFolder(out_dir, force) as out:      # locks, cleans, records
            ... write files into out.path ...
        # success: OUT/manifest.json lists every file the run wrote (path, bytes, sha256)

    Entering refuses a folder that is, holds or lies inside one of `inputs` (the flight log
    being read), creates the folder, takes its lock (`DirLock`), refuses a folder holding a
    flight log (`mav0/`) or another command's outputs (a manifest whose `written_by` is not
    ours: `--force` would delete them), refuses a non-empty folder unless `force`, and with
    `force` deletes the files of the previous outputs of our kind (their manifest) except `keep`
    (e.g. a cache that checks itself), never the user's other files.  A manifest marked
    "running" is written first, so the outputs of a run that dies hard can still be told apart.
    If the body raises, every file the run created or changed is removed again (no half output)
    and an OSError (full disk, read-only folder) becomes one OutputError."""

    def __init__(
        self,
        path: Path,
        force: bool = False,
        keep: tuple[str, ...] = (),
        meta: dict | None = None,
        *,
        written_by: str = RUN_WRITER,
        inputs: tuple[Path, ...] = (),
    ):
        self.path = Path(path)
        self.force = force
        self.keep = tuple(keep)
        self.meta = dict(meta or {})
        self.written_by = written_by
        self.inputs = tuple(Path(i) for i in inputs)
        self.lock = DirLock(self.path)
        self.created_folder = False
        self.removed_previous: list[str] = []
        self.written: list[str] = []
        self._before: dict = {}
        self._dirs_before: set[str] = set()

    def __enter__(self) -> OutputFolder:
        p = self.path
        self._refuse_overlap()
        if os.path.lexists(p) and not p.is_dir():
            raise OutputError(f"{p}: exists and is not a folder")
        try:
            if not p.exists():
                p.mkdir(parents=True)
                self.created_folder = True
        except OSError as e:
            raise OutputError(f"{p}: cannot create the output folder ({e.strerror})") from None
        if not os.access(p, os.W_OK | os.X_OK):
            self._drop_folder()
            raise OutputError(f"{p}: the output folder is not writable")
        try:
            self.lock.acquire()
        except OutputError:
            self._drop_folder()
            raise
        try:
            self._prepare()
        except BaseException as e:
            self.lock.release()
            self._drop_folder()
            if isinstance(e, OSError):
                raise OutputError(f"{p}: cannot prepare the output folder ({e.strerror})") from None
            raise
        return self

    def _refuse_overlap(self) -> None:
        """OutputError if the folder is, holds or lies inside an input (LOG --out LOG, a results
        folder around the flights, or inside one): writing or --force there touches the input."""
        for src in self.inputs:
            how = path_overlap(self.path, src)
            if how is None:
                continue
            what = "" if how == "is" else f" ({src})"
            raise OutputError(
                f"{self.path}: {how} the flight log being read{what}; choose another output folder"
            )

    def _refuse_foreign(self) -> None:
        """OutputError if the folder holds a flight log or another command's outputs (with or
        without --force: the usual "use --force" advice would delete them)."""
        p = self.path
        manifest = read_manifest(p)
        mark = flight_log_mark(p, manifest)
        if mark is not None:
            raise OutputError(
                f"{p}: is a flight log ({mark}), not an output folder; choose another output folder"
            )
        writer = manifest_writer(manifest) if manifest is not None else None
        if writer is not None and writer != self.written_by:
            raise OutputError(
                f"{p}: holds the outputs of `{writer}` (its {MANIFEST_NAME}), not of "
                f"`{self.written_by}`; choose another output folder"
            )

    def _prepare(self) -> None:
        p = self.path
        others = [n for n in os.listdir(p) if n != LOCK_NAME]
        if others:
            self._refuse_foreign()
        if others and not self.force:
            raise OutputError(
                f"{p}: output folder exists; use --force to write into it "
                "(it removes the previous run's outputs and keeps other files)"
            )
        if others:
            self.removed_previous = remove_listed(p, previous_outputs(p), self.keep)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(p / MANIFEST_NAME)
        self._before = _snapshot(p)
        self._dirs_before = _dirs(p)
        self._write_manifest({"status": "running", "files": [], "preexisting": sorted(self._before)})

    def changed_files(self) -> list[str]:
        """Files created or replaced since entering (relative paths, sorted)."""
        now = _snapshot(self.path)
        return sorted(rel for rel, sig in now.items() if self._before.get(rel) != sig)

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if exc_type is None:
                try:
                    changed = self.changed_files()
                    reused = [k for k in self.keep if k not in changed and (self.path / k).is_file()]
                    self.written = sorted(changed + reused)
                    self._write_manifest(
                        {
                            "status": "complete",
                            "files": [
                                {
                                    "path": rel,
                                    "bytes": (self.path / rel).stat().st_size,
                                    "sha256": sha256_file(self.path / rel),
                                    **({"reused": True} if rel in reused else {}),
                                }
                                for rel in self.written
                            ],
                        }
                    )
                    return
                except OSError as e:
                    self._roll_back()
                    raise OutputError(self._os_message(e)) from None
            self._roll_back()
            if issubclass(exc_type, OSError):
                raise OutputError(self._os_message(exc)) from None
        finally:
            self.lock.release()
            if exc_type is not None:
                self._drop_folder()

    def _os_message(self, e: OSError) -> str:
        where = f" ({e.filename})" if getattr(e, "filename", None) else ""
        return (
            f"{self.path}: a file could not be written: {e.strerror or e}{where}; "
            "this run's partial outputs were removed"
        )

    def _roll_back(self) -> None:
        with contextlib.suppress(OSError):
            remove_listed(self.path, self.changed_files())
        with contextlib.suppress(OSError):
            os.unlink(self.path / MANIFEST_NAME)
        for d in sorted(_dirs(self.path) - self._dirs_before, key=len, reverse=True):
            with contextlib.suppress(OSError):
                (self.path / d).rmdir()

    def _drop_folder(self) -> None:
        """Remove the output folder again if this run created it and left it empty."""
        if self.created_folder:
            with contextlib.suppress(OSError):
                self.path.rmdir()

    def _write_manifest(self, body: dict) -> None:
        data = {"format": MANIFEST_FORMAT, "written_by": self.written_by, **self.meta, **body}
        with atomic_open(self.path / MANIFEST_NAME) as f:
            json.dump(data, f, indent=1)
            f.write("\n")
