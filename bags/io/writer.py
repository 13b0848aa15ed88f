"""Writing rosbag2 directories (mcap or sqlite3 storage) with ``rosbags.rosbag2.Writer``.

:class:`BagWriter` writes into a hidden temporary directory next to the target and renames it
into place only when the bag is complete, so a crash never leaves a half-written bag under the
requested name. MCAP bags carry chunk, data section and summary CRCs
(:class:`bags.io.mcap_storage.CrcMcapStorage`), so that damage is detected when they are read.
:func:`write_drive` maps synthetic drive frames to the topic layout of
:mod:`bags.io.topics`.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.labels.classes import BEV_CLASSES, BevClass
from msg_adapters import (
    RosbagsFactory,
    StampedTransform,
    make_camera_info,
    make_compressed_image,
    make_image,
    make_occupancy_grid,
    make_odometry,
    make_tf_message,
)

from ..errors import BagError, BagExistsError
from ..files import partial_name, remove_path
from . import topics as T
from .mcap_storage import CHUNK_SIZE, rosbag2_writer

log = logging.getLogger(__name__)

STORAGES = ("mcap", "sqlite3")


def _latched_qos() -> list:
    """Offered QoS of a latched topic: reliable, transient local, keep last 1."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)  # 0 = RMW default (infinite) deadline / lifespan / lease
    return [
        Qos(QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL,
            zero, zero, QosLiveliness.AUTOMATIC, zero, False)
    ]


def _looks_like_bag(path: Path) -> bool:
    if path.is_dir():
        return (path / "metadata.yaml").exists() or not any(path.iterdir())
    return path.suffix in (".mcap", ".db3")


def check_output(path: Path, force: bool) -> None:
    """Refuse to overwrite ``path`` unless ``force``; never overwrite something not a bag.

    Raises:
        BagExistsError: ``path`` exists and ``force`` is false, or it is not a bag.
    """
    if not path.exists() and not path.is_symlink():
        return
    if not force:
        raise BagExistsError(f"{path} exists; pass --force to overwrite it")
    if path.is_symlink() or not _looks_like_bag(path):
        raise BagExistsError(
            f"refusing to overwrite {path}: it does not look like a bag "
            "(a rosbag2 directory with metadata.yaml, an empty directory, .mcap or .db3)"
        )


class BagWriter:
    """Context manager writing one rosbag2 directory atomically.

    Args:
        path: target directory.
        storage: ``'mcap'`` or ``'sqlite3'``.
        force: replace an existing bag at ``path`` (only once the new one is complete).
        typestore: rosbags typestore (default ``Stores.ROS2_JAZZY``).
        chunk_size: MCAP chunk size in bytes (uncompressed).
    """

    def __init__(self, path: str | Path, *, storage: str = "mcap", force: bool = False,
                 typestore: Any = None, chunk_size: int = CHUNK_SIZE) -> None:
        from rosbags.typesys import Stores, get_typestore

        if storage not in STORAGES:
            raise BagError(f"unknown storage {storage!r}; expected one of {list(STORAGES)}")
        self.path = Path(path)
        self.storage = storage
        self.force = force
        self.typestore = typestore or get_typestore(Stores.ROS2_JAZZY)
        self.factory = RosbagsFactory(self.typestore)
        self.chunk_size = int(chunk_size)
        # <parent>/.<name>.partial-<pid>/<name>: the storage file is named after the bag
        self._tmp_root = partial_name(self.path)
        self._tmp = self._tmp_root / self.path.name
        self._writer: Any = None
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> "BagWriter":
        from rosbags.rosbag2 import WriterError

        check_output(self.path, self.force)
        remove_path(self._tmp_root)  # leftover of a crashed run with this same process id
        try:
            self._tmp_root.mkdir(parents=True)
            self._writer = rosbag2_writer(self._tmp, self.storage, self.chunk_size)
            self._writer.open()
        except BaseException as exc:  # Ctrl-C / SIGTERM here too: __exit__ will not run
            remove_path(self._tmp_root)
            if isinstance(exc, (WriterError, OSError)):
                raise BagError(f"cannot create bag {self.path}: {exc}") from None
            raise
        return self

    def add_topic(self, topic: str, msgtype: str, *, latched: bool = False) -> None:
        """Declare a topic; ``latched`` topics get the transient-local offered QoS."""
        if topic in self._conns:
            return
        self._conns[topic] = self._writer.add_connection(
            topic, msgtype, typestore=self.typestore,
            offered_qos_profiles=_latched_qos() if latched else (),
        )
        self.counts[topic] = 0

    def set_custom_data(self, key: str, value: str) -> None:
        """Store a string in ``metadata.yaml``'s ``custom_data``."""
        self._writer.set_custom_data(key, value)

    def write(self, topic: str, msg: Any, log_ns: int) -> None:
        """Serialize ``msg`` (a rosbags message of the topic's type) and write it."""
        conn = self._conns[topic]
        data = self.typestore.serialize_cdr(msg, conn.msgtype)
        self._writer.write(conn, int(log_ns), data)
        self.counts[topic] += 1

    def write_raw(self, topic: str, data: bytes, log_ns: int) -> None:
        """Write one message of the topic's type already serialized (CDR bytes)."""
        self._writer.write(self._conns[topic], int(log_ns), data)
        self.counts[topic] += 1

    def serialize(self, topic: str, msg: Any) -> bytes:
        """The CDR bytes :meth:`write` would write for ``msg`` on ``topic``."""
        return bytes(self.typestore.serialize_cdr(msg, self._conns[topic].msgtype))

    def __exit__(self, exc_type, exc, tb) -> None:
        writer, self._writer = self._writer, None
        if exc_type is not None:
            try:
                if writer is not None:
                    writer.abort()
            finally:
                remove_path(self._tmp_root)
            return
        try:
            writer.close()
            if self.path.exists() or self.path.is_symlink():
                check_output(self.path, self.force)  # re-check: it may have appeared meanwhile
                remove_path(self.path)
            os.replace(self._tmp, self.path)
        finally:
            remove_path(self._tmp_root)


@dataclass(frozen=True)
class DriveSummary:
    """What :func:`write_drive` wrote."""

    path: Path
    frames: int
    counts: dict[str, int]
    first_stamp_ns: int
    last_stamp_ns: int


#: ``write_drive(compressed=True)``: the codec of each image kind (label images lossless: JPEG
#: changes label ids) and the JPEG quality of the RGB images.
COMPRESSED_FORMATS = {"rgb": "jpeg", "labels": "png"}
JPEG_QUALITY = 90


def camera_image_topic(camera: str, kind: str, compressed: bool) -> str:
    """The topic :func:`write_drive` writes a camera's images of ``kind`` on: the image topic, or
    its ``/compressed`` transport.
    """
    topic = T.image_topic(camera, kind)
    return T.compressed_topic(topic) if compressed else topic


def _image_message(factory, array, kind: str, compressed: bool, stamp_ns: int, frame_id: str):
    """An Image (rgb8 / mono8) or a CompressedImage (:data:`COMPRESSED_FORMATS`) of ``array``."""
    if compressed:
        return make_compressed_image(factory, array, COMPRESSED_FORMATS[kind], stamp_ns, frame_id,
                                     quality=JPEG_QUALITY)
    return make_image(factory, array, "rgb8" if kind == "rgb" else "mono8", stamp_ns, frame_id)


def _frame_messages(f, rig: Rig, grid: BevGrid, classes, factory, ego_frame, odom_frame,
                    truth: bool = True, compressed: bool = False):
    """(log_ns, topic, msg) of one synthetic frame; ``truth``: also the full-truth layers;
    ``compressed``: the images as CompressedImage on ``<image topic>/compressed``.
    """
    out = []
    for cam in rig.cameras:
        cf = f.cameras.get(cam.name)
        if cf is None:  # camera dropped out in this frame
            continue
        s = int(cf.stamp_ns)
        for kind, array in (("rgb", cf.rgb), ("labels", cf.labels)):
            out.append((s, camera_image_topic(cam.name, kind, compressed),
                        _image_message(factory, array, kind, compressed, s, cam.frame_id)))
        out.append((s, T.camera_info_topic(cam.name),
                    make_camera_info(factory, cam.model, s, cam.frame_id)))
    s = int(f.stamp_ns)
    out.append((s, T.ODOM, make_odometry(factory, f.world_from_ego, f.linear_velocity,
                                         f.angular_velocity, s, odom_frame, ego_frame)))
    out.append((s, T.TF, make_tf_message(factory, [StampedTransform(odom_frame, ego_frame, f.world_from_ego, s)])))
    visible = np.asarray(f.visibility, dtype=bool)
    for ci, c in enumerate(classes):
        layer = np.asarray(f.gt[ci], dtype=np.float32)
        out.append((s, T.gt_topic(c.name),
                    make_occupancy_grid(factory, grid, layer, visible, s, ego_frame)))
    ground = getattr(f, "ground_visibility", None)
    if ground is not None:
        layer = np.asarray(ground, dtype=np.float32)
        out.append((s, T.GROUND_VISIBILITY,
                    make_occupancy_grid(factory, grid, layer, None, s, ego_frame)))
    if truth:
        out.append((s, T.ANY_VISIBILITY,
                    make_occupancy_grid(factory, grid, visible.astype(np.float32), None, s, ego_frame)))
        for ci, c in enumerate(classes):
            layer = np.asarray(f.gt[ci], dtype=np.float32)
            out.append((s, T.truth_topic(c.name),
                        make_occupancy_grid(factory, grid, layer, None, s, ego_frame)))
    out.sort(key=lambda x: x[0])  # stable: per-frame log time order
    return out


def write_drive(
    path: str | Path,
    rig: Rig,
    grid: BevGrid,
    frames: Iterable[Any],
    *,
    storage: str = "mcap",
    force: bool = False,
    classes: tuple[BevClass, ...] = BEV_CLASSES,
    ego_frame: str = "base_link",
    odom_frame: str = "odom",
    custom_data: dict[str, str] | None = None,
    truth: bool = True,
    compressed: bool = False,
) -> DriveSummary:
    """Write synthetic drive frames (``SynthFrame``-like objects) as a rosbag2 directory.

    Topics: ``/cameras/<cam>/{image_raw,labels,camera_info}`` at each camera's stamp,
    ``/tf_static`` once (latched) with ``ego_frame -> <camera optical frame>``, ``/odom`` and
    ``/tf`` (both ``odom_frame -> ego_frame``, the same pose) and ``/bev/gt/<class>`` (100 present, 0 absent, -1 not
    visible) at the frame stamp, plus ``/bev/visibility/ground`` (100 where the cell's ground
    point is seen) for frames that carry ``ground_visibility``. With ``truth`` (default) also the
    full truth, whose ``gt`` holds what is in every cell whether seen or not:
    ``/bev/truth/<class>`` (100 present, 0 absent, no -1) and ``/bev/visibility/any`` (100 where
    the cell is seen, i.e. where ``/bev/gt/<class>`` is not -1). Log times equal the header
    stamps. ``compressed``: the images as ``sensor_msgs/CompressedImage`` on image_transport's
    ``<image topic>/compressed`` instead (RGB as JPEG, label images as PNG:
    :data:`COMPRESSED_FORMATS`).

    Raises:
        BagExistsError: ``path`` exists and ``force`` is false.
        BagError: writing failed (nothing is left at ``path`` then).
    """
    n, first, last = 0, None, None
    with BagWriter(path, storage=storage, force=force) as bw:
        fac = bw.factory
        bw.add_topic(T.TF_STATIC, T.TF_TYPE, latched=True)
        for cam in rig.cameras:
            for kind in ("rgb", "labels"):
                bw.add_topic(camera_image_topic(cam.name, kind, compressed),
                             T.COMPRESSED_IMAGE_TYPE if compressed else T.IMAGE_TYPE)
            bw.add_topic(T.camera_info_topic(cam.name), T.CAMERA_INFO_TYPE)
        bw.add_topic(T.ODOM, T.ODOM_TYPE)
        bw.add_topic(T.TF, T.TF_TYPE)
        for c in classes:
            bw.add_topic(T.gt_topic(c.name), T.GRID_TYPE)
        if truth:
            bw.add_topic(T.ANY_VISIBILITY, T.GRID_TYPE)
            for c in classes:
                bw.add_topic(T.truth_topic(c.name), T.GRID_TYPE)
        for key, value in (custom_data or {}).items():
            bw.set_custom_data(key, value)
        for f in frames:
            try:
                msgs = _frame_messages(f, rig, grid, classes, fac, ego_frame, odom_frame, truth, compressed)
            except BevMapperError as exc:
                raise BagError(f"frame {n}: {exc}") from None
            if first is None:
                first = msgs[0][0]
                tfs = [StampedTransform(ego_frame, c.frame_id, c.ego_from_cam_array, first)
                       for c in rig.cameras]
                bw.write(T.TF_STATIC, make_tf_message(fac, tfs), first)
            for log_ns, topic, msg in msgs:
                if topic == T.GROUND_VISIBILITY:
                    bw.add_topic(topic, T.GRID_TYPE)  # only when the frames carry it
                bw.write(topic, msg, log_ns)
            last = msgs[-1][0]
            n += 1
            log.debug("wrote frame %d", n)
        if n == 0:
            raise BagError("no frames to write")
        counts = dict(bw.counts)
    return DriveSummary(Path(path), n, counts, int(first), int(last))
