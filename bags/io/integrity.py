"""Integrity checks of bag storage files, run when a bag is opened (:mod:`bags.io.sources`).

* MCAP: the footer's summary CRC and the DataEnd record's data section CRC are verified when
  the file carries them (non-zero; the bags :class:`bags.io.writer.BagWriter` writes do). Chunk
  CRCs are verified by the readers whenever a chunk is read. The data section check reads the
  file once; its result is remembered per file (path, size, modification time) for the rest of
  the process, since a replay opens its input twice. A file whose data section CRC was verified
  (:func:`data_crc_verified`) needs no chunk CRC checks on top (:mod:`bags.io.raw.mcap_index`).
* sqlite3: messages whose ``topic_id`` is not in the ``topics`` table (their topic, hence
  their type, is unknown: rosbags skips them silently).

Each check returns ``None`` for a file that passed (or carries nothing to verify) and a
sentence describing the damage otherwise; they never raise for a damaged file.
"""

from __future__ import annotations

import sqlite3
import struct
import zlib
from pathlib import Path

MCAP_MAGIC = b"\x89MCAP0\r\n"
_FOOTER_LEN = 1 + 8 + 20  # opcode, record length, summary_start, summary_offset_start, crc
_DATA_END_LEN = 1 + 8 + 4
_BLOCK = 1 << 20
_mcap_cache: dict[tuple, tuple[str | None, bool]] = {}


def _crc_of_range(f, start: int, stop: int, crc: int = 0) -> int:
    f.seek(start)
    left = stop - start
    while left > 0:
        block = f.read(min(_BLOCK, left))
        if not block:
            break
        crc = zlib.crc32(block, crc)
        left -= len(block)
    return crc


def check_mcap(path: Path) -> str | None:
    """Verify the summary and data section CRCs of an MCAP file (see module docstring).

    Returns ``None`` when they match or are absent (0), else what is wrong. A file whose
    footer cannot be read is left to the readers (they report it in their own words).
    """
    return _checked(path)[0]


def data_crc_verified(path: Path) -> bool:
    """True when :func:`check_mcap` found a data section CRC in ``path`` and it matched (every
    byte of every chunk is then as written).
    """
    return _checked(path)[1]


def _checked(path: Path) -> tuple[str | None, bool]:
    path = Path(path)
    try:
        st = path.stat()
    except OSError:
        return None, False
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns, st.st_ino)
    if key not in _mcap_cache:
        verified: list[bool] = []
        _mcap_cache[key] = (_check_mcap(path, st.st_size, verified), bool(verified))
    return _mcap_cache[key]


def _check_mcap(path: Path, size: int, verified: list[bool]) -> str | None:
    if size < 2 * len(MCAP_MAGIC) + _FOOTER_LEN:
        return None
    with path.open("rb") as f:
        footer_at = size - len(MCAP_MAGIC) - _FOOTER_LEN
        f.seek(footer_at)
        tail = f.read(_FOOTER_LEN + len(MCAP_MAGIC))
        if tail[-8:] != MCAP_MAGIC or tail[0] != 0x02:
            return None  # no footer: a truncated file, the readers report it
        (length,) = struct.unpack_from("<Q", tail, 1)
        summary_start, _, summary_crc = struct.unpack_from("<QQI", tail, 9)
        if length != 20:
            return f"{path.name}: MCAP footer has length {length}, expected 20"
        if not len(MCAP_MAGIC) <= summary_start <= footer_at:
            return f"{path.name}: MCAP footer points its summary outside the file ({summary_start})"
        if summary_crc and summary_start:
            crc = _crc_of_range(f, summary_start, footer_at + 1 + 8 + 16)
            if crc != summary_crc:
                return (f"{path.name}: MCAP summary section checksum mismatch (CRC-32 "
                        f"{crc:08x}, footer says {summary_crc:08x})")
        data_end_at = (summary_start or footer_at) - _DATA_END_LEN
        if data_end_at < len(MCAP_MAGIC):
            return None
        f.seek(data_end_at)
        rec = f.read(_DATA_END_LEN)
        if rec[0] != 0x0F or struct.unpack_from("<Q", rec, 1)[0] != 4:
            return None  # DataEnd not where the summary starts: nothing to verify against
        (data_crc,) = struct.unpack_from("<I", rec, 9)
        if data_crc:
            crc = _crc_of_range(f, 0, data_end_at)
            if crc != data_crc:
                return (f"{path.name}: MCAP data section checksum mismatch (CRC-32 {crc:08x}, "
                        f"DataEnd record says {data_crc:08x})")
            verified.append(True)
    return None


def check_sqlite(path: Path) -> str | None:
    """Messages of a rosbag2 sqlite3 file whose ``topic_id`` is not in its ``topics`` table."""
    uri = f"{Path(path).resolve().as_uri()}?mode=ro&immutable=1"
    try:
        con = sqlite3.connect(uri, uri=True)
    except sqlite3.Error:
        return None  # unreadable: rosbags reports it
    try:
        rows = con.execute(
            "SELECT topic_id, COUNT(*) FROM messages "
            "WHERE topic_id NOT IN (SELECT id FROM topics) GROUP BY topic_id"
        ).fetchall()
    except sqlite3.Error as exc:
        return f"{Path(path).name}: sqlite3 database is damaged: {exc}"
    finally:
        con.close()
    if not rows:
        return None
    n = sum(count for _, count in rows)
    ids = sorted(tid for tid, _ in rows)
    return (f"{Path(path).name}: {n} message(s) reference topic id(s) {ids[:10]} missing from "
            "the topics table (their topic and type are unknown; they cannot be read)")
