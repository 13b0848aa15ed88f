"""Seeded generator of damaged bev_mapper bags, for ``tests/bags/io/test_bag_fuzz.py``.

:func:`make_base` writes one small intact synthetic drive (front1 rig at quarter scale, a
coarse grid) as MCAP and as sqlite3 and keeps its deserialized messages in memory;
:func:`variants` lists the damaged bags built from it, each in milliseconds:

* ``storage``: byte flips inside MCAP chunks, byte flips anywhere, truncation at random
  offsets (offsets drawn from a seeded ``random.Random``);
* ``metadata``: ``metadata.yaml`` binary, not a mapping, an alias bomb, wrong field types,
  non-string ``custom_data``, oversized, empty or missing;
* ``message``: the bag re-written through :class:`bags.io.writer.BagWriter` with one defect:
  a wrong message type on a topic, negative / huge stamps, a GT grid with huge dimensions,
  a rotated or truncated GT grid, a wrong-size or undecodable label image, a NaN odometry
  quaternion (most of them from frame :data:`FROM` on), a camera without CameraInfo;
* ``sqlite``: messages whose topic id is not in the topics table, a truncated database.

A variant's :attr:`Variant.from_frame` is the first damaged frame when the damage starts
mid-bag: a replay must keep the outputs of the frames before it.
"""

from __future__ import annotations

import dataclasses
import math
import random
import shutil
import sqlite3
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bags.cli.main import main
from bags.io import topics as T
from bags.io.reader import BagReader
from bags.io.writer import BagWriter

FRAMES = 12
#: first damaged frame of the mid-bag variants
FROM = 6
SEED = 950_000_001
GRID_ARGS = ["--grid-x-min", "-10", "--grid-x-max", "10", "--grid-y-min", "-5",
             "--grid-y-max", "5", "--grid-res", "0.5"]
CAM = "front"
LABELS = T.image_topic(CAM, "labels")
RGB = T.image_topic(CAM, "rgb")
INFO = T.camera_info_topic(CAM)
GT0 = T.gt_topic("drivable")


@dataclass
class Base:
    """The intact bags and their messages ``(topic, msgtype, log_ns, msg)``."""

    root: Path
    mcap: Path
    sqlite: Path
    messages: list[tuple[str, str, int, Any]]
    types: dict[str, str]
    latched: set[str]
    custom_data: dict[str, str]

    @property
    def mcap_file(self) -> Path:
        return next(self.mcap.glob("*.mcap"))


#: MCAP chunk size of the base bag: small, so that it has several chunks (~10) and damage
#: in a later chunk leaves the frames of the earlier ones readable.
CHUNK = 32 << 10


def make_base(root: Path) -> Base:
    """Write the intact drive (mcap with small chunks, and sqlite3) under ``root``."""
    sqlite = root / "base_sqlite3"
    argv = ["synth", str(sqlite), "--rig", "front1", "--scale", "0.25", "--frames",
            str(FRAMES), "--seed", str(SEED), "--storage", "sqlite3", *GRID_ARGS]
    assert main(argv) == 0
    with BagReader(sqlite) as r:
        msgs = [(m.topic, m.msgtype, m.log_ns, m.msg) for m in r.messages()]
        types = {t: s.msgtype for t, s in r.topics.items()}
        base = Base(root, root / "base_mcap", sqlite, msgs, types, r.latched_topics,
                    r.custom_data)
    (root / "w").mkdir()
    rewrite(base, root / "w", lambda t, ty, ns, msg, i: [(t, ns, msg)], chunk_size=CHUNK)
    (root / "w" / "bag").rename(base.mcap)
    return base


@dataclass(frozen=True)
class Variant:
    """One damaged bag: ``build(base, dst_dir, rng) -> bag path``."""

    name: str
    kind: str
    build: Callable[[Base, Path, random.Random], Path]
    from_frame: int | None = None


# ------------------------------------------------------------------ storage level
def _copy(base: Base, dst: Path) -> Path:
    bag = dst / "bag"
    shutil.copytree(base.mcap, bag)
    # the mcap file is named after the directory it was written in
    return bag


def _mcap(bag: Path) -> Path:
    return next(bag.glob("*.mcap"))


def chunk_data_ranges(data: bytes) -> list[tuple[int, int]]:
    """``[(start, end)]`` byte ranges of the record data of every top-level MCAP chunk."""
    out, pos = [], 8
    while pos + 9 <= len(data):
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        body = pos + 9
        if op == 0x06:
            (clen,) = struct.unpack_from("<I", data, body + 28)
            start = body + 32 + clen + 8
            out.append((start, body + length))
        if op == 0x02:  # footer
            break
        pos = body + length
    return out


def mcap_crcs(data: bytes) -> tuple[list[int], int, int]:
    """``(chunk CRCs, data section CRC, summary CRC)`` of an MCAP file (0 = not written)."""
    crcs, pos = [], 8
    data_crc = None
    while pos + 9 <= len(data):
        op = data[pos]
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        if op == 0x06:
            crcs.append(struct.unpack_from("<I", data, pos + 9 + 24)[0])
        elif op == 0x0F:
            (data_crc,) = struct.unpack_from("<I", data, pos + 9)
            break
        pos += 9 + length
    (summary_crc,) = struct.unpack_from("<I", data, len(data) - 8 - 4)
    return crcs, data_crc, summary_crc


def _flip(data: bytearray, offset: int, rng: random.Random) -> None:
    data[offset] ^= 1 << rng.randrange(8)


def flip_in_chunk(base: Base, dst: Path, rng: random.Random) -> Path:
    bag = _copy(base, dst)
    f = _mcap(bag)
    data = bytearray(f.read_bytes())
    a, b = rng.choice(chunk_data_ranges(bytes(data)))
    _flip(data, rng.randrange(a, b), rng)
    f.write_bytes(bytes(data))
    return bag


def flip_anywhere(base: Base, dst: Path, rng: random.Random) -> Path:
    bag = _copy(base, dst)
    f = _mcap(bag)
    data = bytearray(f.read_bytes())
    _flip(data, rng.randrange(len(data)), rng)
    f.write_bytes(bytes(data))
    return bag


def truncate(base: Base, dst: Path, rng: random.Random) -> Path:
    bag = _copy(base, dst)
    f = _mcap(bag)
    data = f.read_bytes()
    f.write_bytes(data[: rng.randrange(1, len(data))])
    return bag


# ------------------------------------------------------------------ metadata.yaml
def _meta(text: str | bytes | None) -> Callable[[Base, Path, random.Random], Path]:
    def build(base: Base, dst: Path, rng: random.Random) -> Path:
        bag = _copy(base, dst)
        meta = bag / "metadata.yaml"
        if text is None:
            meta.unlink()
        elif isinstance(text, bytes):
            meta.write_bytes(text)
        else:
            meta.write_text(text)
        return bag
    return build


def _edit_meta(edit: Callable[[str], str]) -> Callable[[Base, Path, random.Random], Path]:
    def build(base: Base, dst: Path, rng: random.Random) -> Path:
        bag = _copy(base, dst)
        meta = bag / "metadata.yaml"
        new = edit(meta.read_text())
        assert new != meta.read_text(), "metadata edit changed nothing"
        meta.write_text(new)
        return bag
    return build


def _binary_meta(base: Base, dst: Path, rng: random.Random) -> Path:
    return _meta(b"\xff\xfe\x00" + bytes(rng.randrange(256) for _ in range(200)))(base, dst, rng)


def alias_bomb(levels: int = 9) -> str:
    """A metadata.yaml of ~1 KB (9 levels) whose ``custom_data`` expands to ``9 ** levels``
    strings through nested aliases (a "billion laughs")."""
    lines = ['a0: &a0 ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]']
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]")
    body = "".join(f"  {ln}\n" for ln in lines)
    return (f"rosbag2_bagfile_information:\n{body}  version: 9\n  storage_identifier: mcap\n"
            f"  custom_data:\n    bomb: *a{levels - 1}\n")


def _bomb_in_custom(text: str) -> str:
    """The intact metadata with the alias bomb's anchors and a ``custom_data`` value using it."""
    bomb = alias_bomb().split("\n", 1)[1]
    anchors = "".join(ln + "\n" for ln in bomb.splitlines() if ln.startswith("  a"))
    return text.replace("  custom_data:\n", anchors + "  custom_data:\n    bomb: *a8\n", 1)


# ------------------------------------------------------------------ message level
Edit = Callable[[str, str, int, Any, int], list]


def rewrite(base: Base, dst: Path, edit: Edit, *, types: dict[str, str] | None = None,
            storage: str = "mcap", chunk_size: int = CHUNK) -> Path:
    """Re-write the base messages through ``edit(topic, msgtype, log_ns, msg, i)`` (``i``: the
    message's index on its topic, i.e. its frame) returning ``[(topic, log_ns, msg), ...]``."""
    bag = dst / "bag"
    declared = dict(base.types)
    declared.update(types or {})
    seen: dict[str, int] = {}
    with BagWriter(bag, storage=storage, chunk_size=chunk_size) as w:
        for key, value in base.custom_data.items():
            w.set_custom_data(key, value)
        for topic, msgtype in declared.items():
            w.add_topic(topic, msgtype, latched=topic in base.latched)
        for topic, msgtype, log_ns, msg in base.messages:
            i = seen.get(topic, 0)
            seen[topic] = i + 1
            for t, ns, m in edit(topic, msgtype, log_ns, msg, i):
                if t not in w.counts:
                    w.add_topic(t, declared.get(t, msgtype))
                w.write(t, m, ns)
    return bag


def _msg_variant(edit: Edit, types: dict[str, str] | None = None):
    def build(base: Base, dst: Path, rng: random.Random) -> Path:
        return rewrite(base, dst, edit, types=types)
    return build


def _with_stamp(msg: Any, sec: int, nanosec: int) -> Any:
    stamp = dataclasses.replace(msg.header.stamp, sec=sec, nanosec=nanosec)
    return dataclasses.replace(msg, header=dataclasses.replace(msg.header, stamp=stamp))


def _stamp_edit(topic: str, sec: Callable[[Any], int], nanosec: Callable[[Any], int]) -> Edit:
    def edit(t, ty, ns, msg, i):
        if t == topic and i >= FROM:
            s = msg.header.stamp
            msg = _with_stamp(msg, sec(s), nanosec(s))
        return [(t, ns, msg)]
    return edit


def _retype(topic: str, source_topic: str) -> Edit:
    """Messages of ``topic`` replaced by the same frame's message of ``source_topic``."""
    def edit(t, ty, ns, msg, i):
        if t == topic:
            return []
        if t == source_topic:
            return [(t, ns, msg), (topic, ns, msg)]
        return [(t, ns, msg)]
    return edit


def _grid_edit(topic: str, change: Callable[[Any], Any], from_frame: int = FROM) -> Edit:
    def edit(t, ty, ns, msg, i):
        if t == topic and i >= from_frame:
            msg = change(msg)
        return [(t, ns, msg)]
    return edit


def _huge_dims(msg):
    return dataclasses.replace(msg, info=dataclasses.replace(msg.info, width=60000, height=60000))


def _rotated(msg):
    q = dataclasses.replace(msg.info.origin.orientation, z=math.sin(0.3), w=math.cos(0.3))
    origin = dataclasses.replace(msg.info.origin, orientation=q)
    return dataclasses.replace(msg, info=dataclasses.replace(msg.info, origin=origin))


def _truncated(msg):
    return dataclasses.replace(msg, data=np.asarray(msg.data)[: len(msg.data) // 2].copy())


def _image_edit(topic: str, change: Callable[[Any], Any]) -> Edit:
    def edit(t, ty, ns, msg, i):
        if t == topic and i >= FROM:
            msg = change(msg)
        return [(t, ns, msg)]
    return edit


def _half_size(msg):
    h, w = int(msg.height) // 2, int(msg.width) // 2
    data = np.asarray(msg.data, np.uint8).reshape(int(msg.height), int(msg.step))
    small = data[:h * 2:2, :w * 2:2].copy() if msg.encoding == "mono8" else None
    assert small is not None
    return dataclasses.replace(msg, height=h, width=w, step=w, data=small.reshape(-1))


def _bad_encoding(msg):
    return dataclasses.replace(msg, encoding="no-such-encoding")


def _nan_quat(t, ty, ns, msg, i):
    if t == T.ODOM and i >= FROM:
        q = dataclasses.replace(msg.pose.pose.orientation, x=float("nan"))
        pose = dataclasses.replace(msg.pose.pose, orientation=q)
        msg = dataclasses.replace(msg, pose=dataclasses.replace(msg.pose, pose=pose))
    return [(t, ns, msg)]


def _extra_camera(t, ty, ns, msg, i):
    """A second camera 'side' with images but no CameraInfo topic."""
    out = [(t, ns, msg)]
    if t in (LABELS, RGB):
        out.append((t.replace(f"/{CAM}/", "/side/"), ns, msg))
    return out


def _no_camera_info(base: Base, dst: Path, rng: random.Random) -> Path:
    """The CameraInfo topic is declared but holds no message."""
    return rewrite(base, dst, lambda t, ty, ns, msg, i: [] if t == INFO else [(t, ns, msg)])


# ------------------------------------------------------------------ sqlite3
def _sqlite_copy(base: Base, dst: Path) -> tuple[Path, Path]:
    bag = dst / "bag"
    shutil.copytree(base.sqlite, bag)
    return bag, next(bag.glob("*.db3"))


def _dangling(topic: str, delete_row: bool):
    def build(base: Base, dst: Path, rng: random.Random) -> Path:
        bag, db = _sqlite_copy(base, dst)
        con = sqlite3.connect(db)
        try:
            (tid,) = con.execute("SELECT id FROM topics WHERE name = ?", (topic,)).fetchone()
            if delete_row:
                con.execute("DELETE FROM topics WHERE id = ?", (tid,))
            else:
                con.execute("UPDATE messages SET topic_id = 999 WHERE topic_id = ?", (tid,))
            con.commit()
        finally:
            con.close()
        return bag
    return build


def _sqlite_negative_log_time(base: Base, dst: Path, rng: random.Random) -> Path:
    """CameraInfo logged at negative times from frame FROM on."""
    bag, db = _sqlite_copy(base, dst)
    con = sqlite3.connect(db)
    try:
        (tid,) = con.execute("SELECT id FROM topics WHERE name = ?", (INFO,)).fetchone()
        ids = [r[0] for r in con.execute(
            "SELECT id FROM messages WHERE topic_id = ? ORDER BY timestamp", (tid,))]
        con.executemany("UPDATE messages SET timestamp = -timestamp WHERE id = ?",
                        [(i,) for i in ids[FROM:]])
        con.commit()
    finally:
        con.close()
    return bag


def _sqlite_truncate(base: Base, dst: Path, rng: random.Random) -> Path:
    bag, db = _sqlite_copy(base, dst)
    data = db.read_bytes()
    db.write_bytes(data[: rng.randrange(len(data) // 4, len(data) - 1)])
    return bag


# ------------------------------------------------------------------ the list
def variants(n_random: int = 4) -> list[Variant]:
    """Every damaged-bag variant; ``n_random`` seeded draws per random storage-level kind."""
    v: list[Variant] = []
    for k in range(n_random):
        v.append(Variant(f"flip_chunk_{k}", "storage", flip_in_chunk))
        v.append(Variant(f"flip_any_{k}", "storage", flip_anywhere))
        v.append(Variant(f"truncate_{k}", "storage", truncate))
    v += [
        Variant("meta_binary", "metadata", _binary_meta),
        Variant("meta_list", "metadata", _meta("- a\n- b\n")),
        Variant("meta_scalar", "metadata", _meta("just some text\n")),
        Variant("meta_empty", "metadata", _meta("")),
        Variant("meta_missing", "metadata", _meta(None)),
        Variant("meta_no_info_key", "metadata", _meta("something_else: {version: 9}\n")),
        Variant("meta_alias_bomb", "metadata", _meta(alias_bomb())),
        Variant("meta_alias_bomb_in_custom", "metadata", _edit_meta(_bomb_in_custom)),
        Variant("meta_version_str", "metadata", _edit_meta(
            lambda s: s.replace("  version: 9", "  version: nine", 1))),
        Variant("meta_topics_scalar", "metadata", _edit_meta(
            lambda s: s.split("  topics_with_message_count:")[0]
            + "  topics_with_message_count: 5\n  compression_format: ''\n")),
        Variant("meta_topic_name_int", "metadata", _edit_meta(
            lambda s: s.replace(f"name: {LABELS}", "name: 12", 1))),
        Variant("meta_custom_int", "metadata", _edit_meta(
            lambda s: s.replace("  custom_data:\n", "  custom_data:\n    number: 12\n", 1))),
        Variant("meta_custom_list", "metadata", _edit_meta(
            lambda s: s.replace("  custom_data:\n", "  custom_data:\n    items: [1, 2]\n", 1))),
        Variant("meta_oversized", "metadata", _edit_meta(
            lambda s: s + "#" + "x" * (5 << 20) + "\n")),
        Variant("wrong_type_odom", "message", _msg_variant(
            _retype(T.ODOM, LABELS), {T.ODOM: T.IMAGE_TYPE})),
        Variant("wrong_type_labels", "message", _msg_variant(
            _retype(LABELS, T.ODOM), {LABELS: T.ODOM_TYPE})),
        Variant("wrong_type_camera_info", "message", _msg_variant(
            _retype(INFO, RGB), {INFO: T.IMAGE_TYPE})),
        Variant("wrong_type_gt", "message", _msg_variant(
            _retype(GT0, T.ODOM), {GT0: T.ODOM_TYPE})),
        Variant("wrong_type_tf_static", "message", _msg_variant(
            _retype(T.TF_STATIC, INFO), {T.TF_STATIC: T.CAMERA_INFO_TYPE})),
        Variant("negative_stamp_labels", "message", _msg_variant(
            _stamp_edit(LABELS, lambda s: -int(s.sec), lambda s: int(s.nanosec))), FROM),
        Variant("negative_stamp_odom", "message", _msg_variant(
            _stamp_edit(T.ODOM, lambda s: -5, lambda s: 0)), FROM),
        Variant("nanosec_overflow_labels", "message", _msg_variant(
            _stamp_edit(LABELS, lambda s: int(s.sec), lambda s: 1_500_000_000)), FROM),
        Variant("huge_stamp_gt", "message", _msg_variant(
            _stamp_edit(GT0, lambda s: 2**31 - 1, lambda s: 999_999_999)), FROM),
        Variant("gt_huge_dims", "message", _msg_variant(_grid_edit(GT0, _huge_dims, 0))),
        Variant("gt_huge_dims_mid", "message", _msg_variant(_grid_edit(GT0, _huge_dims)), FROM),
        Variant("gt_rotated_mid", "message", _msg_variant(_grid_edit(GT0, _rotated)), FROM),
        Variant("gt_truncated_mid", "message", _msg_variant(_grid_edit(GT0, _truncated)), FROM),
        Variant("label_wrong_size_mid", "message", _msg_variant(
            _image_edit(LABELS, _half_size)), FROM),
        Variant("label_bad_encoding_mid", "message", _msg_variant(
            _image_edit(LABELS, _bad_encoding)), FROM),
        Variant("odom_nan_quaternion_mid", "message", _msg_variant(_nan_quat), FROM),
        Variant("camera_without_camera_info", "message", _msg_variant(_extra_camera)),
        Variant("camera_info_no_messages", "message", _no_camera_info),
        Variant("sqlite_dangling_gt_ids", "sqlite", _dangling(GT0, False)),
        Variant("sqlite_dangling_labels_row", "sqlite", _dangling(LABELS, True)),
        Variant("sqlite_negative_log_time", "sqlite", _sqlite_negative_log_time),
        Variant("sqlite_truncated", "sqlite", _sqlite_truncate),
    ]
    return v
