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
"""

from __future__ import annotations

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
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=CompressionType.NONE, enable_crcs=True,
                              enable_data_crcs=True)
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
        finally:
            self._file.close()

    def abort(self) -> None:
        """Close without summary (the file is left truncated)."""
        self._file.close()


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
