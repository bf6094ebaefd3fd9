"""Recover a truncated MCAP file (a ROS 2 recording cut short): copy every complete record up
to the damage into a new file that rosbags can open (what `mcap recover` does, without the
mcap CLI).

MCAP (mcap.dev/spec): the magic `\\x89MCAP0\\r\\n`, then records `opcode u8, length u64,
content`, ending with DataEnd (0x0F), the summary section and the Footer (0x02) and the magic
again.  rosbags needs the footer; a recording cut short has none.  The records before the cut
are intact: Schema (0x03), Channel (0x04), Message (0x05) and Chunk (0x06: start u64, end u64,
uncompressed size u64, crc u32, compression string, records u64-sized; compressed with zstd or
lz4, or not at all).  The copy holds the complete records, the complete records inside an
uncompressed chunk that the cut went through, then DataEnd and a Footer without a summary
(summary_start 0), which rosbags reads by scanning.
"""

from __future__ import annotations

import logging
import mmap
import struct
from pathlib import Path
from typing import BinaryIO

from fusion.errors import LogError
from fusion.fileio import recovered_copy_path

log = logging.getLogger(__name__)

MAGIC = b"\x89MCAP0\r\n"
OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_DATA_END = 0x0F
KEPT_OPS = (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK)
RECORD_HEAD = 9  # opcode u8 + length u64
CHUNK_FIXED = 8 + 8 + 8 + 4  # start, end, uncompressed size, crc


def _record(op: int, content: bytes) -> bytes:
    return struct.pack("<BQ", op, len(content)) + content


def _inner_records(data: bytes) -> tuple[list[bytes], int]:
    """The complete records at the start of an uncompressed chunk's record bytes (each as
    written: opcode, length, content), and how many of them are messages."""
    out, n_msg, off = [], 0, 0
    while off + RECORD_HEAD <= len(data):
        op, n = struct.unpack_from("<BQ", data, off)
        end = off + RECORD_HEAD + n
        if end > len(data):
            break
        if op in (OP_SCHEMA, OP_CHANNEL, OP_MESSAGE):
            out.append(data[off:end])
            n_msg += op == OP_MESSAGE
        off = end
    return out, n_msg


def _cut_chunk_records(partial: bytes) -> tuple[list[bytes], int]:
    """Complete records of an uncompressed chunk cut short (`partial`: its content so far)."""
    if len(partial) < CHUNK_FIXED + 4:
        return [], 0
    (clen,) = struct.unpack_from("<I", partial, CHUNK_FIXED)
    at = CHUNK_FIXED + 4
    compression = partial[at : at + clen]
    if compression != b"" or len(partial) < at + clen + 8:
        return [], 0  # a compressed stream cut short cannot be decoded
    return _inner_records(partial[at + clen + 8 :])


def recover_mcap(src: Path, dst: Path) -> tuple[int, int, str]:
    """Copy the complete records of the MCAP file `src` into `dst` (module docstring); returns
    (top-level messages + messages salvaged from a cut chunk, complete chunks, where it stopped).
    The source is memory-mapped and each record written as it is found: reading it whole (and
    joining the copy in memory) took three times a multi-GB recording's size."""
    src, dst = Path(src), Path(dst)
    with open(src, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise LogError(f"{src}: not an MCAP file (no MCAP magic)")
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data, open(dst, "wb") as out:
            n_msg, n_chunks, note = _copy_records(data, out)
            out.write(_record(OP_DATA_END, struct.pack("<I", 0)))
            out.write(_record(OP_FOOTER, struct.pack("<QQI", 0, 0, 0)))
            out.write(MAGIC)
    return n_msg, n_chunks, note


def _copy_records(data: mmap.mmap, out: BinaryIO) -> tuple[int, int, str]:
    """recover_mcap's loop over the records after the magic: (messages, chunks, note)."""
    off = len(MAGIC)
    out.write(MAGIC)
    n_msg = n_chunks = 0
    while True:
        if off + RECORD_HEAD > len(data):
            return n_msg, n_chunks, f"cut after {off} of its bytes" if off < len(data) else "no data end"
        op, n = struct.unpack_from("<BQ", data, off)
        end = off + RECORD_HEAD + n
        if end > len(data):
            if op == OP_CHUNK:
                salvaged, k = _cut_chunk_records(data[off + RECORD_HEAD :])
                out.writelines(salvaged)
                n_msg += k
            return n_msg, n_chunks, f"cut at byte {off} (inside a record of {n} bytes)"
        if op in (OP_DATA_END, OP_FOOTER):
            return n_msg, n_chunks, "no summary"
        if op == OP_HEADER or op in KEPT_OPS:
            out.write(data[off:end])
            n_msg += op == OP_MESSAGE
            n_chunks += op == OP_CHUNK
        off = end


def recovered_mcap(src: Path) -> tuple[Path, str]:
    """A readable copy of a damaged MCAP file in the temp folder (reused while `src` is
    unchanged) and a one-line note of what was recovered; LogError when nothing was."""
    src = Path(src)
    st = src.stat()
    dst = recovered_copy_path(src.stem, f"{src.resolve()}|{st.st_size}|{st.st_mtime_ns}", ".mcap")
    tmp = dst.with_suffix(".partial")
    tmp.unlink(missing_ok=True)
    n_msg, n_chunks, note = recover_mcap(src, tmp)
    if n_msg == 0 and n_chunks == 0:
        tmp.unlink(missing_ok=True)
        raise LogError(f"{src}: truncated MCAP file with no complete message")
    tmp.replace(dst)
    what = f"{n_chunks} complete chunk(s)" + (f" and {n_msg} message(s)" if n_msg else "")
    return dst, f"{src}: truncated MCAP file ({note}); read {what} from the copy {dst}"
