"""Raw messages of an indexed MCAP file, read through its chunk and message indexes.

``rosbags`` reads every chunk that holds a wanted message whole: it copies each record of the
chunk (the RGB images a labels replay never looks at included) and computes the chunk's CRC-32.
:class:`IndexedMcap` looks the wanted messages up in the chunk's message index records and
reads only their bytes from a memory map of the file. Where the whole data section's CRC was
verified when the bag was opened (:func:`bags.io.integrity.data_crc_verified`), the chunk CRCs
are redundant and an uncompressed chunk is never read whole; otherwise (no data CRC, compressed
chunks) each chunk is read, decompressed and CRC-checked as rosbags does.

The messages come in the order of ``rosbags``' MCAP reader: by log time, ties by the chunk's
position in the file, within a chunk by log time and then by position (rosbags sorts each chunk
stably and merges the chunks on ``(log time, chunk offset)``).

Only files that are a bag's sole storage file, indexed (a summary with chunk indexes, every
chunk with message indexes) and of the ``ros2`` profile are read this way; :meth:`IndexedMcap.open`
returns ``None`` for others, which are left to ``rosbags``.
"""

from __future__ import annotations

import heapq
import mmap
import struct
from collections.abc import Iterator
from pathlib import Path

_MSG_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, log time, publish time
_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, record length, channel, entries' byte length
_MESSAGE, _MESSAGE_INDEX = 0x05, 0x07
_CHUNK_FIXED = 1 + 8 + 8 + 8 + 8 + 4 + 4  # opcode, length, start, end, uncompressed size, crc, compression's length


class McapIndexError(Exception):
    """The file's indexes do not match its records (damage the caller reports)."""


class IndexedMcap:
    """Raw messages of one indexed MCAP file (see module docstring). Use :meth:`open`."""

    def __init__(self, path: Path, summary, verified: bool) -> None:
        self.path = path
        self._file = path.open("rb")
        self._mm = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
        self._chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
        #: channel id -> topic
        self.topics = {cid: ch.topic for cid, ch in summary.channels.items()}
        self._verified = verified
        self._cached: tuple[int, bytes] | None = None

    @classmethod
    def open(cls, path: Path, verified: bool) -> IndexedMcap | None:
        """The reader of ``path``, or ``None`` when the file is not indexed as this reader needs.

        ``verified``: the data section CRC was checked when the bag was opened.
        """
        from mcap.reader import make_reader

        try:
            with path.open("rb") as f:
                reader = make_reader(f)
                header, summary = reader.get_header(), reader.get_summary()
        except Exception:  # noqa: BLE001 - any doubt: leave the file to rosbags
            return None
        if (summary is None or header.profile != "ros2" or not summary.chunk_indexes
                or any(not c.message_index_offsets and c.uncompressed_size for c in summary.chunk_indexes)):
            return None
        try:
            from rosbags.rosbag2.storage_mcap import DECOMPRESSORS
        except ImportError:
            return None
        if any(c.compression not in DECOMPRESSORS for c in summary.chunk_indexes):
            return None
        try:
            return cls(path, summary, verified)
        except (OSError, ValueError):  # e.g. a file that cannot be memory-mapped
            return None

    def close(self) -> None:
        """Release the memory map and the file (a map that views of :meth:`messages` still
        use is released with the last of them).
        """
        self._cached = None
        try:
            self._mm.close()
        except BufferError:  # views still exported: the map goes when they do
            pass
        self._file.close()

    # ------------------------------------------------------------------ index
    def _entries(self, chunk, channels: set[int]) -> list[tuple[int, int, int, int]]:
        """``(log time, chunk offset, record offset, channel)`` of the chunk's wanted messages."""
        mm, out = self._mm, []
        for cid, at in chunk.message_index_offsets.items():
            if cid not in channels:
                continue
            op, _, channel, n = _INDEX_HEAD.unpack_from(mm, at)
            if op != _MESSAGE_INDEX or channel != cid or n % 16:
                raise McapIndexError(f"message index of channel {cid} at byte {at} is damaged")
            entries = struct.unpack_from(f"<{n // 8}Q", mm, at + _INDEX_HEAD.size)
            start = chunk.chunk_start_offset
            out.extend((entries[i], start, entries[i + 1], cid) for i in range(0, len(entries), 2))
        out.sort()
        return out

    def _chunk_source(self, chunk, channels: set[int]) -> Iterator[tuple[int, int, int, int]]:
        # first a marker at the chunk's start time, so that merging reads no index before it is due
        yield (chunk.message_start_time, 0, 0, -1)
        yield from self._entries(chunk, channels)

    def _records(self, chunk) -> tuple[bytes | mmap.mmap, int]:
        """The buffer holding the chunk's records and where they start in it."""
        records_at = chunk.chunk_start_offset + _CHUNK_FIXED + len(chunk.compression) + 8
        if self._verified and not chunk.compression:
            return self._mm, records_at
        if self._cached is not None and self._cached[0] == chunk.chunk_start_offset:
            return self._cached[1], 0
        from rosbags.rosbag2.storage_mcap import decompress

        (crc,) = struct.unpack_from("<I", self._mm, chunk.chunk_start_offset + 1 + 8 + 24)
        data = decompress(self._mm[records_at:records_at + chunk.compressed_size], chunk.compression,
                          chunk.uncompressed_size, crc)
        self._cached = (chunk.chunk_start_offset, data)
        return data, 0

    # --------------------------------------------------------------- messages
    def messages(self, topics: set[str] | None, views: bool = False) -> Iterator[tuple[str, int, bytes | memoryview]]:
        """``(topic, log_ns, raw CDR bytes)`` of ``topics`` (None = all) in rosbags' order.

        ``views``: each message as a read-only memoryview of the file's bytes (no copy), for
        callers that decode it before it is dropped or copy it (the map stays while it lives).

        Raises:
            McapIndexError: an index entry that does not point at its message record.
            rosbags' ReaderError: a chunk whose CRC or size does not match.
        """
        channels = {cid for cid, t in self.topics.items() if topics is None or t in topics}
        if not channels:
            return
        by_offset = {c.chunk_start_offset: c for c in self._chunks}
        sources = [self._chunk_source(c, channels) for c in self._chunks
                   if any(cid in channels for cid in c.message_index_offsets)]
        for log_ns, chunk_at, offset, cid in heapq.merge(*sources):
            if cid < 0:
                continue
            buf, base = self._records(by_offset[chunk_at])
            at = base + offset
            op, length, channel, _, log_time, _ = _MSG_HEAD.unpack_from(buf, at)
            if op != _MESSAGE or channel != cid or log_time != log_ns or length < 22:
                raise McapIndexError(f"message index entry at chunk {chunk_at} + {offset} does not "
                                     "point at its message")
            if views:
                yield self.topics[cid], log_ns, memoryview(buf)[at + _MSG_HEAD.size:at + 9 + length]
            else:
                yield self.topics[cid], log_ns, bytes(buf[at + _MSG_HEAD.size:at + 9 + length])
