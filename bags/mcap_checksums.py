"""MCAP checksums: the footer's summary CRC and the DataEnd record's data section CRC,
verified where the file carries them (non-zero; the bags :class:`bags.io.writer.BagWriter`
writes do); part of :mod:`bags.io.integrity`'s checks when a bag is opened.

The data section check reads the whole file; its result is remembered per file (path, size,
modification time, inode) for the rest of the process, since a replay opens its input twice. A
file whose data section CRC was verified (:func:`data_crc_verified`) needs no chunk CRC checks
on top (:mod:`bags.io.raw.mcap_index`).

This module imports nothing else of the package: ``bev-bag`` starts the checks of the bags on
its command line (:func:`check_in_background`) before it loads the rest (about half a second of
imports on 2 cores, while the check of a 1 GB bag takes about 0.4 s).

Each check returns ``None`` for a file that passed (or carries nothing to verify) and a
sentence describing the damage otherwise; they never raise for a damaged file.
"""

from __future__ import annotations

import mmap
import os
import struct
import threading
import zlib
from collections.abc import Iterable
from pathlib import Path

MCAP_MAGIC = b"\x89MCAP0\r\n"
_FOOTER_LEN = 1 + 8 + 20  # opcode, record length, summary_start, summary_offset_start, crc
_DATA_END_LEN = 1 + 8 + 4
_BLOCK = 4 << 20
#: results per file (path, size, modification time, inode) for the rest of the process
_mcap_cache: dict[tuple, tuple[str | None, bool]] = {}
#: files being checked now -> set when their result is in the cache
_running: dict[tuple, threading.Event] = {}
_lock = threading.Lock()


def _crc_of_range(f, start: int, stop: int, crc: int = 0) -> int:
    """CRC-32 of the file's bytes ``start:stop``: through a read-only memory map in one zlib call,
    which holds no GIL for the whole range (read in blocks instead, every block has to take the
    GIL back, waiting up to the switch interval while another thread runs Python: 3.5 s instead
    of 0.6 s for a 1 GB bag beside a busy thread); a file that does not map is read in blocks.
    """
    try:
        with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
            if hasattr(mmap, "MADV_SEQUENTIAL"):
                mm.madvise(mmap.MADV_SEQUENTIAL)
            with memoryview(mm) as view, view[start:stop] as part:
                return zlib.crc32(part, crc)
    except (OSError, ValueError):  # empty, or not a regular file
        pass
    f.seek(start)
    buf = memoryview(bytearray(min(_BLOCK, max(stop - start, 0))))
    left = stop - start
    while left > 0:
        n = f.readinto(buf[:min(len(buf), left)])
        if not n:
            break
        crc = zlib.crc32(buf[:n], crc)
        left -= n
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
    with _lock:
        done = _mcap_cache.get(key)
        if done is not None:
            return done
        running = _running.get(key)
        if running is None:  # this thread checks it; any other asking waits for the result
            running = _running[key] = threading.Event()
            mine = True
        else:
            mine = False
    if not mine:
        running.wait()
        with _lock:
            done = _mcap_cache.get(key)
        return done if done is not None else _checked(path)  # its checker failed: check here
    try:
        verified: list[bool] = []
        result = (_check_mcap(path, st.st_size, verified), bool(verified))
        with _lock:
            _mcap_cache[key] = result
        return result
    finally:
        with _lock:
            _running.pop(key, None)
        running.set()


def check_in_background(paths: Iterable[str | os.PathLike]) -> threading.Thread | None:
    """Start checking the MCAP files of ``paths`` (bag directories, ``.mcap`` files; anything
    else is skipped) in a daemon thread: reading and CRC-32 hold no GIL, so it runs beside the
    caller's own start (its imports). Whoever asks for a file's result later
    (:func:`check_mcap`, :func:`data_crc_verified`) gets it, waiting if it is still being
    computed. Returns the thread (``None``: no MCAP file named).
    """
    files = []
    for p in map(Path, paths):
        try:
            if p.is_dir():
                files += sorted(p.glob("*.mcap"))
            elif p.suffix == ".mcap" and p.is_file():
                files.append(p)
        except OSError:
            continue
    if not files:
        return None

    def run() -> None:
        for f in files:
            try:
                _checked(f)
            except Exception:  # noqa: BLE001 - the opener checks again and reports it
                pass

    thread = threading.Thread(target=run, name="mcap-checksums", daemon=True)
    thread.start()
    return thread


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

__all__ = ["MCAP_MAGIC", "check_in_background", "check_mcap", "data_crc_verified"]
