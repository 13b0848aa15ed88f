"""Reading bev_mapper bags: the rig, the grid and synchronized frames.

:class:`BagReader` opens a rosbag2 directory (mcap or sqlite3) or a plain ``.mcap``/``.db3``
file, builds the :class:`~bev_mapper_core.geometry.rig.Rig` from the bag's own CameraInfo and
``/tf_static``, the :class:`~bev_mapper_core.geometry.grid.BevGrid` from the GT OccupancyGrid info, and
iterates frames synchronized by :class:`msg_adapters.FrameSynchronizer` on the header stamps.

A damaged bag yields every frame before the damage, then raises :class:`BagCorruptError`.
Topics of the wrong type are a :class:`BagContentError`; single damaged messages (an image
that does not decode or does not fit its calibration, a GT grid that does not fit the grid,
an odometry pose that is no rotation, an invalid header stamp) are skipped and counted in
:attr:`BagReader.issues` (see :mod:`bags.io.input_checks`).
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig, RigCamera, preset_rig
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES
from bev_mapper_core.labels.label_maps import LabelMap
from msg_adapters import (
    AdapterError,
    FrameSynchronizer,
    OdometryState,
    SyncConfig,
    SyncedSet,
    TfTree,
    camera_info_to_model,
    grid_from_info,
    header_stamp_ns,
    image_to_labels,
    image_to_rgb,
    occupancy_grid_to_layer,
    odometry_to_state,
    tf_message_transforms,
)

from ..errors import BagContentError, BagCorruptError
from . import topics as T
from .input_checks import DECODE_ERRORS, InputIssues, StampDrift, check_grid_size, check_types, stamp_problem, type_problems
from .rig_source import RIG_FLAGS_HINT, RigHints, matching_preset
from .sources import TopicSummary, open_source
from .sync_report import SyncReport

log = logging.getLogger(__name__)

MS = 1_000_000
#: Default synchronization of bag frames: :meth:`SyncConfig.replay` (the node's window, cameras
#: of one frame within 50 ms of each other and half the frame period; a longer timeout).
DEFAULT_SYNC = SyncConfig.replay()


@dataclass(frozen=True)
class BagMessage:
    """One deserialized message (rosbags dataclass) with its topic, type and log time."""

    topic: str
    msgtype: str
    log_ns: int
    msg: Any


@dataclass(frozen=True)
class BagFrame:
    """One synchronized frame of a bag.

    Attributes:
        index: 0-based count of yielded frames.
        stamp_ns: the frame's reference stamp: the matched GT (else odometry) header stamp,
            else the mean of the camera stamps.
        camera_stamps: per camera, the header stamp of its image (``None`` if missing).
        valid: per camera (rig order), True when all requested images are present and decoded.
        rgb, labels: per valid camera, ``(H, W, 3)`` uint8 RGB / ``(H, W)`` uint8 label ids
            (only the kinds requested).
        gt_classes: names of the GT layers, in layer order.
        gt: ``(C, H, W)`` float32 in [0, 1] (100 -> 1.0), or ``None`` if no GT matched.
        gt_known: ``(C, H, W)`` bool, False where the layer was -1 (not visible).
        odom: the matched odometry, or ``None``.
        ground_visibility: ``(H, W)`` bool, cells whose ground point some camera sees (from
            ``/bev/visibility/ground``), or ``None`` when the bag has no such layer.
        visibility: ``(H, W)`` bool, cells some camera sees (from ``/bev/visibility/any``), or
            ``None`` when the bag has no such layer (then ``gt_known`` tells the same).
        truth: ``(C, H, W)`` float32 0/1, what is in every cell whether seen or not (from
            ``/bev/truth/<class>``, layers in ``gt_classes`` order), or ``None`` when the bag
            lacks a truth layer of one of the GT classes (bags written before they existed).
    """

    index: int
    stamp_ns: int
    camera_stamps: dict[str, int | None]
    valid: dict[str, bool]
    rgb: dict[str, np.ndarray]
    labels: dict[str, np.ndarray]
    gt_classes: tuple[str, ...]
    gt: np.ndarray | None
    gt_known: np.ndarray | None
    odom: OdometryState | None
    ground_visibility: np.ndarray | None = None
    visibility: np.ndarray | None = None
    truth: np.ndarray | None = None

    @property
    def valid_mask(self) -> np.ndarray:
        """Validity as a bool array in rig order."""
        return np.array(list(self.valid.values()), dtype=bool)


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


class BagReader:
    """Reads a bev_mapper bag (see module docstring). Use as a context manager.

    Args:
        path: rosbag2 directory, ``.mcap`` or ``.db3`` file.
        ego_frame: the frame the camera extrinsics are expressed in (``hints.base_frame``
            replaces it).
        hints: what the user says about the rig where the bag lacks it (``--rig``,
            ``--params-file``: :mod:`bags.io.rig_source`): camera names and order, topic
            patterns, extrinsics and intrinsics, the rig's name.
    """

    def __init__(self, path: str | Path, *, ego_frame: str = "base_link", hints: RigHints | None = None) -> None:
        self.path = Path(path)
        self.hints = hints or RigHints()
        self.ego_frame = self.hints.base_frame or ego_frame
        self._src = open_source(self.path)
        self._rig: Rig | None = None
        self._grid: BevGrid | None = None
        #: messages skipped as damaged, cameras without calibration (see module docstring)
        self.issues = InputIssues()
        self.issues.cameras_without_calibration = list(self.uncalibrated_cameras)
        #: cameras missing from synchronized sets, per camera (filled as :meth:`frames` runs)
        self.sync_report = SyncReport()

    def __enter__(self) -> "BagReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release the underlying files."""
        self._src.close()

    # ---------------------------------------------------------------- content
    @property
    def topics(self) -> dict[str, TopicSummary]:
        """Topic -> type and message count."""
        return dict(self._src.topics)

    @property
    def damage(self) -> str | None:
        """Why the bag is read in degraded (stream) mode, or ``None`` for an intact bag."""
        return self._src.damage

    @property
    def latched_topics(self) -> set[str]:
        """Topics recorded with transient-local durability (empty when the storage has no QoS)."""
        return set(getattr(self._src, "latched", ()))

    @property
    def custom_data(self) -> dict[str, str]:
        """``custom_data`` of metadata.yaml (empty for plain files)."""
        return dict(self._src.custom_data)

    def image_topic(self, camera: str, kind: str = "rgb") -> str:
        """The image topic of ``camera`` (``/cameras/<camera>/image_raw`` unless the hints say)."""
        return self.hints.image_topics[kind].format(camera=camera)

    def camera_info_topic(self, camera: str) -> str:
        """The CameraInfo topic of ``camera`` (``/cameras/<camera>/camera_info`` unless the hints say)."""
        return self.hints.camera_info_topic.format(camera=camera)

    @property
    def camera_names(self) -> tuple[str, ...]:
        """The rig's cameras: the hints' (in their order) that have a CameraInfo topic or given
        intrinsics; else those with a ``/cameras/<cam>/camera_info`` topic, in the bag's topic order.
        """
        if self.hints.cameras:
            return tuple(c for c in self.hints.cameras if c not in self.uncalibrated_cameras)
        names = []
        for topic in self._src.topic_order:
            parsed = T.parse_camera_topic(topic)
            if parsed and parsed[1] == "camera_info" and parsed[0] not in names:
                names.append(parsed[0])
        return tuple(names)

    @property
    def uncalibrated_cameras(self) -> tuple[str, ...]:
        """Cameras with image topics but no CameraInfo topic (nor intrinsics from the hints):
        they cannot be mapped.
        """
        if self.hints.cameras:
            return tuple(c for c in self.hints.cameras
                         if self.camera_info_topic(c) not in self._src.topics and c not in self.hints.intrinsics
                         and any(self.image_topic(c, k) in self._src.topics for k in T.IMAGE_KINDS))
        names = []
        for topic in self._src.topic_order:
            parsed = T.parse_camera_topic(topic)
            if (parsed and parsed[1] != "camera_info" and parsed[0] not in names
                    and T.camera_info_topic(parsed[0]) not in self._src.topics):
                names.append(parsed[0])
        return tuple(names)

    @property
    def type_problems(self) -> list[str]:
        """Topics whose type differs from the one their name calls for (see
        :func:`bags.io.input_checks.expected_type`).
        """
        return type_problems({t: s.msgtype for t, s in self._src.topics.items()})

    @property
    def decode_errors(self) -> int:
        """Messages that could not be decoded so far (see :attr:`issues`)."""
        return self.issues.decode_errors

    def _check_types(self, topics: Iterable[str]) -> None:
        check_types(self.path, {t: s.msgtype for t, s in self._src.topics.items()}, set(topics))

    @property
    def gt_classes(self) -> tuple[str, ...]:
        """Classes with a ``/bev/gt/<class>`` topic: standard order first, then the rest sorted."""
        found = {c for c in map(T.parse_gt_topic, self._src.topics) if c}
        return tuple(c for c in BEV_CLASS_NAMES if c in found) + tuple(
            sorted(found - set(BEV_CLASS_NAMES))
        )

    @property
    def truth_classes(self) -> tuple[str, ...]:
        """Classes with a ``/bev/truth/<class>`` topic, in the order of :attr:`gt_classes` (then
        the rest sorted).
        """
        found = {c for c in map(T.parse_truth_topic, self._src.topics) if c}
        gt = self.gt_classes
        return tuple(c for c in gt if c in found) + tuple(sorted(found - set(gt)))

    def messages(self, topics: Iterable[str] | None = None) -> Iterator[BagMessage]:
        """Deserialized messages in log-time order, optionally only of ``topics``.

        Raises:
            BagCorruptError: at the point of damage, after the readable messages.
        """
        wanted = None if topics is None else set(topics)
        for topic, msgtype, t, msg in self._src.messages(wanted):
            yield BagMessage(topic, msgtype, t, msg)

    # ------------------------------------------------------------ rig & grid
    def rig(self) -> Rig:
        """The camera rig: each camera's first CameraInfo and its extrinsics from ``/tf_static``;
        where the bag has none, the hints' intrinsics and extrinsics. Named by the hints, else
        the bag's ``bev_mapper.rig`` metadata, else the preset whose cameras and calibration it
        has (:func:`~bags.io.rig_source.matching_preset`), else after the bag's file name.

        Raises:
            BagContentError: no cameras, a camera without CameraInfo or a camera frame that
                ``/tf_static`` does not connect to ``ego_frame``, and no hints for them (the
                message names ``--rig`` / ``--params-file``).
        """
        if self._rig is not None:
            return self._rig
        names = self.camera_names
        if not names:
            raise BagContentError(f"{self.path}: no /cameras/<name>/camera_info topics; {RIG_FLAGS_HINT}")
        infos: dict[str, Any] = {}
        tree = TfTree()
        info_topics = {self.camera_info_topic(n): n for n in names if self.camera_info_topic(n) in self._src.topics}
        has_tf = T.TF_STATIC in self._src.topics
        wanted = set(info_topics) | ({T.TF_STATIC} if has_tf else set())
        self._check_types(wanted)
        for m in self.messages(wanted):
            if m.topic == T.TF_STATIC:
                try:
                    tree.add_message(m.msg)
                except DECODE_ERRORS as exc:
                    raise BagContentError(f"{self.path}: {T.TF_STATIC}: {exc}") from None
            else:
                infos.setdefault(info_topics[m.topic], m.msg)
            if len(infos) == len(info_topics) and (not has_tf or self._all_connected(tree, infos)):
                break
        missing = [n for n in names if n not in infos and n not in self.hints.intrinsics]
        if missing:
            raise BagContentError(f"{self.path}: no CameraInfo message for cameras {missing}; {RIG_FLAGS_HINT}")
        cams = [self._camera(n, infos.get(n), tree) for n in names]
        rig = Rig(self.path.stem, tuple(cams))
        preset = matching_preset(rig)
        name = self.hints.name or self.custom_data.get("bev_mapper.rig") or preset
        if name and not self.hints.cameras and preset == name:
            rig = Rig(name, tuple(rig[c] for c in preset_rig(name).names))  # the preset's camera order
        self._rig = Rig(name or self.path.stem, rig.cameras)
        return self._rig

    def _camera(self, name: str, info: Any, tree: TfTree) -> RigCamera:
        """One camera of :meth:`rig`: the bag's CameraInfo and TF, else the hints'."""
        try:
            if info is not None:
                frame = str(info.header.frame_id).lstrip("/")
                model = camera_info_to_model(info)
            else:
                frame, model = name, self.hints.intrinsics[name]
            try:
                ego_from_cam = tree.lookup(self.ego_frame, frame)
            except DECODE_ERRORS as exc:
                if name not in self.hints.extrinsics:
                    raise BagContentError(f"{self.path}: camera {name!r}: {exc}; {RIG_FLAGS_HINT}") from None
                ego_from_cam = self.hints.extrinsics[name]
            return RigCamera(name, model, ego_from_cam, frame)
        except (BevMapperError, *DECODE_ERRORS) as exc:
            raise BagContentError(f"{self.path}: camera {name!r}: {exc}") from None

    def _all_connected(self, tree: TfTree, infos: dict[str, Any]) -> bool:
        try:
            for msg in infos.values():
                tree.lookup(self.ego_frame, str(msg.header.frame_id))
        except DECODE_ERRORS:
            return False
        return True

    def grid(self) -> BevGrid | None:
        """The BEV grid of the GT layers (from the first GT OccupancyGrid), ``None`` without GT
        (or when damage comes before the first GT message: the frames report it).

        Raises:
            BagContentError: a GT topic has the wrong type, or the first GT message no usable
                grid (e.g. more than :data:`~bags.io.input_checks.MAX_GRID_CELLS` cells).
        """
        if self._grid is None and self.gt_classes:
            topics = {T.gt_topic(c) for c in self.gt_classes}
            self._check_types(topics)
            try:
                for m in self.messages(topics):
                    try:
                        check_grid_size(m.msg.info)
                        self._grid = grid_from_info(m.msg.info)
                    except DECODE_ERRORS as exc:
                        raise BagContentError(f"{self.path}: {m.topic}: {exc}") from None
                    break
            except BagCorruptError:
                pass
        return self._grid

    def _camera_sizes(self) -> dict[str, tuple[int, int]]:
        """Delivered image ``(width, height)`` per camera: the rig's, else from the first
        CameraInfo (cameras whose CameraInfo does not decode are not checked).
        """
        if self._rig is not None:
            return {c.name: tuple(c.model.image_size) for c in self._rig.cameras}
        names = self.camera_names
        sizes: dict[str, tuple[int, int]] = {}
        try:
            topics = {self.camera_info_topic(n): n for n in names}
            wanted = set(topics) & set(self._src.topics)
            for m in self.messages(wanted):
                cam = topics[m.topic]
                try:  # the delivered size: after binning and ROI
                    sizes.setdefault(cam, tuple(camera_info_to_model(m.msg).image_size))
                except (BevMapperError, *DECODE_ERRORS):
                    pass
                if len(sizes) == len(wanted):
                    break
        except BagCorruptError:
            pass  # the frame pass reports the damage
        for n in names:  # cameras calibrated by the hints alone
            if n not in sizes and n in self.hints.intrinsics:
                sizes[n] = tuple(self.hints.intrinsics[n].image_size)
        return sizes

    # ----------------------------------------------------------------- frames
    def frames(
        self,
        *,
        rgb: bool = True,
        labels: bool = True,
        gt: bool = True,
        odom: bool = True,
        sync: SyncConfig = DEFAULT_SYNC,
        lookahead_ns: int = 500 * MS,
        label_map: LabelMap | None = None,
    ) -> Iterator[BagFrame]:
        """Synchronized frames of the bag (see :class:`BagFrame`).

        Args:
            rgb, labels: which images to decode; a camera is valid in a frame when all the
                requested kinds are present for it.
            gt, odom: match GT layers / odometry to each frame (nearest stamp within
                ``sync.slop_ns`` of the mean camera stamp).
            sync: synchronizer settings (stamp-driven time).
            lookahead_ns: a frame is yielded once the bag's log time passes its newest camera
                stamp by this much, so that its GT and odometry have been read.
            label_map: what the label images hold (:mod:`bev_mapper_core.labels.label_maps`), applied as
                each is decoded, so ``labels`` are Label ids; None = ``native``. A label image of
                another encoding than the map takes is a decode error (skipped, counted).

        Messages with an invalid header stamp, images that do not decode or whose size differs
        from their camera's CameraInfo, GT layers that do not fit the grid and odometry that
        does not decode are skipped and counted in :attr:`issues`.

        Raises:
            BagContentError: no image topics for the requested kinds, or a topic used of the
                wrong type.
            BagCorruptError: after the frames before the damage were yielded.
        """
        cams = self.camera_names
        kinds = [k for k, on in (("rgb", rgb), ("labels", labels)) if on]
        stream_of = {
            self.image_topic(c, k): f"{c}/{k}" for c in cams for k in kinds
            if self.image_topic(c, k) in self._src.topics
        }
        if not stream_of:
            raise BagContentError(f"{self.path}: no image topics for {kinds} of cameras {cams}")
        classes = self.gt_classes if gt else ()
        grid = self.grid() if classes else None
        gt_topics = {T.gt_topic(c): c for c in classes}
        for extra in (T.GROUND_VISIBILITY, T.ANY_VISIBILITY):
            if classes and extra in self._src.topics:
                gt_topics[extra] = extra
        if classes and set(classes) <= set(self.truth_classes):  # all or nothing
            gt_topics.update({T.truth_topic(c): T.truth_topic(c) for c in classes})
        want_odom = odom and T.ODOM in self._src.topics
        want_tf = odom and not want_odom and T.TF in self._src.topics  # ego poses from /tf without /odom
        topics = set(stream_of) | set(gt_topics) | ({T.ODOM} if want_odom else set()) | ({T.TF} if want_tf else set())
        self._check_types(topics)

        streams = [f"{c}/{k}" for c in cams for k in kinds]
        sync_ = FrameSynchronizer(streams, sync)
        self.sync_report = SyncReport(cameras=cams, window_ms=sync.slop_ns / 1e6, cameras_without_images=tuple(
            c for c in cams if not all(self.image_topic(c, k) in self._src.topics for k in kinds)))
        gt_buf = {c: deque() for c in gt_topics.values()}
        odom_buf: deque = deque()
        ready: deque[SyncedSet] = deque()
        ctx = dict(cams=cams, kinds=kinds, classes=classes, grid=grid, gt_buf=gt_buf,
                   odom_buf=odom_buf, tol=sync.slop_ns, sizes=self._camera_sizes(), label_map=label_map, sync=sync_)
        drift = StampDrift()
        index = 0
        try:
            for m in self.messages(topics):
                if m.topic == T.TF:
                    odom_buf.extend(self._tf_poses(m.msg))
                    continue
                bad = stamp_problem(m.msg)
                stamp = header_stamp_ns(m.msg) if bad is None else 0
                bad = bad or drift.problem(m.topic, stamp, m.log_ns)
                if bad is not None:
                    self.issues.bad_stamp(m.topic, bad)
                    continue
                if m.topic in stream_of:
                    ready.extend(sync_.add(stream_of[m.topic], stamp, m.msg))
                elif m.topic in gt_topics:
                    gt_buf[gt_topics[m.topic]].append((stamp, m.msg))
                else:
                    odom_buf.append((stamp, m.msg))
                while ready and _newest(ready[0]) + lookahead_ns < m.log_ns:
                    yield self._build(ready.popleft(), index, ctx)
                    index += 1
        except BagCorruptError as exc:
            while ready:  # sets completed before the damage
                yield self._build(ready.popleft(), index, ctx)
                index += 1
            raise BagCorruptError(f"{exc}; {index} frame(s) were read before the damage") from None
        ready.extend(sync_.flush())
        while ready:
            yield self._build(ready.popleft(), index, ctx)
            index += 1

    def _tf_poses(self, msg: Any) -> list[tuple[int, OdometryState]]:
        """``(stamp, pose)`` of each ``<fixed frame> -> ego_frame`` transform of a ``/tf`` message,
        the ego pose as the node's ``pose_source: tf`` reads it (no velocities); a message that
        does not decode is counted in :attr:`issues` and skipped.
        """
        try:
            found = [t for t in tf_message_transforms(msg) if t.child == self.ego_frame]
        except DECODE_ERRORS as exc:
            self.issues.decode_error(T.TF, str(exc))
            return []
        zero = np.zeros(3)
        return [(t.stamp_ns, OdometryState(t.stamp_ns, t.parent, t.child, t.matrix, zero, zero)) for t in found]

    def _build(self, s: SyncedSet, index: int, ctx: dict) -> BagFrame:
        images, valid, cam_stamps = self._images(s, index, ctx)
        self.sync_report.add(valid, ctx["sync"])
        mean = s.mean_stamp_ns
        stamp, gt, known = self._gt(mean, ctx)
        ground = self._layer(T.GROUND_VISIBILITY, mean, index, ctx)
        ground = None if ground is None else ground >= 0.5
        visibility = self._layer(T.ANY_VISIBILITY, mean, index, ctx)
        visibility = None if visibility is None else visibility >= 0.5
        truth = None
        if gt is not None:
            layers = [self._layer(T.truth_topic(c), mean, index, ctx) for c in ctx["classes"]]
            if all(layer is not None for layer in layers):
                truth = (np.stack(layers) >= 0.5).astype(np.float32)  # C x (H, W) -> (C, H, W)
        odom_state = None
        hit = _nearest(ctx["odom_buf"], mean, ctx["tol"])
        if hit is not None:
            try:
                odom_state = hit[1] if isinstance(hit[1], OdometryState) else odometry_to_state(hit[1])
                stamp = hit[0] if stamp is None else stamp
            except DECODE_ERRORS as exc:
                self.issues.decode_error(T.ODOM, f"frame {index}: {exc}")
        for buf in list(ctx["gt_buf"].values()) + [ctx["odom_buf"]]:
            while buf and buf[0][0] < mean - ctx["tol"]:  # older than any later frame can match
                buf.popleft()
        return BagFrame(
            index=index,
            stamp_ns=int(mean if stamp is None else stamp),
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
        )

    def _layer(self, topic: str, mean: int, index: int, ctx: dict) -> np.ndarray | None:
        """``(H, W)`` float32 of the extra layer ``topic`` nearest ``mean`` (unknown cells 0), or
        ``None`` when the bag has none there or it does not decode (counted in :attr:`issues`).
        """
        buf = ctx["gt_buf"].get(topic)
        hit = None if buf is None else _nearest(buf, mean, ctx["tol"])
        if hit is None:
            return None
        try:
            return occupancy_grid_to_layer(hit[1], ctx["grid"])[0]
        except DECODE_ERRORS as exc:
            self.issues.decode_error(topic, f"frame {index}: {exc}")
            return None

    def _images(self, s: SyncedSet, index: int, ctx: dict):
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
                        arr = (image_to_rgb(msg) if k == "rgb"
                               else image_to_labels(msg, label_map=ctx["label_map"]))
                        h, w = arr.shape[:2]
                        if c in sizes and (w, h) != sizes[c]:
                            raise AdapterError(f"image is {w}x{h}, camera {c!r} is calibrated "
                                               f"for {sizes[c][0]}x{sizes[c][1]}")
                        images[k][c] = np.array(arr, copy=True)
                    except DECODE_ERRORS as exc:
                        log.warning("frame %d camera %s: %s", index, c, exc)
                        self.issues.decode_error(self.image_topic(c, k), f"frame {index}: {exc}")
                        ok = False
                        break
                if not ok:
                    for k in kinds:
                        images[k].pop(c, None)
            valid[c] = ok
        return images, valid, cam_stamps

    def _gt(self, mean: int, ctx: dict):
        """``(stamp, gt, known)`` of the GT layers nearest ``mean``; ``gt`` and ``known`` are
        ``None`` when a layer is missing or, counted in :attr:`issues`, does not fit the grid;
        ``stamp`` is that of the last layer found.
        """
        if not ctx["classes"]:
            return None, None, None
        layers, stamp = [], None
        for c in ctx["classes"]:
            hit = _nearest(ctx["gt_buf"][c], mean, ctx["tol"])
            if hit is None:
                return stamp, None, None
            stamp = hit[0]
            try:
                layers.append(occupancy_grid_to_layer(hit[1], ctx["grid"]))
            except DECODE_ERRORS as exc:
                self.issues.decode_error(T.gt_topic(c), f"stamp {hit[0]}: {exc}")
                return stamp, None, None
        gt = np.stack([p for p, _ in layers])  # C x (H, W) -> (C, H, W)
        known = np.stack([k for _, k in layers])
        return stamp, gt, known
