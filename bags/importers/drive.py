"""Writing one imported drive (a scene, a log) as a rosbag2 bag, through :class:`bags.io.writer.BagWriter`
(written under a temporary name, renamed when complete; a killed import's temporary is removed
by the next).

Topics (the layout of :mod:`bags.io.topics`, the images compressed):

* ``/cameras/<cam>/image_raw/compressed``: ``sensor_msgs/CompressedImage``, the dataset's JPEG
  bytes as they are (checked, never re-encoded), at the image's own stamp;
* ``/cameras/<cam>/camera_info`` beside each image; ``/tf_static`` once (``base_link`` -> each
  camera's optical frame, latched);
* ``/odom`` and ``/tf`` (``odom`` -> ``base_link``) at every ego pose, velocities by central
  differences of the poses;
* ``/bev/gt/<class>`` at each key frame, only for the classes the dataset has a source for
  (100 present, 0 absent, -1 not scored, e.g. under a box the visibility filter left out).

A missing, truncated or undecodable image is skipped and counted (:class:`ImportCounts`); the
drive's messages are written in stamp order.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import BevGrid
from msg_adapters import (
    EncodingError,
    StampedTransform,
    compressed_image_header,
    make_camera_info,
    make_occupancy_grid,
    make_odometry,
    make_tf_message,
)
from msg_adapters.factory import make_header

from ..files import remove_dead_partials
from ..io import topics as T
from ..io.writer import BagWriter
from .errors import DatasetError

COMPRESSED_TYPE = "sensor_msgs/msg/CompressedImage"
EGO_FRAME, ODOM_FRAME = "base_link", "odom"


def compressed_topic(camera: str) -> str:
    """``/cameras/<camera>/image_raw/compressed``: the image topic with image_transport's suffix."""
    return f"{T.image_topic(camera, 'rgb')}/compressed"


@dataclass(frozen=True)
class ImportedCamera:
    """One camera of an imported drive: its name in topics, optical frame, intrinsics, mount."""

    name: str
    frame_id: str
    model: CameraModel
    ego_from_cam: np.ndarray  # (4, 4)


@dataclass(frozen=True)
class ImageRef:
    """One image file of the drive, to be copied into the bag at ``stamp_ns``."""

    stamp_ns: int
    camera: str
    path: Path


#: A key frame's layers: class name -> ``(present (H, W) bool, known (H, W) bool or None = all known)``.
Layers = dict[str, tuple[np.ndarray, np.ndarray | None]]


@dataclass(frozen=True)
class KeyFrame:
    """A frame with ground truth: its stamp and a function computing its layers (called once,
    when the frame is written, so that a drive's layers are never all in memory).
    """

    stamp_ns: int
    layers: Callable[[], Layers]


@dataclass(frozen=True)
class ImportedDrive:
    """Everything one bag of an imported drive holds (see the module docstring)."""

    name: str
    cameras: tuple[ImportedCamera, ...]
    images: Sequence[ImageRef]
    poses: Sequence[tuple[int, np.ndarray]]  # (stamp ns, world_from_ego (4, 4)), any order
    keyframes: Sequence[KeyFrame]
    classes: tuple[str, ...]  # the GT classes written (those with a source)
    grid: BevGrid
    custom_data: dict[str, str] = field(default_factory=dict)


@dataclass
class ImportCounts:
    """What was written and what was skipped (and why) for one drive."""

    images: int = 0
    key_frames: int = 0
    poses: int = 0
    missing_images: int = 0
    corrupt_images: int = 0
    skipped: list[str] = field(default_factory=list)  # the first few skipped files, with the reason

    def skip(self, kind: str, what: str) -> None:
        """Count one skipped image (``kind`` ``missing`` or ``corrupt``)."""
        setattr(self, f"{kind}_images", getattr(self, f"{kind}_images") + 1)
        if len(self.skipped) < 5:
            self.skipped.append(what)


def check_jpeg(data: bytes, width: int, height: int) -> str | None:
    """Why ``data`` is not a JPEG of ``width`` x ``height`` that decodes, or ``None``: its header
    (and end marker) is read, then it is decoded at an eighth of its size (cheap, and it finds
    damaged entropy-coded data that the header alone does not).
    """
    try:
        header = compressed_image_header(data)
    except EncodingError as exc:
        return str(exc)
    if header.format != "jpeg":
        return f"a {header.format.upper()} image, not a JPEG"
    if (header.width, header.height) != (width, height):
        return f"{header.width}x{header.height}, the table says {width}x{height}"
    buf = np.frombuffer(data, np.uint8)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_REDUCED_GRAYSCALE_8)
    except cv2.error as exc:
        return f"undecodable: {str(exc).strip().splitlines()[-1]}"
    return "undecodable" if img is None else None


def _odometry(poses: Sequence[tuple[int, np.ndarray]]) -> list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]:
    """``(stamp, world_from_ego, v (3,) in the ego frame, w (3,))`` per pose, stamps unique and
    increasing, velocities by central differences (forward / backward at the ends).
    """
    by_stamp: dict[int, np.ndarray] = {}
    for s, T_ in poses:
        by_stamp.setdefault(int(s), np.asarray(T_, dtype=np.float64))
    stamps = sorted(by_stamp)
    out = []
    for i, s in enumerate(stamps):
        a, b = stamps[max(i - 1, 0)], stamps[min(i + 1, len(stamps) - 1)]
        Ta, Tb, T_ = by_stamp[a], by_stamp[b], by_stamp[s]
        v, w = np.zeros(3), np.zeros(3)
        if b > a:
            dt = (b - a) * 1e-9
            v = T_[:3, :3].T @ ((Tb[:3, 3] - Ta[:3, 3]) / dt)
            dR = Ta[:3, :3].T @ Tb[:3, :3]  # rotation from a to b in a's frame
            w[2] = np.arctan2(dR[1, 0], dR[0, 0]) / dt
        out.append((s, T_, v, w))
    return out


def _compressed(factory, data: bytes, stamp_ns: int, frame_id: str):
    return factory.msg(COMPRESSED_TYPE, header=make_header(factory, stamp_ns, frame_id), format="jpeg",
                       data=np.frombuffer(data, np.uint8))


def write_imported_drive(path: str | Path, drive: ImportedDrive, *, force: bool = False) -> ImportCounts:
    """Write ``drive`` as a rosbag2 (MCAP) directory at ``path`` (see the module docstring).

    Raises:
        BagExistsError: ``path`` exists and ``force`` is false.
        DatasetError: nothing to write (no image could be read).
        BagError: writing failed (nothing is left at ``path`` then).
    """
    counts = ImportCounts()
    cams = {c.name: c for c in drive.cameras}
    odom = _odometry(drive.poses)
    # (stamp, order, index): poses first at equal stamps, then images, then the key frame's layers
    events: Iterable = heapq.merge(
        ((s, 0, i) for i, (s, *_rest) in enumerate(odom)),
        sorted((int(im.stamp_ns), 1, i) for i, im in enumerate(drive.images)),
        sorted((int(k.stamp_ns), 2, i) for i, k in enumerate(drive.keyframes)),
    )
    remove_dead_partials(path)  # what a killed import of this drive left (it could not clean up)
    with BagWriter(path, storage="mcap", force=force) as bw:
        fac = bw.factory
        bw.add_topic(T.TF_STATIC, T.TF_TYPE, latched=True)
        for cam in drive.cameras:
            bw.add_topic(compressed_topic(cam.name), COMPRESSED_TYPE)
            bw.add_topic(T.camera_info_topic(cam.name), T.CAMERA_INFO_TYPE)
        bw.add_topic(T.ODOM, T.ODOM_TYPE)
        bw.add_topic(T.TF, T.TF_TYPE)
        for c in drive.classes:
            bw.add_topic(T.gt_topic(c), T.GRID_TYPE)
        for key, value in drive.custom_data.items():
            bw.set_custom_data(key, value)
        static_written = False
        for stamp, kind, i in events:
            if not static_written:
                tfs = [StampedTransform(EGO_FRAME, c.frame_id, np.asarray(c.ego_from_cam), stamp) for c in drive.cameras]
                bw.write(T.TF_STATIC, make_tf_message(fac, tfs), stamp)
                static_written = True
            if kind == 0:
                _, T_, v, w = odom[i]
                bw.write(T.ODOM, make_odometry(fac, T_, v, w, stamp, ODOM_FRAME, EGO_FRAME), stamp)
                bw.write(T.TF, make_tf_message(fac, [StampedTransform(ODOM_FRAME, EGO_FRAME, T_, stamp)]), stamp)
                counts.poses += 1
            elif kind == 1:
                im = drive.images[i]
                cam = cams[im.camera]
                try:
                    data = im.path.read_bytes()
                except OSError as exc:
                    counts.skip("missing", f"{im.path}: {exc.strerror or exc}")
                    continue
                problem = check_jpeg(data, cam.model.width, cam.model.height)
                if problem is not None:
                    counts.skip("corrupt", f"{im.path}: {problem}")
                    continue
                bw.write(compressed_topic(cam.name), _compressed(fac, data, stamp, cam.frame_id), stamp)
                bw.write(T.camera_info_topic(cam.name), make_camera_info(fac, cam.model, stamp, cam.frame_id), stamp)
                counts.images += 1
            else:
                layers = drive.keyframes[i].layers()
                for c in drive.classes:
                    present, known = layers[c]
                    bw.write(T.gt_topic(c), make_occupancy_grid(
                        fac, drive.grid, np.asarray(present, np.float32), known, stamp, EGO_FRAME), stamp)
                counts.key_frames += 1
        if counts.images == 0:
            raise DatasetError(f"{drive.name}: no image could be read ({counts.missing_images} missing, "
                               f"{counts.corrupt_images} corrupt; e.g. {'; '.join(counts.skipped[:2])})")
    return counts


__all__ = ["COMPRESSED_TYPE", "ImageRef", "ImportCounts", "ImportedCamera", "ImportedDrive", "KeyFrame",
           "check_jpeg", "compressed_topic", "write_imported_drive"]
