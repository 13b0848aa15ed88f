"""MCAP storage with checksums for :class:`bags.io.writer.BagWriter`.

``rosbags``' own MCAP storage writes every CRC as 0 ("not computed"), so a flipped byte in a
bag goes unnoticed: the message deserializes to a different value and a replay scores it as
if nothing happened. :class:`CrcMcapStorage` is a drop-in storage plugin for
``rosbags.rosbag2.Writer`` built on the ``mcap`` library's writer instead, with

* a CRC-32 of every chunk's uncompressed records (verified by rosbags and by the ``mcap``
  stream reader whenever a chunk is read),
* the data section CRC in the DataEnd record and the summary CRC in the footer (verified
  when a bag is opened, see :mod:`bags.io.integrity`).

The records are those of rosbag2's MCAP layout (profile ``ros2``, one schema per message type
in ``ros2msg``/``ros2idl``, channels with ``offered_qos_profiles`` metadata, a ``rosbag2``
metadata record with the serialized bag metadata), uncompressed chunks of at most
:data:`CHUNK_SIZE` bytes. :func:`rosbag2_writer` opens a ``rosbags`` writer that uses it.

The data section CRC covers every byte before the DataEnd record, so each chunk's records would
be read twice, once for the chunk's CRC and once for the data section's. :class:`_DataCrcFile`
(the file under the ``mcap`` writer) computes the data section's CRC instead: a chunk record's
records enter it through the chunk's own CRC (:func:`crc32_combine`, zlib's arithmetic), the rest
byte by byte; once the file is finished, it writes the CRC into the DataEnd record (which the
``mcap`` writer, its data CRCs off, left 0). The bytes are those the ``mcap`` writer writes with
its data CRCs on.
"""

from __future__ import annotations

import struct
import zlib
from importlib.metadata import version
from pathlib import Path
from typing import Any

#: Default uncompressed chunk size (bytes), as rosbags' and rosbag2's MCAP writers use.
CHUNK_SIZE = 1 << 20


class CrcMcapStorage:
    """A ``rosbags`` storage writer (``StorageWriter`` protocol) producing checksummed MCAP.

    Args:
        path: the bag directory; the file is ``<path>/<path.name>.mcap``.
        compression: rosbags' compression mode; only ``NONE`` is supported.
        chunk_size: uncompressed bytes per chunk.
    """

    def __init__(self, path: Path, compression: Any, chunk_size: int = CHUNK_SIZE) -> None:
        from mcap.writer import CompressionType, Writer
        from rosbags.rosbag2.enums import CompressionMode

        if compression not in (None, CompressionMode.NONE):
            raise ValueError(f"compression mode {compression} is not supported")
        self.path = path / f"{path.name}.mcap"
        self._file = self.path.open("xb")
        self._data_crc = _DataCrcFile(self._file, self.path)
        self._writer = Writer(self._data_crc, chunk_size=chunk_size,
                              compression=CompressionType.NONE, enable_crcs=True,
                              enable_data_crcs=False)  # _DataCrcFile computes it
        self._writer.start(profile="ros2", library=f"bev_mapper+mcap-{version('mcap')}")
        self._schemas: dict[str, int] = {}
        self._channels: dict[int, int] = {}

    def add_msgtype(self, connection: Any) -> None:
        """Register the schema of a connection's message type."""
        from rosbags.interfaces import MessageDefinitionFormat

        fmt = "ros2msg" if connection.msgdef.format == MessageDefinitionFormat.MSG else "ros2idl"
        self._schemas[connection.msgtype] = self._writer.register_schema(
            connection.msgtype, fmt, connection.msgdef.data.encode())

    def add_connection(self, connection: Any, offered_qos_profiles: str) -> None:
        """Register a channel for a connection."""
        self._channels[connection.id] = self._writer.register_channel(
            connection.topic, connection.ext.serialization_format,
            self._schemas[connection.msgtype], {"offered_qos_profiles": offered_qos_profiles})

    def write(self, connection: Any, timestamp: int, data: bytes | memoryview) -> None:
        """Write one serialized message (log and publish time = ``timestamp``)."""
        self._writer.add_message(self._channels[connection.id], timestamp, bytes(data),
                                 timestamp)

    def close(self, version: int, metadata: str) -> None:
        """Write the rosbag2 metadata record, the summary and the footer; close the file."""
        del version
        try:
            self._writer.add_metadata("rosbag2", {"serialized_metadata": metadata})
            self._writer.finish()
            self._data_crc.write_data_end()
        finally:
            self._file.close()

    def abort(self) -> None:
        """Close without summary (the file is left truncated)."""
        self._file.close()


_CRC_POLY = 0xEDB88320  # CRC-32 (zlib's), reflected


def _multmodp(a: int, b: int) -> int:
    """``a * b`` modulo the CRC polynomial (zlib's ``multmodp``; ``a`` nonzero)."""
    m, p = 1 << 31, 0
    while True:
        if a & m:
            p ^= b
            if not a & (m - 1):
                return p
        m >>= 1
        b = (b >> 1) ^ _CRC_POLY if b & 1 else b >> 1


def _x2n_table() -> list[int]:
    p, table = 1 << 30, []  # x^1
    for _ in range(32):
        table.append(p)
        p = _multmodp(p, p)
    return table


_X2N = _x2n_table()  # x^(2^n) modulo the polynomial
_X2N_BYTES: dict[int, list[list[int]]] = {}  # n -> per byte of b, _multmodp(_X2N[n], b) of that byte's 256 values


def _times_x2n(n: int, b: int) -> int:
    """``_multmodp(_X2N[n], b)`` by four table lookups (the product is linear in ``b``)."""
    tables = _X2N_BYTES.get(n)
    if tables is None:
        bits = [_multmodp(_X2N[n], 1 << j) for j in range(32)]
        tables = []
        for byte in range(4):
            t = [0] * 256
            for v in range(1, 256):
                low = v & -v  # the lowest set bit: t[v] = t[v without it] ^ its product
                t[v] = t[v ^ low] ^ bits[8 * byte + low.bit_length() - 1]
            tables.append(t)
        _X2N_BYTES[n] = tables
    t0, t1, t2, t3 = tables
    return t0[b & 255] ^ t1[(b >> 8) & 255] ^ t2[(b >> 16) & 255] ^ t3[b >> 24]


def crc32_combine(crc1: int, crc2: int, len2: int) -> int:
    """The CRC-32 of ``A + B`` from ``crc1 = zlib.crc32(A)``, ``crc2 = zlib.crc32(B)`` and
    ``len2 = len(B)`` (zlib's ``crc32_combine``), without reading the bytes.
    """
    p, k, n = 1 << 31, 3, len2  # x^0; x^(8 * len2) from the table
    while n:
        if n & 1:
            p = _times_x2n(k & 31, p)
        n >>= 1
        k += 1
    return _multmodp(p, crc1) ^ crc2


_CHUNK_HEAD = struct.Struct("<BQQQQII")  # opcode, length, start, end, uncompressed size, CRC, compression's length
_DATA_END = b"\x0f" + struct.pack("<QI", 4, 0)  # DataEnd, its CRC 0 (the writer's data CRCs off)
_FOOTER = struct.Struct("<BQQQI")  # opcode, length, summary start, summary offset start, summary CRC
_MAGIC_LEN = 8


class _DataCrcFile:
    """The file under the ``mcap`` writer: passes every write on and computes the data section's
    CRC on the way (see module docstring); :meth:`write_data_end` writes it into the DataEnd record.
    """

    def __init__(self, file, path: Path) -> None:
        self._file = file
        self._path = path
        self._at = file.tell()
        self._crc = 0
        self._data_end: tuple[int, int] | None = None  # where DataEnd was written, the CRC before it

    def tell(self) -> int:
        """The position in the file (every write goes through here)."""
        return self._at

    def flush(self) -> None:
        """Flush the file."""
        self._file.flush()

    def write(self, data) -> int:
        """Write ``data`` on, its bytes entered into the CRC."""
        if self._data_end is None and data == _DATA_END:  # no other record is 13 bytes long
            self._data_end = (self._at, self._crc)
        self._crc = self._entered(data)
        n = self._file.write(data)
        self._at += n
        return n

    def _entered(self, data) -> int:
        """The CRC with ``data`` entered: an uncompressed chunk record through its own CRC."""
        crc = self._crc
        if len(data) > _CHUNK_HEAD.size and data[0] == 0x06:
            _, length, _, _, size, chunk_crc, comp = _CHUNK_HEAD.unpack_from(data)
            head = _CHUNK_HEAD.size + comp + 8  # then the records' length and the records
            if (comp == 0 and chunk_crc and len(data) == 9 + length == head + size
                    and struct.unpack_from("<Q", data, head - 8)[0] == size):
                return crc32_combine(zlib.crc32(memoryview(data)[:head], crc), chunk_crc, size)
        return zlib.crc32(data, crc)

    def write_data_end(self) -> None:
        """Write the data section's CRC into the DataEnd record of the finished file: the record
        the footer's summary start follows (where the CRC was not followed up to it, it is read
        from the file).

        Raises:
            ValueError: the file has no DataEnd record before its summary.
        """
        f = self._file
        f.flush()
        with self._path.open("rb") as r:
            r.seek(self._at - _MAGIC_LEN - _FOOTER.size)
            opcode, _, summary_start, _, _ = _FOOTER.unpack(r.read(_FOOTER.size))
            at = summary_start - len(_DATA_END)
            r.seek(max(at, 0))
            if opcode != 0x02 or at < 0 or r.read(len(_DATA_END)) != _DATA_END:
                raise ValueError(f"{self._path}: no DataEnd record before the summary")
            if self._data_end is not None and self._data_end[0] == at:
                crc = self._data_end[1]
            else:
                r.seek(0)
                crc = zlib.crc32(r.read(at))
        f.seek(at + 9)  # the DataEnd's CRC
        f.write(struct.pack("<I", crc))
        f.seek(self._at)


def rosbag2_writer(path: Path, storage: str, chunk_size: int = CHUNK_SIZE) -> Any:
    """A ``rosbags.rosbag2.Writer`` for ``path`` (not opened); MCAP through
    :class:`CrcMcapStorage` with ``chunk_size``, sqlite3 through rosbags' own storage.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer

    class _McapStorage(CrcMcapStorage):
        def __init__(self, p: Path, compression: Any) -> None:
            super().__init__(p, compression, chunk_size)

    class _Writer(Writer):
        STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: _McapStorage}

    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    return _Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugin)
