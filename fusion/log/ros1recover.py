"""Recover a truncated or unindexed ROS 1 bag: copy every complete message up to the damage
into a new, indexed bag (what `rosbag reindex` does, without ROS).

ROS 1 bag format 2.0 (wiki.ros.org/Bags/Format/2.0): after the line `#ROSBAG V2.0`, records of
    uint32 header_len, header (fields: uint32 len, b"name=value"), uint32 data_len, data
with the header's `op`: 0x02 message data (conn, time), 0x03 bag header, 0x04 index data,
0x05 chunk (compression none / bz2 / lz4, holding connection and message records), 0x06 chunk
info, 0x07 connection (conn, topic; data = topic, type, md5sum, message_definition, ...).
A recording cut short has no index (`index_pos` = 0 or pointing past the end), which rosbags
refuses; the records before the cut are intact.
"""

from __future__ import annotations

import bz2
import io
import logging
import struct
from pathlib import Path

from fusion.errors import LogError
from fusion.fileio import recovered_copy_path

log = logging.getLogger(__name__)

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_CHUNK, OP_CONNECTION = 0x02, 0x05, 0x07


def _fields(raw: bytes) -> dict[str, bytes]:
    out, off = {}, 0
    while off + 4 <= len(raw):
        (n,) = struct.unpack_from("<I", raw, off)
        field = raw[off + 4 : off + 4 + n]
        if len(field) != n:
            raise EOFError
        name, _, value = field.partition(b"=")
        out[name.decode("ascii", "replace")] = value
        off += 4 + n
    return out


class _Cut(Exception):
    """A record cut short: its header fields and the data bytes that are there."""

    def __init__(self, fields: dict, data: bytes):
        super().__init__("record cut short")
        self.fields, self.data = fields, data


def _records(f):
    """Yield (header fields, data) until the end; raises _Cut at an incomplete record."""
    while True:
        head = f.read(4)
        if len(head) < 4:
            return
        (hlen,) = struct.unpack("<I", head)
        header = f.read(hlen)
        dlen_raw = f.read(4)
        if len(header) < hlen or len(dlen_raw) < 4:
            raise _Cut({}, b"")
        (dlen,) = struct.unpack("<I", dlen_raw)
        data = f.read(dlen)
        if len(data) < dlen:
            raise _Cut(_fields(header), data)
        yield _fields(header), data


def _decompress(kind: bytes, data: bytes) -> bytes:
    if kind == b"none":
        return data
    if kind == b"bz2":
        return bz2.decompress(data)
    if kind == b"lz4":
        import lz4.frame

        return lz4.frame.decompress(data)
    raise ValueError(f"chunk compression {kind!r}")


def _msgtype(ros1_type: str) -> str:
    pkg, _, name = ros1_type.partition("/")
    return f"{pkg}/msg/{name}"


def recover_ros1(src: Path, dst: Path) -> tuple[int, str]:
    """Copy the complete messages of the ROS 1 bag `src` into the indexed bag `dst`; returns
    (messages copied, where the copy stopped)."""
    from rosbags.rosbag1 import Writer

    src, dst = Path(src), Path(dst)
    conns: dict[int, object] = {}
    n, note = 0, "end of file"
    with open(src, "rb") as f, Writer(dst) as writer:
        if f.readline() != MAGIC:
            raise LogError(f"{src}: not a ROS 1 bag (no '#ROSBAG V2.0' line)")

        def handle(fields, data):
            nonlocal n
            op = fields.get("op", b"\0")[0]
            if op == OP_CONNECTION:
                cid = struct.unpack("<I", fields["conn"])[0]
                if cid not in conns:
                    info = _fields(data)
                    conns[cid] = writer.add_connection(
                        info["topic"].decode(),
                        _msgtype(info["type"].decode()),
                        msgdef=info.get("message_definition", b"").decode(),
                        md5sum=info["md5sum"].decode(),
                        callerid=info["callerid"].decode() if "callerid" in info else None,
                    )
            elif op == OP_MESSAGE:
                cid = struct.unpack("<I", fields["conn"])[0]
                sec, nsec = struct.unpack("<II", fields["time"])
                if cid in conns:
                    writer.write(conns[cid], sec * 1_000_000_000 + nsec, data)
                    n += 1

        def chunk_records(data):
            for fields, inner in _records(io.BytesIO(data)):
                handle(fields, inner)

        try:
            for fields, data in _records(f):
                if fields.get("op", b"\0")[0] == OP_CHUNK:
                    chunk_records(_decompress(fields.get("compression", b"none"), data))
                else:
                    handle(fields, data)
        except _Cut as cut:
            if (
                cut.fields.get("op", b"\0")[0] == OP_CHUNK
                and cut.fields.get("compression", b"none") == b"none"
            ):
                try:  # an uncompressed chunk cut short: keep its messages
                    chunk_records(cut.data)
                except _Cut:
                    pass
            note = f"cut after {n} messages"
        except (struct.error, KeyError, ValueError, OSError, EOFError) as e:
            note = f"damaged after {n} messages ({e.__class__.__name__})"
    return n, note


def recovered_copy(src: Path) -> Path:
    """An indexed copy of a damaged ROS 1 bag in the temp folder (reused while `src` is
    unchanged); logs a warning saying how much was recovered."""
    src = Path(src)
    st = src.stat()
    dst = recovered_copy_path(src.stem, f"{src.resolve()}|{st.st_size}|{st.st_mtime_ns}", ".bag")
    if not dst.exists():
        tmp = dst.with_suffix(".partial")
        tmp.unlink(missing_ok=True)
        n, note = recover_ros1(src, tmp)
        if n == 0:
            tmp.unlink(missing_ok=True)
            raise LogError(f"{src}: truncated or unindexed ROS 1 bag with no complete message")
        tmp.replace(dst)
        log.warning(
            "%s: truncated or unindexed ROS 1 bag, %s; read %d messages from the copy %s", src, note, n, dst
        )
    return dst
