"""The BEV mapper node: synchronized camera images in, per-class OccupancyGrids out.

    ros2 run bev_mapper_ros mapper_node --ros-args -p rig:=surround6
    ros2 run bev_mapper_ros mapper_node --ros-args --params-file <share>/config/surround6.yaml
    ros2 run bev_mapper_ros mapper_node --help     # usage and every parameter

Callbacks only convert stamps and feed the synchronizer; complete (or timed-out partial) sets
go to a one-slot mailbox; a worker thread decodes, maps and publishes. Bad input is logged
(throttled), counted in ``/diagnostics`` and skipped: the node keeps running.

Outputs ``<output_prefix>/<class>`` (``nav_msgs/OccupancyGrid``) and ``<output_prefix>/image``
are published RELIABLE + TRANSIENT_LOCAL with depth 1 (:data:`OUTPUT_QOS`): volatile
subscribers match, and a late transient-local one (RViz's Map display, Nav2) gets the last
grid. Their publishers exist from start-up (the classes are known once the configuration
passed its preflight), so ``ros2 topic echo /bev/drivable`` finds the type before data flows.

SIGINT / SIGTERM stop the node cleanly: the worker finishes (or abandons) its frame, nothing
is logged as an error, exit status 0.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time

#: SIGINT / SIGTERM received while the imports below run (rclpy, numpy, the core: ~0.5 s) in a
#: process started as the node (``python -m bev_mapper_ros.mapper_node`` or the ``mapper_node``
#: script): :func:`main` then stops at once with exit status 0, instead of Python's
#: KeyboardInterrupt traceback (exit -2) or SIGTERM's default death (issue #41).
_EARLY_STOP = threading.Event()
if threading.current_thread() is threading.main_thread() and (
        __name__ == "__main__" or os.path.basename(sys.argv[0] if sys.argv else "") == "mapper_node"):
    for _sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(_sig, lambda signum, frame: _EARLY_STOP.set())

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import OccupancyGrid, Odometry
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.ego_mask import EgoMaskError, attach_ego_masks, load_ego_mask, mask_notes
from bev_mapper_core.labels.classes import bev_picture
from bev_mapper_core.labels.label_maps import label_map
from bev_mapper_core.mapper import create_mapper, mapper_class, output_classes, preflight
from bev_mapper_core.nn.export_process import cancel_exports
from bev_mapper_core.placement import RigPlacer
from bev_mapper_core.temporal import TemporalFusion
from msg_adapters import (
    FrameSynchronizer,
    RclpyFactory,
    camera_info_key,
    camera_info_to_model,
    compressed_to_labels,
    compressed_to_rgb,
    header_stamp_ns,
    image_to_labels,
    image_to_rgb,
    make_image,
    make_occupancy_grid,
)

from .calibration import LiveCalibration
from .command_line import CommandLineError, check_command_line, rcl_message, wants_help
from .config import RUNTIME_PARAMETERS, NodeConfigError, node_config_from_params, with_runtime_parameters
from .ego_pose import EgoPoses
from .input_qos import RECHECK_S, CameraSubscription
from .odometry import ClockWatch
from .params import declare_parameters, parameter_help, read_parameters
from .stats import WARN, NodeStats, clock_mismatch_text, diagnostic_values
from .tf_source import TF_ERROR_KINDS, make_tf_source
from .worker import LatestSlot, Worker

THROTTLE_S = 5.0
#: QoS of the grids and the picture: reliable, transient local, depth 1. Volatile subscribers
#: match it too; a transient-local one that comes late (RViz Map display, Nav2) gets the last.
OUTPUT_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.TRANSIENT_LOCAL)


class _ShuttingDown(Exception):
    """The node stops: the worker abandons its frame without a word."""


class MapperNode(Node):
    """Subscribes to N cameras, maps synchronized sets to BEV, publishes grids + diagnostics."""

    def __init__(self, **kwargs) -> None:
        super().__init__("mapper_node", **kwargs)
        for text in declare_parameters(self):  # unknown parameters: before an error they may explain
            self.get_logger().warning(text)
        self.cfg = node_config_from_params(read_parameters(self))  # raises on bad parameters
        cfg = self.cfg
        preflight(cfg.mapper, cfg.rig, cfg.grid, cfg.cameras)  # e.g. missing weights: fail now
        self.class_names = output_classes(cfg.mapper, cfg.rig)
        self.label_map = label_map(cfg.mapper.label_map)  # one lookup table, applied as images are decoded
        self.factory = RclpyFactory()
        self.stats = NodeStats()
        self._last_logged: dict[str, float] = {}
        self._stopping = threading.Event()
        self.mapper = None
        self._mapper_version = -1
        # TF: extrinsics (base_frame <- each CameraInfo's frame) and, per pose_source, ego poses;
        # its problems are counted per kind (tf_errors_<kind> in /diagnostics), never fatal
        self.tf_errors = dict.fromkeys(TF_ERROR_KINDS, 0)
        self._tf_errors_reported = 0
        self.tf_last_error = ""
        self.tf = make_tf_source(self, self._tf_problem, cfg.clock_mismatch_s, self._contained) if cfg.use_tf else None
        if cfg.use_tf and self.tf is None:
            if cfg.pose_source == "tf":
                raise NodeConfigError("pose_source tf needs tf2_ros, which is not importable here "
                                      "(scripts/setup_venv.sh builds it; or source a ROS 2 distribution)")
            self.get_logger().warning("use_tf: tf2_ros is not importable, so TF is not read: extrinsics come from the "
                                      "extrinsics.<camera> parameters, ego poses from odom_topic")
        self.calibration = LiveCalibration(
            cfg.rig, cfg.cameras, cfg.base_frame, dict(cfg.extrinsics), self.tf,
            max_jump_m=cfg.tf_extrinsic_jump_m, on_problem=self._tf_problem,
        )
        self._sources_logged: dict[str, str] = {}
        # ego-body masks: loaded once; a camera whose mask is unusable is left out (counted, logged)
        self._ego_masks, self._mask_load_problems = {}, {}
        for cam, path in cfg.ego_masks:
            try:
                self._ego_masks[cam] = load_ego_mask(path)
            except EgoMaskError as exc:
                self._mask_load_problems[cam] = str(exc)
        self.mask_problems: dict[str, str] = dict(self._mask_load_problems)
        self.sync = FrameSynchronizer(cfg.cameras, cfg.sync_config(), callback=self._on_set)
        self.slot: LatestSlot = LatestSlot()
        self.worker = Worker(self.slot, self._process, self._on_worker_error)

        image_type = CompressedImage if cfg.compressed else Image
        self._info_keys: dict[str, tuple | None] = {}  # camera -> key of its last accepted CameraInfo
        self._subs = []
        # images and CameraInfo: reliability as image_reliability says (input_qos: a reliable
        # subscription loses no camera of a burst, but matches reliable publishers only)
        self._camera_subs = []
        for cam in cfg.cameras:
            for msg_type, topic, where, cb in (
                    (image_type, cfg.image_topic_for(cam), f"{cam} image", self._image_cb(cam)),
                    (CameraInfo, cfg.camera_info_topic_for(cam), f"{cam} camera_info", self._info_cb(cam))):
                self._camera_subs.append(CameraSubscription(
                    self, msg_type, topic, self._contained(where, cb), cfg.image_reliability,
                    on_change=self.get_logger().info,
                    on_incompatible=lambda text, t=topic: self._throttled_warning(f"qos:{t}", text)))
        if cfg.image_reliability == "auto":
            self.create_timer(RECHECK_S, self._contained("qos", self._recheck_qos))
        # the ego pose at each image stamp from odometry, for the temporal fusion (window > 1)
        # and for methods with their own memory (FocusBEV), and to place each camera at its own
        # time (IPM, segipm); none of them: no odometry subscription
        self.fusion = TemporalFusion(cfg.grid, cfg.temporal) if cfg.temporal.window > 1 else None
        method_cls = mapper_class(cfg.mapper.method)
        # each camera at its own time (issue #38): the ego pose at every camera's stamp
        self.placer = RigPlacer(cfg.grid, cfg.time_placement) if cfg.time_placement.enabled else None
        placing = self.placer is not None  # IPM and segipm: a placed rig; learned methods: warped images
        #: a memory (the fusion's or the method's) reads the set's pose, vetted
        self.needs_pose = self.fusion is not None or method_cls.uses_ego_pose
        # odometry vetted and counted before the memories see it; latency kept honest (issue #29)
        self.ego = EgoPoses(cfg, self.tf, self._stopping, self._data_now_ns, self._tf_problem,
                            self._throttled_warning, self._bad_input) if self.needs_pose or placing else None
        self.clock_watch = ClockWatch()
        if self.ego is not None and cfg.pose_source != "tf":
            self._subs.append(self.create_subscription(
                Odometry, cfg.odom_topic, self._contained("odometry", self.ego.on_odometry), 50))
        self._grid_pubs = {c: self.create_publisher(OccupancyGrid, f"{cfg.output_prefix}/{c}", OUTPUT_QOS)
                           for c in self.class_names}
        self._image_pub = self.create_publisher(Image, f"{cfg.output_prefix}/image", OUTPUT_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))
        self.create_timer(min(0.05, cfg.sync_timeout_s / 2), self._contained("synchronizer", self._poll_sync))
        # on the steady clock: the period holds under sim time that loops or stops
        self._diag_timer = self.create_timer(cfg.diagnostics_period_s,
                                             self._contained("diagnostics", self._publish_diagnostics),
                                             clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.worker.start()
        label_text = f", label_map {self.label_map.name} ({self.label_map.encoding})" if cfg.mapper.input_kind == "labels" else ""
        self.get_logger().info(
            f"mapping {list(cfg.cameras)} with {cfg.mapper.method} ({cfg.mapper.input_kind}{label_text}) onto "
            f"{cfg.grid.describe()} in {cfg.base_frame}; publishing {list(self.class_names)} on "
            f"{cfg.output_prefix}/<class>; a set's images within {cfg.sync_slop_s * 1e3:g} ms of each other "
            f"(at most half the cameras' frame period), {cfg.sync_timeout_s * 1e3:g} ms for a late one; "
            "waiting for camera_info and extrinsics"
        )

    # ---------------------------------------------------------------- parameters
    def _runtime_changes(self, params) -> dict:
        return {p.name: p.value for p in params if p.name in RUNTIME_PARAMETERS}

    def _validate_parameters(self, params) -> SetParametersResult:
        """Accept a run-time change only if :class:`NodeConfig` accepts the new values."""
        try:
            with_runtime_parameters(self.cfg, self._runtime_changes(params))
        except NodeConfigError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params) -> None:
        changes = self._runtime_changes(params)
        if not changes:
            return
        old, self.cfg = self.cfg, with_runtime_parameters(self.cfg, changes)
        if self.cfg.diagnostics_period_s != old.diagnostics_period_s:
            self._diag_timer.timer_period_ns = round(self.cfg.diagnostics_period_s * 1e9)
        self.get_logger().info("parameters changed: " + ", ".join(f"{k}={v}" for k, v in changes.items()))

    # ---------------------------------------------------------------- callbacks
    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _use_sim_time(self) -> bool:
        return bool(self.get_parameter("use_sim_time").value)

    def _image_cb(self, cam: str):
        def cb(msg) -> None:
            now = self._now_ns()
            try:
                stamp = header_stamp_ns(msg)
            except BevMapperError as exc:
                self._bad_input(f"{cam}: {exc}", f"{cam}:stamp")
                return
            skew_s = (now - stamp) / 1e9
            self.stats.record_input(time.monotonic(), skew_s)
            if abs(skew_s) > self.cfg.clock_mismatch_s:
                self._throttled_warning("clock", clock_mismatch_text(skew_s, self._use_sim_time(), now))
            try:
                self.sync.add(cam, stamp, msg, now_ns=now)
            except BevMapperError as exc:
                self._bad_input(f"{cam}: {exc}", f"{cam}:stamp")
        return cb

    def _info_cb(self, cam: str):
        def cb(msg) -> None:
            key = camera_info_key(msg)
            if key is not None and key == self._info_keys.get(cam):
                return  # the same calibration again (drivers send it with every image)
            try:
                model = camera_info_to_model(msg)
            except BevMapperError as exc:
                self._bad_input(f"{cam} camera_info rejected: {exc}", f"{cam}:camera_info")
                return
            self._info_keys[cam] = key
            if self.calibration.update_intrinsics(cam, model, str(msg.header.frame_id)):
                self.get_logger().info(f"calibration of {cam}: {model.image_size[0]}x{model.image_size[1]}")
        return cb

    def _recheck_qos(self) -> None:
        for sub in self._camera_subs:
            sub.recheck()

    def _poll_sync(self) -> None:
        self.sync.poll(self._now_ns())

    def _on_set(self, synced) -> None:
        self.slot.put(synced)

    def _data_now_ns(self) -> int:
        """The node's clock moved onto the images' clock (the measured skew taken out)."""
        skew = self.stats.clock_skew_s  # node clock - newest image stamp
        return self._now_ns() - (0 if skew is None else int(skew * 1e9))

    def _reset_memories(self) -> None:
        """Drop the temporal fusion's and the method's memory (a pose they cannot align with)."""
        if self.fusion is not None:
            self.fusion.reset()
        if self.mapper.uses_ego_pose:
            self.mapper.reset()

    def _tf_problem(self, kind: str, message: str) -> None:
        """Count a TF problem of ``kind`` (:data:`TF_ERROR_KINDS`); log it at most every THROTTLE_S per kind."""
        with self.stats.lock:
            self.tf_errors[kind] += 1
            self.tf_last_error = message
        self._throttled_warning(f"tf:{kind}", f"TF ({kind}): {message}")

    def _log_extrinsic_sources(self) -> None:
        """Say where each camera's extrinsic comes from, whenever that changes."""
        sources = self.calibration.sources()
        if sources != self._sources_logged:
            self._sources_logged = sources
            self.get_logger().info(f"extrinsics: {self.calibration.describe_sources()}")

    def _throttled_warning(self, key: str, message: str) -> None:
        """Log a warning ``message`` at most every THROTTLE_S per ``key``."""
        if self._due(key):
            self.get_logger().warning(message)

    def _due(self, key: str) -> bool:
        """True (and remembered) when ``key`` was not logged in the last THROTTLE_S."""
        now = time.monotonic()
        with self.stats.lock:
            last = self._last_logged.get(key)
            if last is not None and now - last < THROTTLE_S:
                return False
            self._last_logged[key] = now
        return True

    def _bad_input(self, message: str, key: str = "") -> None:
        """Count a rejected input; log it at most every THROTTLE_S per ``key`` (camera + problem)."""
        self.stats.record_bad_input(message)
        self._throttled_warning(key or message, message)

    def _contained(self, where: str, fn):
        """``fn`` wrapped so that no exception escapes into the executor (which would end the
        node): anything unexpected is counted under ``errors`` in /diagnostics and logged
        (throttled per place), and the callback's input is skipped.
        """
        def wrapper(*args):
            try:
                return fn(*args)
            except Exception as exc:  # noqa: BLE001 - a callback must never end the node
                if self._stopping.is_set() or not self.context.ok():
                    return None
                self.stats.record_error(f"{where}: {type(exc).__name__}: {exc}")
                self._throttled_error(f"error:{where}", f"{where} failed, input skipped: {type(exc).__name__}: {exc}")
                return None
        return wrapper

    def _throttled_error(self, key: str, message: str) -> None:
        """Log an error ``message`` at most every THROTTLE_S per ``key``."""
        if self._due(key):
            self.get_logger().error(message)

    def _on_worker_error(self, exc: BaseException) -> None:
        if isinstance(exc, _ShuttingDown) or self._stopping.is_set() or not self.context.ok():
            return  # the node stops: the frame is abandoned, nothing to report
        self.stats.record_error(f"{type(exc).__name__}: {exc}")
        self.get_logger().error(f"mapping failed: {type(exc).__name__}: {exc}", throttle_duration_sec=THROTTLE_S)

    # ------------------------------------------------------------------- worker
    def _ensure_mapper(self) -> bool:
        """Build or update the mapper for the current calibration; False while waiting."""
        missing = self.calibration.missing()
        with self.stats.lock:
            self.stats.waiting_for = missing
        if missing:
            with self.stats.lock:
                self.stats.waiting += 1
            self.get_logger().warning("waiting for " + "; ".join(missing), throttle_duration_sec=THROTTLE_S)
            return False
        rig = self._masked(self.calibration.rig())
        if self.mapper is None:
            mapper = create_mapper(rig, self.cfg.grid, self.cfg.mapper)
            for note in mapper.notes:  # e.g. the weights for any rig chosen for a rig its own do not fit
                self.get_logger().warning(note)
            mapper.export_in_background()  # torch maps until the fast backend's model is ready (issue #41)
            self.mapper = mapper
            if self.placer is not None:
                self.placer.set_base(rig)
            if tuple(self.mapper.class_names) != tuple(self.class_names):
                raise BevMapperError(f"the mapper produces {list(self.mapper.class_names)}, "
                                     f"not the announced {list(self.class_names)}")
            self._log_extrinsic_sources()
            self.get_logger().info(
                f"calibration complete (extrinsics from {self.calibration.sources()}); publishing "
                f"{list(self.class_names)} on {self.cfg.output_prefix}/<class>")
        elif self._mapper_version != self.calibration.version:
            self.mapper.set_rig(rig)
            if self.placer is not None:
                self.placer.set_base(rig)
            self._log_extrinsic_sources()
            self.get_logger().info("calibration changed: lookup tables recomputed")
        self._mapper_version = self.calibration.version
        return True

    def _masked(self, rig):
        """``rig`` with the ego masks attached; an unusable mask (missing, not binary, wrong
        size) is logged here and its camera left out of the frames (:meth:`_decode`).
        """
        if not self._ego_masks and not self._mask_load_problems:
            return rig
        rig, problems = attach_ego_masks(rig, self._ego_masks)
        self.mask_problems = {**self._mask_load_problems, **problems}
        for cam, problem in sorted(self.mask_problems.items()):
            self.get_logger().error(f"ego_mask.{cam}: {problem}: the camera's images are left out")
        for note in mask_notes(rig):
            self.get_logger().warning(note)
        return rig

    def _decode(self, cam: str, msg) -> np.ndarray | None:
        """Decode one camera's image; None (counted, logged) when it is unusable."""
        problem = self.mask_problems.get(cam)
        if problem is not None:
            self._bad_input(f"{cam}: image left out: ego_mask.{cam}: {problem}", f"{cam}:ego_mask")
            return None
        try:
            w, h = self.mapper.rig[cam].model.image_size
            # the calibrated size is checked before decoding (a compressed image's header first);
            # label images leave the adapters in Label ids (the label map applied once)
            labels = self.cfg.mapper.input_kind == "labels"
            if self.cfg.compressed:
                img = (compressed_to_labels(msg, (w, h), label_map=self.label_map, check_format=True) if labels
                       else compressed_to_rgb(msg, expected_size=(w, h), check_format=True))
            elif labels:
                img = image_to_labels(msg, expected_size=(w, h), label_map=self.label_map)
            else:
                img = image_to_rgb(msg, expected_size=(w, h))
            if img.shape[:2] != (h, w):
                raise BevMapperError(f"image is {img.shape[1]}x{img.shape[0]}, camera_info says {w}x{h}")
            return img
        except BevMapperError as exc:
            self._bad_input(f"{cam}: {exc}", f"{cam}:image")
            return None

    def _publish(self, pub, msg) -> None:
        """Publish unless the node stops (then :class:`_ShuttingDown`: the frame is abandoned)."""
        if self._stopping.is_set() or not self.context.ok():
            raise _ShuttingDown()
        try:
            pub.publish(msg)
        except Exception:
            if self._stopping.is_set() or not self.context.ok():
                raise _ShuttingDown() from None
            raise

    def _process(self, synced) -> None:
        if self._stopping.is_set() or not self._ensure_mapper():
            return
        t0 = time.perf_counter()
        images = {}
        for cam in synced.valid_names:
            img = self._decode(cam, synced.messages[cam])
            if img is not None:
                images[cam] = img
        missing = [c for c in self.cfg.cameras if c not in images]
        if not images:
            return
        stamp = synced.stamp_ns
        if missing:
            self._throttled_warning("missing", f"mapping a set without cameras {missing} ({synced.reason}); "
                                               "/diagnostics counts them per camera (missing_by_camera)")
        images = self._place(synced, images)
        pose = self.ego.at(stamp) if self.needs_pose else None
        if self.needs_pose:  # vetted: a pose the memories cannot align with resets them
            verdict = self.ego.watch.vet(stamp, pose)
            if verdict.reset and verdict.pose is not None:
                self._reset_memories()
                self._throttled_warning("temporal", verdict.note)
            pose = verdict.pose
        with self.stats.lock:
            self.stats.mapping_since_s = time.monotonic()
        try:
            pred = self.mapper.map(images, ego_pose=pose, stamp_ns=stamp)
        finally:
            with self.stats.lock:
                self.stats.mapping_since_s = None
        self._note_backend()
        if self.mapper.uses_ego_pose:  # the method's own memory
            self.ego.watch.count_memory(pred.note, pose)
            with self.stats.lock:
                self.stats.temporal_frames, self.stats.temporal_note = pred.frames, pred.note
            if pred.note:
                self._throttled_warning("temporal", pred.note)
        if self.fusion is not None:
            fused = self.fusion.update(pred, stamp, pose)
            pred = fused.prediction
            self.ego.watch.count_memory(fused.note, pose)
            with self.stats.lock:
                self.stats.temporal_frames, self.stats.temporal_note = fused.frames, fused.note
            if fused.note:
                self._throttled_warning("temporal", fused.note)
        if self.needs_pose and verdict.note and verdict.pose is not None:  # the reset it asked for
            with self.stats.lock:
                self.stats.temporal_note = self.stats.temporal_note or verdict.note
        for ci, name in enumerate(self.class_names):
            msg = make_occupancy_grid(self.factory, self.cfg.grid, pred.probs[ci], pred.known,
                                      stamp, self.cfg.base_frame)
            self._publish(self._grid_pubs[name], msg)
        picture = bev_picture(self.cfg.grid, pred.probs, self.mapper.classes, pred.known)
        self._publish(self._image_pub, make_image(self.factory, picture, "rgb8", stamp, self.cfg.base_frame))
        processing_ms = (time.perf_counter() - t0) * 1000.0
        jumps = self.clock_watch.jumps_back
        latency_ms = self.clock_watch.latency_ms(self._now_ns(), stamp, processing_ms, self.cfg.clock_mismatch_s)
        if self.clock_watch.jumps_back > jumps:
            self._throttled_warning("clock_back", f"the node's clock jumped back {self.clock_watch.last_jump_s:.1f} s "
                                                  "(a bag looping with /clock?): that set's latency is not measured")
        self.stats.record_mapped(time.monotonic(), processing_ms, latency_ms, missing)

    def _place(self, synced, images):
        """Place each camera of the set with the ego pose of its own stamp (IPM's and segipm's
        rig follows; a learned method's moved images are warped), counted in /diagnostics; what
        holds for the whole run is said once, a set's problems throttled. Returns the images to map.
        """
        if self.placer is None:
            return images
        stamps = {c: synced.stamps.get(c) for c in images}
        lookup = self.ego.lookup if self.ego is not None else (lambda stamp: None)
        _, notes = self.placer.place(self.mapper, stamps, synced.stamp_ns, lookup)
        for key, text in notes:
            if key.startswith("placement:"):
                self.get_logger().info(f"time placement: {text}")
            else:
                self._throttled_warning(key, f"time placement: {text}")
        return self.placer.warp(images)

    def _note_backend(self) -> None:
        """Say what runs the model whenever that changes (torch while the fast backend's model is
        exported, then that backend), in the log and in /diagnostics (``backend``).
        """
        state = self.mapper.backend_state
        with self.stats.lock:
            old, self.stats.backend = self.stats.backend, state
        if state == old or not state:
            return
        if state.startswith("torch (until"):
            self.get_logger().info(f"inference: mapping with {state}: its export runs in the background "
                                   "(once per weights and calibration; later starts reuse the cache)")
        elif state.startswith("torch ("):
            self.get_logger().warning(f"inference: {state}; mapping goes on with torch")
        elif old.startswith("torch (until"):
            self.get_logger().info(f"inference: switched from torch to {state}")
        else:
            self.get_logger().info(f"inference: {state}")

    # -------------------------------------------------------------- diagnostics
    def _publish_diagnostics(self) -> None:
        s = self.sync.stats
        window_ms = self.sync.window_ns / 1e6
        with self.stats.lock:
            new_splits, self.stats.split_sets, self.stats.sync_window_ms = s.split - self.stats.split_sets, s.split, window_ms
        if new_splits > 0:
            self._throttled_warning("split", f"{s.split} frame(s) so far were split into two partial sets: their cameras' "
                                             f"stamps spread wider than the {window_ms:.0f} ms window (raise sync_slop_s)")
        dropped = self.slot.dropped + s.late + s.overflow + s.dropped_on_reset
        level, text, values = diagnostic_values(self.stats, time.monotonic(), self.cfg, dropped)
        values["use_sim_time"] = str(self._use_sim_time()).lower()
        values["clock_jumps_back"] = self.clock_watch.jumps_back
        if self.ego is not None:
            values.update(self.ego.watch.values())
        values["time_placement"] = self.cfg.time_placement.mode
        if self.placer is not None:
            values.update(self.placer.values())
        level, text = self._tf_diagnostics(values, level, text)
        status = DiagnosticStatus(level=bytes([level]), name=f"{self.get_name()}: bev mapper",
                                  message=text, hardware_id=self.calibration.rig_name)
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(msg)

    def _tf_diagnostics(self, values: dict, level: int, text: str) -> tuple[int, str]:
        """TF's key/values (which extrinsics, which pose, the error counters); WARN when TF
        problems arrived since the last report.
        """
        values["tf"] = "off" if not self.cfg.use_tf else ("tf2_ros" if self.tf is not None else "not importable")
        values["extrinsics_source"] = ",".join(f"{c}:{s}" for c, s in self.calibration.sources().items())
        values["pose_source"] = self.ego.used if self.ego is not None else ""
        with self.stats.lock:
            for kind, n in self.tf_errors.items():
                values[f"tf_errors_{kind}"] = n
            values["tf_last_error"] = self.tf_last_error
            total, new = sum(self.tf_errors.values()), sum(self.tf_errors.values()) - self._tf_errors_reported
            self._tf_errors_reported = total
        if new > 0:
            note = f"{new} TF problem(s) since the last report: {self.tf_last_error}"
            text = note if level == 0 else f"{text}; {note}"
            level = max(level, WARN)
        return level, text

    def stop(self) -> None:
        """Stop the worker: its current frame is finished or abandoned, quietly; an export under
        way is stopped (its child process and partial file go).
        """
        self._stopping.set()
        cancel_exports()  # no torch import: an IPM node stays torch-free
        self.worker.stop()
        if self.mapper is not None:
            self.mapper.close()

    def destroy_node(self) -> None:
        """Stop the worker before the node goes away."""
        self.stop()
        super().destroy_node()


class _StopSignals:
    """SIGINT and SIGTERM set :attr:`event` (no KeyboardInterrupt, no rcl shutdown under the
    worker's feet): the node then stops in order, worker first, and exits 0.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.event = threading.Event()
        for sig in self.SIGNALS:
            signal.signal(sig, self._handler)
        if _EARLY_STOP.is_set():  # one arrived while the modules were imported
            self.event.set()

    def _handler(self, signum, frame) -> None:
        self.event.set()


def _spin(node: Node, stop: threading.Event) -> None:
    """Spin ``node`` until ``stop`` is set or its context shuts down."""
    executor = SingleThreadedExecutor(context=node.context)
    executor.add_node(node)
    try:
        while not stop.is_set() and node.context.ok():
            executor.spin_once(timeout_sec=0.1)
    except ExternalShutdownException:
        pass
    finally:
        executor.remove_node(node)
        executor.shutdown(timeout_sec=1.0)


def main(args=None) -> int:
    """Entry point of ``mapper_node``: ``--help`` prints the parameters; bad parameters or
    command line exit 2 with ``error: ...``; SIGINT / SIGTERM exit 0.
    """
    argv = list(sys.argv if args is None else args)
    if wants_help(argv):
        sys.stdout.write(parameter_help())
        return 0
    signals = _StopSignals()  # from here on, a signal means: stop cleanly
    try:
        check_command_line(argv)
        if signals.event.is_set():
            return 0
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except CommandLineError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except Exception as exc:  # noqa: BLE001 - rcl's argument errors (RCLError)
        print(f"error: {rcl_message(exc)}", file=sys.stderr)
        return 2
    try:
        node = MapperNode()
    except (BevMapperError, ParameterException, NameValidationException) as exc:
        print(f"error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    except BaseException:
        rclpy.try_shutdown()
        raise
    try:
        _spin(node, signals.event)
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
