"""Message sources behind :class:`bags.io.reader.BagReader`.

* :class:`AnyReaderSource`: ``rosbags.highlevel.AnyReader`` on a rosbag2 directory (mcap or
  sqlite3 storage) or a plain ``.mcap`` / ``.db3`` file. The normal path.
* :class:`McapStreamSource`: a forward-only scan with the ``mcap`` library's
  :class:`~mcap.stream_reader.StreamReader`. Used when rosbags refuses an mcap file because
  its summary/footer is missing (a truncated or interrupted recording): it yields every
  message of the intact chunks, then raises :class:`BagCorruptError`.

Both yield ``(topic, msgtype, log_ns, message)`` with messages deserialized by rosbags (or by
the caller's ``deserialize``, e.g. :func:`bags.io.raw.fast_deserializer`), and turn any storage
failure during iteration into :class:`BagCorruptError`. A bag whose storage is one indexed MCAP
file is read by :class:`AnyReaderSource` through the file's indexes
(:class:`bags.io.raw.IndexedMcap`: only the wanted messages' bytes, in rosbags' order).

:func:`open_source` reads ``metadata.yaml`` safely (:mod:`bags.io.metadata`) and checks the
storage files (:mod:`bags.io.integrity`): an MCAP file whose summary or data section checksum
does not match is read as a stream (chunk checksums verified), stopping at the first damaged
chunk; a sqlite3 file with messages of unknown topic ids is read with :attr:`damage` set. An
unusable ``metadata.yaml`` next to MCAP files is reported the same way (the files are read as
streams); without MCAP files it is a :class:`BagFormatError`.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from ..errors import BagCorruptError, BagFormatError
from .integrity import check_mcap, check_sqlite, data_crc_verified
from .metadata import MetadataError, read_metadata
from .raw import IndexedMcap

#: suffixes of bag files (a rosbag2 bag is a directory holding ``metadata.yaml`` or MCAP files)
BAG_SUFFIXES = (".mcap", ".db3")

log = logging.getLogger(__name__)
T = TypeVar("T")


@dataclass(frozen=True)
class TopicSummary:
    """A topic of a bag: its type and message count (as far as the source could tell)."""

    topic: str
    msgtype: str
    count: int


def _mcap_files(path: Path, meta: dict) -> list[Path]:
    if path.is_file():
        return [path] if path.suffix == ".mcap" else []
    names = meta.get("relative_file_paths") or sorted(p.name for p in path.glob("*.mcap"))
    names = [Path(str(n)).name for n in names]  # as rosbags: files lie in the bag directory
    return [path / n for n in names if n.endswith(".mcap") and (path / n).exists()]


class AnyReaderSource:
    """Messages through ``rosbags.highlevel.AnyReader``.

    ``damage`` is set when the storage has messages rosbags cannot attribute (sqlite3 rows
    with unknown topic ids): :meth:`messages` then yields every readable message and raises
    :class:`BagCorruptError` at the end, like a stream that reached its damage.
    """

    def __init__(self, path: Path, meta: dict, damage: str | None = None, mcap_files: list[Path] = (),
                 damaged: Callable[[], list[str]] | None = None) -> None:
        from rosbags.highlevel import AnyReader

        self.path = path
        self.damage = damage
        self.custom_data = dict(meta.get("custom_data") or {})
        self._reader = AnyReader([path])
        self._reader.open()  # errors handled by open_source
        self._indexed = None
        # damaged(): the MCAP checksums' findings (checked beside the opening; damaged: not indexed,
        # the caller reads the files as a stream)
        bad = damaged() if damaged is not None else []
        if len(mcap_files) == 1 and not damage and not bad and meta.get("compression_mode", "") != "message":
            self._indexed = IndexedMcap.open(mcap_files[0], data_crc_verified(mcap_files[0]))
        self.topics = {
            name: TopicSummary(name, info.msgtype or "", int(info.msgcount))
            for name, info in self._reader.topics.items()
        }
        self.topic_order = [c.topic for c in sorted(self._reader.connections, key=lambda c: c.id)]
        self.latched = {
            c.topic for c in self._reader.connections
            for qos in (getattr(getattr(c, "ext", None), "offered_qos_profiles", ()) or ())
            if getattr(getattr(qos, "durability", None), "name", "") == "TRANSIENT_LOCAL"
        }

    def _raw(self, topics: set[str] | None, views: bool = False) -> Iterator[tuple[str, str, int, bytes]]:
        """``(topic, msgtype, log_ns, CDR bytes)`` of ``topics`` (None = all) in log-time order
        (``views``: memoryviews of the file where it is read through its indexes).
        """
        conns = [c for c in self._reader.connections if topics is None or c.topic in topics]
        if not conns:
            return
        if self._indexed is not None:
            types = {c.topic: c.msgtype for c in conns}
            for topic, t, raw in self._indexed.messages(set(types), views):
                yield topic, types[topic], t, raw
            return
        for conn, t, raw in self._reader.messages(connections=conns):
            yield conn.topic, conn.msgtype, t, raw

    def messages(self, topics: set[str] | None = None, deserialize=None,
                 views: bool = False) -> Iterator[tuple[str, str, int, Any]]:
        """``(topic, msgtype, log_ns, message)`` of ``topics`` (None = all) in log-time order,
        deserialized by ``deserialize(raw, msgtype)`` (default: rosbags'). ``views``:
        ``deserialize`` takes read-only memoryviews of the file as well as bytes (no copy of
        each message's bytes; it copies what it keeps).
        """
        it = self._raw(topics, views and deserialize is not None)
        deserialize = deserialize or self._reader.deserialize
        count = 0
        while True:
            try:
                topic, msgtype, t, raw = next(it)
                msg = deserialize(raw, msgtype)
            except StopIteration:
                if self.damage:
                    raise BagCorruptError(f"{self.path}: bag is damaged ({self.damage}); read "
                                          f"{count} messages") from None
                return
            except Exception as exc:  # anything the storage layer raises here is damage
                raise BagCorruptError(
                    f"{self.path}: bag is damaged after {count} readable messages: "
                    f"{type(exc).__name__}: {exc}"
                ) from exc
            if t < 0:  # sqlite3 stores any integer; a log time before 1970 is damage
                raise BagCorruptError(f"{self.path}: bag is damaged after {count} readable "
                                      f"messages: {topic} has the negative log time {t}")
            count += 1
            yield topic, msgtype, t, msg

    def deserializer(self):
        """``deserialize(raw, msgtype)`` of this bag's types (rosbags')."""
        return self._reader.deserialize

    def close(self) -> None:
        """Release the storage."""
        if self._indexed is not None:
            self._indexed.close()
        self._reader.close()


class McapStreamSource:
    """Forward-only reading of (possibly truncated) mcap files."""

    def __init__(self, path: Path, files: list[Path], meta: dict, damage: str) -> None:
        self.path = path
        self.files = files
        self.damage = damage
        self.custom_data = dict(meta.get("custom_data") or {})
        self._typestore = None
        self.topics: dict[str, TopicSummary] = {}
        self.topic_order: list[str] = []
        self._scan()

    def _records(self, path: Path):
        from mcap.stream_reader import StreamReader

        with path.open("rb") as f:
            yield from StreamReader(f, skip_magic=False, validate_crcs=True).records

    def _scan(self) -> None:
        """Collect schemas, channels and counts up to the damage."""
        from mcap.records import Channel, Message, Schema

        schemas: dict[tuple[Path, int], Any] = {}
        channels: dict[tuple[Path, int], tuple[str, str]] = {}
        counts: dict[str, int] = {}
        for path in self.files:
            try:
                for rec in self._records(path):
                    if isinstance(rec, Schema):
                        schemas[(path, rec.id)] = rec
                    elif isinstance(rec, Channel):
                        schema = schemas.get((path, rec.schema_id))
                        name = schema.name if schema is not None else ""
                        channels[(path, rec.id)] = (rec.topic, name)
                        if rec.topic not in self.topic_order:
                            self.topic_order.append(rec.topic)
                    elif isinstance(rec, Message) and (path, rec.channel_id) in channels:
                        topic = channels[(path, rec.channel_id)][0]
                        counts[topic] = counts.get(topic, 0) + 1
            except Exception as exc:  # damage ends the scan; messages() reports it
                log.debug("scan of %s stopped: %s", path, exc)
        if not channels:
            with self.files[0].open("rb") as f:
                is_mcap = f.read(8) == b"\x89MCAP0\r\n"
            if is_mcap:
                raise BagCorruptError(
                    f"{self.path}: mcap file damaged before its first complete chunk, nothing "
                    f"is readable ({self.damage})"
                )
            raise BagFormatError(f"{self.path}: not an mcap file ({self.damage})")
        self._channels = channels
        for topic, msgtype in channels.values():
            self.topics[topic] = TopicSummary(topic, msgtype, counts.get(topic, 0))
        self._typestore = self._make_typestore(schemas.values())

    @staticmethod
    def _make_typestore(schemas):
        from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

        store = get_typestore(Stores.EMPTY)
        try:
            types: dict = {}
            for s in schemas:
                text = s.data.decode()
                if s.encoding == "ros2msg":
                    types.update(get_types_from_msg(text, s.name))
                elif s.encoding == "ros2idl":
                    types.update(get_types_from_idl(text))
            store.register(types)
            return store
        except Exception as exc:  # fall back to the stock Jazzy definitions
            log.debug("schema parsing failed (%s); using the Jazzy typestore", exc)
            return get_typestore(Stores.ROS2_JAZZY)

    def messages(self, topics: set[str] | None = None, deserialize=None,
                 views: bool = False) -> Iterator[tuple[str, str, int, Any]]:
        """``(topic, msgtype, log_ns, message)`` of ``topics`` (None = all), CRC-checked, up to any
        damage; deserialized by ``deserialize(raw, msgtype)`` (default: rosbags'); ``views`` as
        :meth:`AnyReaderSource.messages` (the bytes here are always copies).
        """
        from mcap.records import Message

        del views
        deserialize = deserialize or self._typestore.deserialize_cdr
        count = 0
        for path in self.files:
            it = self._records(path)
            while True:
                try:
                    rec = next(it)
                    if not isinstance(rec, Message) or (path, rec.channel_id) not in self._channels:
                        continue
                    topic, msgtype = self._channels[(path, rec.channel_id)]
                    if topics is not None and topic not in topics:
                        continue
                    msg = deserialize(rec.data, msgtype)
                except StopIteration:
                    break
                except Exception as exc:
                    raise BagCorruptError(
                        f"{self.path}: bag is damaged ({self.damage}); stopped after {count} "
                        f"readable messages: {type(exc).__name__}: {exc}"
                    ) from exc
                count += 1
                yield topic, msgtype, int(rec.log_time), msg
        # the scan ended cleanly although rosbags refused the file (e.g. no summary section)
        raise BagCorruptError(f"{self.path}: bag is damaged ({self.damage}); read {count} messages")

    def deserializer(self):
        """``deserialize(raw, msgtype)`` of this bag's types (rosbags')."""
        return self._typestore.deserialize_cdr

    def close(self) -> None:
        """Nothing to release (every read opens the file itself)."""


def _sqlite_files(path: Path, meta: dict) -> list[Path]:
    if path.is_file():
        return [path] if path.suffix == ".db3" else []
    names = meta.get("relative_file_paths") or ()
    names = [Path(str(n)).name for n in names]
    return [path / n for n in names if n.endswith(".db3") and (path / n).exists()]


def open_source(path: str | Path):
    """Open a bag path with the best source (see module docstring).

    Raises:
        BagFormatError: not a bag (missing path, unknown suffix, no readable content, unusable
            metadata.yaml without MCAP files to fall back on).
        BagCorruptError: a damaged bag that no source can read at all.
    """
    from rosbags.highlevel import AnyReaderError

    path = Path(path)
    if not path.exists():
        raise BagFormatError(f"{path}: no such file or directory")
    if path.is_file() and path.suffix not in BAG_SUFFIXES:
        raise BagFormatError(f"{path}: not a bag (expected a rosbag2 directory, .mcap or .db3)")
    meta: dict = {}
    if path.is_dir():
        try:
            meta = read_metadata(path) or {}
        except MetadataError as exc:
            files = _mcap_files(path, {})
            if not files:
                raise BagFormatError(f"{path}: {exc}") from None
            log.warning("%s: %s; reading the MCAP files as streams", path, exc)
            return McapStreamSource(path, files, {}, f"unusable metadata.yaml: {exc}")
        if not meta:
            files = _mcap_files(path, meta)
            if files:
                return McapStreamSource(path, files, meta, "metadata.yaml is missing")
            raise BagFormatError(f"{path}: not a rosbag2 directory (no metadata.yaml)")
    files = _mcap_files(path, meta)
    # the MCAP checksums (reading every byte of the files) run beside rosbags' opening of the
    # bag (mostly Python): both are done before a message is read, and a damaged file is read
    # as a stream, as if it had been checked first
    damaged = _in_background(lambda: [p for p in map(check_mcap, files) if p])
    damage = "; ".join(p for p in map(check_sqlite, _sqlite_files(path, meta)) if p) or None
    try:
        source = AnyReaderSource(path, meta, damage, files, damaged)
    except Exception as exc:  # rosbags' ReaderError/AnyReaderError, sqlite3 errors, ...
        if damaged():
            return _damaged_stream(path, files, meta, damaged())
        reason = f"{type(exc).__name__}: {exc}"
        if files and not isinstance(exc, FileNotFoundError):
            log.warning("%s: rosbags cannot open it (%s); reading it as a stream", path, reason)
            return McapStreamSource(path, files, meta, reason)
        if isinstance(exc, AnyReaderError) and "malformed" not in str(exc):
            raise BagFormatError(f"{path}: cannot open bag: {reason}") from None
        raise BagCorruptError(f"{path}: cannot open bag: {reason}") from None
    if damaged():
        source.close()
        return _damaged_stream(path, files, meta, damaged())
    return source


def _damaged_stream(path: Path, files: list[Path], meta: dict, bad: list[str]) -> McapStreamSource:
    """The stream source of a bag whose MCAP files failed their checksums (``bad``: what is wrong)."""
    log.warning("%s: %s; reading it as a stream up to the damage", path, bad[0])
    return McapStreamSource(path, files, meta, "; ".join(bad))


def _in_background(fn: Callable[[], T]) -> Callable[[], T]:
    """Start ``fn()`` in a thread; returns a function that waits for its result (re-raising its
    exception), any number of times.
    """
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - re-raised by the caller's wait
            box["error"] = exc

    thread = threading.Thread(target=run, name="bag-checksums", daemon=True)
    thread.start()

    def result() -> T:
        thread.join()
        if "error" in box:
            raise box["error"]
        return box["value"]

    return result
