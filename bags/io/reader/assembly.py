"""Assembling a bag's synchronized frames (:meth:`BagReader.frames
<bags.io.reader.BagReader.frames>`): the messages of the image, GT, odometry and ``/tf`` topics in
log-time order, the images grouped into sets by :class:`msg_adapters.FrameSynchronizer`, and each
set built into a :class:`~bags.io.reader.frame.BagFrame` with the GT layers and odometry nearest
its stamp. Damaged messages are skipped and counted in the reader's ``issues``.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

import numpy as np

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.pose_buffer import PoseBuffer
from bev_mapper_core.labels.label_maps import LabelMap
from msg_adapters import (
    AdapterError,
    FrameSynchronizer,
    OdometryState,
    SyncConfig,
    SyncedSet,
    compressed_to_labels,
    compressed_to_rgb,
    header_stamp_ns,
    image_to_labels,
    image_to_rgb,
    odometry_to_state,
    tf_message_transforms,
)

from ...errors import BagContentError, BagCorruptError
from .. import topics as T
from ..input_checks import DECODE_ERRORS, StampDrift
from ..raw.cdr import Undecodable
from ..sync_report import SyncReport
from .frame import BagFrame
from .layers import LayerDecoder

if TYPE_CHECKING:
    from .bag_reader import BagReader

log = logging.getLogger("bags.io.reader")


def _newest(s: SyncedSet) -> int:
    """Newest stamp of a synchronized set."""
    return max(t for t in s.stamps.values() if t is not None)


def _nearest(buf: deque, stamp: int, tol: int):
    """Entry ``(stamp, msg)`` of ``buf`` closest to ``stamp`` within ``tol``, else ``None``."""
    best = None
    for s, m in buf:
        if abs(s - stamp) <= tol and (best is None or abs(s - stamp) < abs(best[0] - stamp)):
            best = (s, m)
    return best


def decode_image(msg: Any, kind: str, compressed: bool, size: tuple[int, int] | None,
                 label_map: LabelMap | None) -> np.ndarray:
    """One camera image of ``kind`` (``rgb``: ``(H, W, 3)`` uint8 RGB; ``labels``: ``(H, W)``
    uint8 Label ids), from a ``sensor_msgs/Image`` or, ``compressed``, a ``CompressedImage``
    (the adapters' decoders, the node's: its ``format`` must name the data's codec, its header's
    size must be ``size`` before anything is decoded, and label images must be PNG: JPEG changes
    label ids). ``size``: the camera's calibrated ``(width, height)`` (``None``: not checked).

    Raises:
        AdapterError (and what :data:`DECODE_ERRORS` lists): the image cannot be used.
    """
    if compressed:
        if kind == "rgb":
            arr = compressed_to_rgb(msg, size, check_format=True)
        else:  # refuses JPEG: it changes label ids
            arr = compressed_to_labels(msg, size, label_map=label_map, check_format=True)
    else:
        arr = image_to_rgb(msg) if kind == "rgb" else image_to_labels(msg, label_map=label_map)
    h, w = arr.shape[:2]
    if size is not None and (w, h) != size:
        raise AdapterError(f"image is {w}x{h}, the camera is calibrated for {size[0]}x{size[1]}")
    return arr


def read_frames(reader: BagReader, *, rgb: bool, labels: bool, gt: bool, odom: bool, sync: SyncConfig,
                lookahead_ns: int, label_map: LabelMap | None, gt_half: bool = False) -> Iterator[BagFrame]:
    """The frames of :meth:`BagReader.frames <bags.io.reader.BagReader.frames>` (see there)."""
    topics_in = reader.topics
    asm = FrameAssembler(reader)
    cams = reader.camera_names
    kinds = [k for k, on in (("rgb", rgb), ("labels", labels)) if on]
    stream_of = {
        reader.image_topic(c, k): f"{c}/{k}" for c in cams for k in kinds
        if reader.image_topic(c, k) in topics_in
    }
    if not stream_of:
        raise BagContentError(f"{reader.path}: no image topics for {kinds} of cameras {cams}")
    classes = reader.gt_classes if gt else ()
    grid = reader.grid() if classes else None
    gt_topics = {T.gt_topic(c): c for c in classes}
    for extra in (T.GROUND_VISIBILITY, T.ANY_VISIBILITY):
        if classes and extra in topics_in:
            gt_topics[extra] = extra
    if classes and set(classes) <= set(reader.truth_classes):  # all or nothing
        gt_topics.update({T.truth_topic(c): T.truth_topic(c) for c in classes})
    want_odom = odom and T.ODOM in topics_in
    want_tf = odom and not want_odom and T.TF in topics_in  # ego poses from /tf without /odom
    topics = set(stream_of) | set(gt_topics) | ({T.ODOM} if want_odom else set()) | ({T.TF} if want_tf else set())
    reader._check_types(topics)

    streams = [f"{c}/{k}" for c in cams for k in kinds]
    sync_ = FrameSynchronizer(streams, sync)
    reader.sync_report = SyncReport(cameras=cams, window_ms=sync.slop_ns / 1e6, cameras_without_images=tuple(
        c for c in cams if not all(reader.image_topic(c, k) in topics_in for k in kinds)))
    gt_buf = {c: deque() for c in gt_topics.values()}
    odom_buf: deque = deque()
    poses = PoseBuffer() if want_odom or want_tf else None  # every pose read, for the frames' stamps
    ready: deque[SyncedSet] = deque()
    compressed = {stream: reader.is_compressed(topic) for topic, stream in stream_of.items()}
    ctx = dict(cams=cams, kinds=kinds, classes=classes, grid=grid, gt_buf=gt_buf, layers=grid and LayerDecoder(grid),
               compressed=compressed,
               odom_buf=odom_buf, tol=sync.slop_ns, sizes=reader._camera_sizes(), label_map=label_map, sync=sync_,
               gt_half=gt_half, poses=poses)
    drift = StampDrift()
    index = 0
    try:
        for m in reader.messages(topics, fast=True):
            if m.topic == T.TF:
                found = asm.tf_poses(m.msg)
                odom_buf.extend(found)
                for stamp, state in found:
                    _keep_pose(poses, stamp, state)
                continue
            if isinstance(m.msg, Undecodable):  # e.g. a truncated image message: that image is lost
                reader.issues.decode_error(m.topic, m.msg.reason)
                continue
            try:  # stamp_problem's rule, the stamp read once
                stamp, bad = header_stamp_ns(m.msg), None
            except AdapterError as exc:
                stamp, bad = 0, str(exc)
            bad = bad or drift.problem(m.topic, stamp, m.log_ns)
            if bad is not None:
                reader.issues.bad_stamp(m.topic, bad)
                continue
            if m.topic in stream_of:
                ready.extend(sync_.add(stream_of[m.topic], stamp, m.msg))
            elif m.topic in gt_topics:
                gt_buf[gt_topics[m.topic]].append((stamp, m.msg))
            else:
                odom_buf.append((stamp, m.msg))
                _keep_pose(poses, stamp, m.msg)
            while ready and _newest(ready[0]) + lookahead_ns < m.log_ns:
                yield asm.build(ready.popleft(), index, ctx)
                index += 1
    except BagCorruptError as exc:
        while ready:  # sets completed before the damage
            yield asm.build(ready.popleft(), index, ctx)
            index += 1
        raise BagCorruptError(f"{exc}; {index} frame(s) were read before the damage") from None
    ready.extend(sync_.flush())
    while ready:
        yield asm.build(ready.popleft(), index, ctx)
        index += 1


def _keep_pose(poses: PoseBuffer | None, stamp: int, msg: Any) -> None:
    """Keep an odometry message's (or an :class:`OdometryState`'s) pose in ``poses``; one that
    does not decode is left out here (the frame it is nearest counts it).
    """
    if poses is None:
        return
    try:
        state = msg if isinstance(msg, OdometryState) else odometry_to_state(msg)
        poses.add(stamp, state.world_from_ego)
    except (*DECODE_ERRORS, BevMapperError):
        pass


def _stamp_poses(poses: PoseBuffer | None, stamps) -> dict[int, np.ndarray | None] | None:
    """``world_from_ego`` at each of ``stamps`` (interpolated, None where there is none), or None
    without odometry.
    """
    if poses is None:
        return None
    return {t: poses.at(t) for t in {int(t) for t in stamps if t is not None}}  # each stamp once


class FrameAssembler:
    """Builds the frames of one pass over a bag; what fails to decode is counted in the reader's
    ``issues``, camera dropouts in its ``sync_report``.
    """

    def __init__(self, reader: BagReader) -> None:
        self.reader = reader

    def tf_poses(self, msg: Any) -> list[tuple[int, OdometryState]]:
        """``(stamp, pose)`` of each ``<fixed frame> -> ego_frame`` transform of a ``/tf`` message,
        the ego pose as the node's ``pose_source: tf`` reads it (no velocities); a message that
        does not decode is counted in :attr:`issues` and skipped.
        """
        try:
            found = [t for t in tf_message_transforms(msg) if t.child == self.reader.ego_frame]
        except DECODE_ERRORS as exc:
            self.reader.issues.decode_error(T.TF, str(exc))
            return []
        zero = np.zeros(3)
        return [(t.stamp_ns, OdometryState(t.stamp_ns, t.parent, t.child, t.matrix, zero, zero)) for t in found]

    def build(self, s: SyncedSet, index: int, ctx: dict) -> BagFrame:
        """The frame of the synchronized set ``s``: its images, GT layers and odometry."""
        images, valid, cam_stamps = self.images(s, index, ctx)
        self.reader.sync_report.add(valid, ctx["sync"])
        mean = s.mean_stamp_ns
        stamp, gt, known = self.gt(mean, index, ctx)
        ground = self.layer(T.GROUND_VISIBILITY, mean, index, ctx)
        visibility = self.layer(T.ANY_VISIBILITY, mean, index, ctx)
        truth = None
        if gt is not None:
            truth = np.empty(gt.shape, gt.dtype)  # (C, H, W) 0/1 (bool with gt_half): the layers >= 0.5
            found = [self.layer(T.truth_topic(c), mean, index, ctx, out=truth[ci])
                     for ci, c in enumerate(ctx["classes"])]
            if any(layer is None for layer in found):
                truth = None
        odom_state = None
        hit = _nearest(ctx["odom_buf"], mean, ctx["tol"])
        if hit is not None:
            try:
                odom_state = hit[1] if isinstance(hit[1], OdometryState) else odometry_to_state(hit[1])
                stamp = hit[0] if stamp is None else stamp
            except DECODE_ERRORS as exc:
                self.reader.issues.decode_error(T.ODOM, f"frame {index}: {exc}")
        ref_stamp = int(mean if stamp is None else stamp)
        stamp_poses = _stamp_poses(ctx["poses"], [ref_stamp, *cam_stamps.values()])
        for buf in list(ctx["gt_buf"].values()) + [ctx["odom_buf"]]:
            while buf and buf[0][0] < mean - ctx["tol"]:  # older than any later frame can match
                buf.popleft()
        return BagFrame(
            index=index,
            stamp_ns=ref_stamp,
            camera_stamps=cam_stamps,
            valid=valid,
            rgb=images["rgb"],
            labels=images["labels"],
            gt_classes=tuple(ctx["classes"]),
            gt=gt,
            gt_known=known,
            odom=odom_state,
            ground_visibility=ground,
            visibility=visibility,
            truth=truth,
            stamp_poses=stamp_poses,
        )

    def layer(self, topic: str, mean: int, index: int, ctx: dict, out: np.ndarray | None = None) -> np.ndarray | None:
        """``(H, W)`` bool: cells >= 0.5 of the extra layer ``topic`` nearest ``mean`` (or written
        into ``out``, see :meth:`LayerDecoder.half`), or ``None`` when the bag has none there or it
        does not decode (counted in :attr:`issues`).
        """
        buf = ctx["gt_buf"].get(topic)
        hit = None if buf is None else _nearest(buf, mean, ctx["tol"])
        if hit is None:
            return None
        try:
            return ctx["layers"].half(hit[1], out)
        except DECODE_ERRORS as exc:
            self.reader.issues.decode_error(topic, f"frame {index}: {exc}")
            return None

    def images(self, s: SyncedSet, index: int, ctx: dict):
        """Decoded images per kind and camera, validity and stamp per camera, of one set.

        A camera is valid when all requested kinds are present, decode, and have the size of
        its CameraInfo; a failure is counted in :attr:`issues` and invalidates the camera.
        """
        cams, kinds, sizes = ctx["cams"], ctx["kinds"], ctx["sizes"]
        images: dict[str, dict[str, np.ndarray]] = {"rgb": {}, "labels": {}}
        valid: dict[str, bool] = {}
        cam_stamps: dict[str, int | None] = {}
        for c in cams:
            ok = all(s.messages[f"{c}/{k}"] is not None for k in kinds)
            stamps = [s.stamps[f"{c}/{k}"] for k in kinds if s.stamps[f"{c}/{k}"] is not None]
            cam_stamps[c] = min(stamps) if stamps else None
            if ok:
                for k in kinds:
                    msg = s.messages[f"{c}/{k}"]
                    try:
                        arr = decode_image(msg, k, ctx["compressed"][f"{c}/{k}"], sizes.get(c), ctx["label_map"])
                        images[k][c] = np.array(arr, copy=True)
                    except DECODE_ERRORS as exc:
                        log.warning("frame %d camera %s: %s", index, c, exc)
                        self.reader.issues.decode_error(self.reader.image_topic(c, k), f"frame {index}: {exc}")
                        ok = False
                        break
                if not ok:
                    for k in kinds:
                        images[k].pop(c, None)
            valid[c] = ok
        return images, valid, cam_stamps

    def gt(self, mean: int, index: int, ctx: dict):
        """``(stamp, gt, known)`` of the GT layers nearest ``mean``; ``gt`` and ``known`` are
        ``None`` when a layer is missing or, counted in :attr:`issues`, does not fit the grid;
        ``stamp`` is that of the last layer found.
        """
        classes = ctx["classes"]
        if not classes:
            return None, None, None
        stamp = None
        shape = (len(classes),) + ctx["grid"].shape
        half = ctx["gt_half"]
        gt, known = np.empty(shape, bool if half else np.float32), np.empty(shape, bool)  # (C, H, W)
        for ci, c in enumerate(classes):
            hit = _nearest(ctx["gt_buf"][c], mean, ctx["tol"])
            if hit is None:
                return stamp, None, None
            stamp = hit[0]
            try:
                (ctx["layers"].half_into if half else ctx["layers"].into)(hit[1], gt[ci], known[ci])
            except DECODE_ERRORS as exc:
                self.reader.issues.decode_error(T.gt_topic(c), f"stamp {hit[0]}: {exc}")
                return stamp, None, None
        return stamp, gt, known
