"""Reading bev_mapper bags: the rig, the grid and synchronized frames.

:class:`BagReader` opens a rosbag2 directory (mcap or sqlite3) or a plain ``.mcap``/``.db3``
file, builds the :class:`~bev_mapper_core.geometry.rig.Rig` from the bag's own CameraInfo and
``/tf_static``, the :class:`~bev_mapper_core.geometry.grid.BevGrid` from the GT OccupancyGrid info, and
iterates frames synchronized by :class:`msg_adapters.FrameSynchronizer` on the header stamps
(assembled in :mod:`bags.io.reader.assembly`).

A damaged bag yields every frame before the damage, then raises :class:`BagCorruptError`.
Topics of the wrong type are a :class:`BagContentError`; single damaged messages (an image
that does not decode or does not fit its calibration, a GT grid that does not fit the grid,
an odometry pose that is no rotation, an invalid header stamp) are skipped and counted in
:attr:`BagReader.issues` (see :mod:`bags.io.input_checks`).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from bev_mapper_core.errors import BevMapperError, ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig, RigCamera, preset_rig
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, bev_class
from bev_mapper_core.labels.label_maps import LabelMap
from msg_adapters import SyncConfig, TfTree, camera_info_to_model, grid_from_info

from ...errors import BagContentError, BagCorruptError
from .. import topics as T
from ..input_checks import DECODE_ERRORS, InputIssues, check_grid_size, check_types, type_problems
from ..raw import fast_deserializer
from ..rig_source import RIG_FLAGS_HINT, RigHints, matching_preset
from ..sources import TopicSummary, open_source
from ..sync_report import SyncReport
from .assembly import read_frames
from .frame import DEFAULT_SYNC, MS, BagFrame, BagMessage


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
        """The image topic of ``camera`` (``/cameras/<camera>/image_raw`` unless the hints say);
        where the bag lacks it but has its compressed transport (``<topic>/compressed``,
        image_transport's convention), that one.
        """
        topic = self.hints.image_topics[kind].format(camera=camera)
        if topic not in self._src.topics and T.compressed_topic(topic) in self._src.topics:
            return T.compressed_topic(topic)
        return topic

    def is_compressed(self, topic: str) -> bool:
        """Whether ``topic`` carries ``sensor_msgs/CompressedImage`` (JPEG / PNG), whatever its name."""
        s = self._src.topics.get(topic)
        return s is not None and s.msgtype == T.COMPRESSED_IMAGE_TYPE

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
        """Classes with a ``/bev/gt/<class>`` topic: standard order first, then the rest sorted;
        only classes this package defines (:func:`~bev_mapper_core.labels.classes.bev_class`): the
        others are :attr:`unknown_gt_classes`, never read.
        """
        found = {c for c in map(T.parse_gt_topic, self._src.topics) if c} - set(self.unknown_gt_classes)
        return tuple(c for c in BEV_CLASS_NAMES if c in found) + tuple(
            sorted(found - set(BEV_CLASS_NAMES))
        )

    @property
    def unknown_gt_classes(self) -> tuple[str, ...]:
        """``/bev/gt/<class>`` layers of classes this package does not define (e.g. another
        recorder's ``walkway``), sorted: nothing can be scored against them, so they are skipped.
        """
        return tuple(sorted(c for c in map(T.parse_gt_topic, self._src.topics) if c and not _known_class(c)))

    @property
    def truth_classes(self) -> tuple[str, ...]:
        """Classes with a ``/bev/truth/<class>`` topic, in the order of :attr:`gt_classes` (then
        the rest sorted); only classes this package defines, as there.
        """
        found = {c for c in map(T.parse_truth_topic, self._src.topics) if c and _known_class(c)}
        gt = self.gt_classes
        return tuple(c for c in gt if c in found) + tuple(sorted(found - set(gt)))

    def messages(self, topics: Iterable[str] | None = None, *, fast: bool = False,
                 raw: bool = False) -> Iterator[BagMessage]:
        """Deserialized messages in log-time order, optionally only of ``topics``.

        ``fast``: Images and OccupancyGrids come as read-only views of their bytes
        (:func:`bags.io.raw.fast_deserializer`: the same fields, but no rosbags message to
        serialize again), for callers that only read them. ``raw``: every message as its CDR
        bytes, not deserialized (see :meth:`deserialize`).

        Raises:
            BagCorruptError: at the point of damage, after the readable messages.
        """
        wanted = None if topics is None else set(topics)
        decode = _as_bytes if raw else fast_deserializer(self._src.deserializer()) if fast else None
        for topic, msgtype, t, msg in self._src.messages(wanted, decode, views=fast):
            yield BagMessage(topic, msgtype, t, msg)

    def deserialize(self, raw: bytes, msgtype: str) -> Any:
        """A message of :meth:`messages` with ``raw=True`` deserialized (rosbags')."""
        return self._src.deserializer()(raw, msgtype)

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
        gt_half: bool = False,
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
            gt_half: ``gt`` and ``truth`` as bool, the cells ``>= 0.5`` (what the scorers
                read), instead of float32: no float decoding (the replay's).

        Messages with an invalid header stamp, images that do not decode or whose size differs
        from their camera's CameraInfo, GT layers that do not fit the grid and odometry that
        does not decode are skipped and counted in :attr:`issues`.

        Raises:
            BagContentError: no image topics for the requested kinds, or a topic used of the
                wrong type.
            BagCorruptError: after the frames before the damage were yielded.
        """
        yield from read_frames(self, rgb=rgb, labels=labels, gt=gt, odom=odom, sync=sync,
                               lookahead_ns=lookahead_ns, label_map=label_map, gt_half=gt_half)


def _known_class(name: str) -> bool:
    """Whether ``name`` is a BEV class of this package (any of its class sets)."""
    try:
        bev_class(name)
    except ConfigError:
        return False
    return True


def _as_bytes(raw: bytes, msgtype: str) -> bytes:
    """The "deserializer" of raw messages: the CDR bytes themselves."""
    del msgtype
    return bytes(raw)
