"""Recover a ROS 2 sqlite3 bag that rosbags cannot open: a `.db3` file cut short (SQLite calls
it "malformed") or a bag folder without its metadata.yaml (a recording that never closed; what
`ros2 bag reindex` repairs).  Copies every message that can be read, in recording order, into an
MCAP file that rosbags opens.

SQLite file format (sqlite.org/fileformat.html, sec. 1.3): the page size is the big-endian u16
at offset 16 (1 = 65536); the database size in pages, at offset 28, is trusted when valid, so a
file cut short looks corrupt from its first query.  The copy keeps the whole pages that are
there and states their number at offset 28; reading then stops with an error at the first page
that the cut removed, and the rows before it are kept.  rosbag2's tables (schema 3+): `topics
(id, name, type, serialization_format, ...)`, `messages (id, topic_id, timestamp, data)`.
"""

from __future__ import annotations

import logging
import shutil
import sqlite3
import struct
import tempfile
from pathlib import Path
from typing import Any

from fusion.errors import LogError
from fusion.fileio import recovered_copy_path
from fusion.log.euroc import LogWarning

log = logging.getLogger(__name__)

PAGE_SIZE_OFFSET, PAGE_COUNT_OFFSET = 16, 28
SQLITE_MAGIC = b"SQLite format 3\x00"


def _whole_pages_copy(src: Path, dst: Path) -> None:
    """`src` cut to whole pages, with the page count in its header set to what is there."""
    data = src.read_bytes()
    if not data.startswith(SQLITE_MAGIC) or len(data) < 100:
        raise LogError(f"{src}: not an SQLite database")
    (ps,) = struct.unpack_from(">H", data, PAGE_SIZE_OFFSET)
    ps = 65536 if ps == 1 else ps
    n_pages = len(data) // ps
    out = bytearray(data[: n_pages * ps])
    struct.pack_into(">I", out, PAGE_COUNT_OFFSET, n_pages)
    dst.write_bytes(bytes(out))


def recover_db3(files: list[Path], dst: Path) -> tuple[int, dict[str, int], list[str]]:
    """Copy the readable messages of rosbag2 sqlite3 files (in order) into the MCAP file `dst`.
    Returns (messages copied, {"topic (type)": messages left out} for topics whose type is
    unknown, one note per file that stopped early)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from fusion.log.rosbag import typestore_for

    ts = typestore_for(False)
    notes: list[str] = []
    n = 0
    unknown: dict[str, int] = {}
    work = Path(tempfile.mkdtemp(prefix=".recover-", dir=dst.parent))
    try:
        target = work / "bag"
        conns: dict[str, Any] = {}  # rosbags Connection
        with Writer(target, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            for db in files:
                fixed = work / db.name
                _whole_pages_copy(db, fixed)
                con = sqlite3.connect(f"file:{fixed}?mode=ro", uri=True)
                read = 0
                try:
                    topics = {
                        int(i): (name, msgtype)
                        for i, name, msgtype in con.execute("SELECT id, name, type FROM topics")
                    }
                    for topic_id, stamp, data in con.execute(
                        "SELECT topic_id, timestamp, data FROM messages ORDER BY id"
                    ):
                        name, msgtype = topics.get(int(topic_id), (f"topic id {topic_id}", ""))
                        if name not in conns:
                            if msgtype not in ts.types:
                                what = f"{name} ({msgtype})"
                                unknown[what] = unknown.get(what, 0) + 1
                                continue
                            conns[name] = writer.add_connection(name, msgtype, typestore=ts)
                        writer.write(conns[name], int(stamp), bytes(data))
                        read += 1
                except sqlite3.DatabaseError as e:
                    notes.append(f"{db.name}: stopped after {read} messages ({e})")
                finally:
                    con.close()
                n += read
        shutil.move(str(target / "bag.mcap"), str(dst))
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return n, unknown, notes


def recovered_sqlite_bag(folder: Path, warnings: list[LogWarning] | None = None) -> tuple[Path, str | None]:
    """A readable MCAP copy of the sqlite3 bag `folder` (its *.db3 files, in name order; or one
    .db3 file) in the temp folder, reused while the files are unchanged, and a one-line note of
    what was damaged and read (None for one .db3 file read whole); LogError when no message
    could be read.  Messages of types the typestore does not know cannot go into the copy: they
    are a `bag_unknown_types_left_out` LogWarning in `warnings` (count: the messages)."""
    folder = Path(folder)
    files = [folder] if folder.is_file() else sorted(folder.glob("*.db3"))
    if not files:
        raise LogError(f"{folder}: no .db3 files")
    stamp = "|".join(f"{p.resolve()}:{p.stat().st_size}:{p.stat().st_mtime_ns}" for p in files)
    dst = recovered_copy_path(folder.stem, stamp, ".mcap")
    n, unknown, notes = recover_db3(files, dst.with_suffix(".partial"))
    if n == 0:
        dst.with_suffix(".partial").unlink(missing_ok=True)
        raise LogError(f"{folder}: ROS 2 sqlite3 bag with no readable message")
    dst.with_suffix(".partial").replace(dst)
    if unknown and warnings is not None:
        # its own warning, not the damage note: a bag read whole was called damaged for these
        n_unknown = sum(unknown.values())
        kinds = ", ".join(f"{what}: {k}" for what, k in sorted(unknown.items()))
        message = f"{folder}: {n_unknown} message(s) of unknown types left out of the copy read ({kinds})"
        warnings.append(LogWarning("bag_unknown_types_left_out", n_unknown, message))
    if folder.is_file() and not notes:
        # a .db3 given alone has no metadata.yaml of its own to miss, and every row was read:
        # nothing is damaged (the note became a bag_truncated warning with nothing missing)
        return dst, None
    why = "; ".join(notes) if notes else "no usable metadata.yaml"
    return dst, f"{folder}: damaged ROS 2 sqlite3 bag ({why}); read {n} message(s) from the copy {dst}"
