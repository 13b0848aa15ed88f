"""The BEV mapper node: synchronized camera images in, per-class OccupancyGrids out.

    ros2 run bev_mapper_ros mapper_node --ros-args --params-file <share>/config/surround6.yaml

Callbacks only convert stamps and feed the synchronizer; complete (or timed-out partial) sets
go to a one-slot mailbox; a worker thread decodes, maps and publishes. Bad input is logged
(throttled), counted in ``/diagnostics`` and skipped: the node keeps running.
"""

from __future__ import annotations

import sys
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nav_msgs.msg import OccupancyGrid
from rclpy.exceptions import NameValidationException, ParameterException
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

from bev_mapper_core.classes import bev_picture
from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.mapper import create_mapper, preflight
from msg_adapters import (
    FrameSynchronizer,
    RclpyFactory,
    camera_info_to_model,
    compressed_to_array,
    header_stamp_ns,
    image_to_labels,
    image_to_rgb,
    make_image,
    make_occupancy_grid,
)

from .calibration import LiveCalibration
from .config import node_config_from_params
from .params import declare_parameters, read_parameters
from .stats import NodeStats, diagnostic_values
from .worker import LatestSlot, Worker

THROTTLE_S = 5.0


def _tf_lookup_for(node: Node):
    """A TF lookup callable when tf2_ros is importable (a ROS install), else None."""
    try:
        from tf2_ros import Buffer, TransformListener  # noqa: PLC0415 - optional dependency
    except ImportError:
        return None
    buffer = Buffer()
    node._tf_listener = TransformListener(buffer, node)  # keep it alive with the node

    def lookup(target: str, source: str):
        from msg_adapters import transform_stamped_to_matrix  # noqa: PLC0415

        try:
            ts = buffer.lookup_transform(target, source, rclpy.time.Time())
        except Exception:  # noqa: BLE001 - not yet available
            return None
        return transform_stamped_to_matrix(ts).matrix

    return lookup


class MapperNode(Node):
    """Subscribes to N cameras, maps synchronized sets to BEV, publishes grids + diagnostics."""

    def __init__(self, **kwargs) -> None:
        super().__init__("mapper_node", **kwargs)
        declare_parameters(self)
        self.cfg = node_config_from_params(read_parameters(self))  # raises on bad parameters
        cfg = self.cfg
        preflight(cfg.mapper, cfg.rig, cfg.grid, cfg.cameras)  # e.g. missing weights: fail now
        self.factory = RclpyFactory()
        self.stats = NodeStats()
        self._last_logged: dict[str, float] = {}
        self.mapper = None
        self._mapper_version = -1
        use_tf = cfg.use_tf
        self.calibration = LiveCalibration(
            cfg.rig, cfg.cameras, cfg.base_frame,
            dict(cfg.extrinsics), _tf_lookup_for(self) if use_tf else None,
        )
        self.sync = FrameSynchronizer(cfg.cameras, cfg.sync_config(), callback=self._on_set)
        self.slot: LatestSlot = LatestSlot()
        self.worker = Worker(self.slot, self._process, self._on_worker_error)

        image_type = CompressedImage if cfg.compressed else Image
        self._subs = []
        for cam in cfg.cameras:
            self._subs.append(self.create_subscription(
                image_type, cfg.image_topic_for(cam), self._image_cb(cam), qos_profile_sensor_data))
            self._subs.append(self.create_subscription(
                CameraInfo, cfg.camera_info_topic_for(cam), self._info_cb(cam), qos_profile_sensor_data))
        self.classes = None  # set with the mapper
        self._grid_pubs = {}
        self._image_pub = self.create_publisher(Image, f"{cfg.output_prefix}/image", QoSProfile(depth=2))
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", QoSProfile(depth=10))
        self.create_timer(min(0.05, cfg.sync_timeout_s / 2), self._poll_sync)
        self.create_timer(cfg.diagnostics_period_s, self._publish_diagnostics)
        self.worker.start()
        self.get_logger().info(
            f"mapping {list(cfg.cameras)} with {cfg.mapper.method} ({cfg.mapper.input_kind}) onto "
            f"{cfg.grid.describe()} in {cfg.base_frame}; waiting for camera_info and extrinsics"
        )

    # ---------------------------------------------------------------- callbacks
    def _now_ns(self) -> int:
        return self.get_clock().now().nanoseconds

    def _image_cb(self, cam: str):
        def cb(msg) -> None:
            try:
                self.sync.add(cam, header_stamp_ns(msg), msg, now_ns=self._now_ns())
            except BevMapperError as exc:
                self._bad_input(f"{cam}: {exc}", f"{cam}:stamp")
        return cb

    def _info_cb(self, cam: str):
        def cb(msg) -> None:
            try:
                model = camera_info_to_model(msg)
            except BevMapperError as exc:
                self._bad_input(f"{cam} camera_info rejected: {exc}", f"{cam}:camera_info")
                return
            if self.calibration.update_intrinsics(cam, model, str(msg.header.frame_id)):
                self.get_logger().info(f"calibration of {cam}: {model.image_size[0]}x{model.image_size[1]}")
        return cb

    def _poll_sync(self) -> None:
        self.sync.poll(self._now_ns())

    def _on_set(self, synced) -> None:
        self.slot.put(synced)

    def _bad_input(self, message: str, key: str = "") -> None:
        """Count a rejected input; log it at most every THROTTLE_S per ``key`` (camera + problem)."""
        self.stats.record_bad_input(message)
        now = time.monotonic()
        key = key or message
        with self.stats.lock:
            last = self._last_logged.get(key)
            if last is not None and now - last < THROTTLE_S:
                return
            self._last_logged[key] = now
        self.get_logger().warning(message)

    def _on_worker_error(self, exc: BaseException) -> None:
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
        rig = self.calibration.rig()
        if self.mapper is None:
            self.mapper = create_mapper(rig, self.cfg.grid, self.cfg.mapper)
            self.classes = self.mapper.classes
            for c in self.classes:
                self._grid_pubs[c.name] = self.create_publisher(
                    OccupancyGrid, f"{self.cfg.output_prefix}/{c.name}", QoSProfile(depth=2))
            self.get_logger().info(
                f"calibration complete (extrinsics from {self.calibration.sources()}); publishing "
                f"{[c.name for c in self.classes]} on {self.cfg.output_prefix}/<class>")
        elif self._mapper_version != self.calibration.version:
            self.mapper.set_rig(rig)
            self.get_logger().info("calibration changed: lookup tables recomputed")
        self._mapper_version = self.calibration.version
        return True

    def _decode(self, cam: str, msg) -> np.ndarray | None:
        """Decode one camera's image; None (counted, logged) when it is unusable."""
        try:
            if self.cfg.compressed:
                img = compressed_to_array(msg)
                if self.cfg.mapper.input_kind == "labels" and img.ndim == 3:
                    raise BevMapperError("compressed label image must be single-channel")
            elif self.cfg.mapper.input_kind == "labels":
                img = image_to_labels(msg)
            else:
                img = image_to_rgb(msg)
            w, h = self.mapper.rig[cam].model.image_size
            if img.shape[:2] != (h, w):
                raise BevMapperError(f"image is {img.shape[1]}x{img.shape[0]}, camera_info says {w}x{h}")
            return img
        except BevMapperError as exc:
            self._bad_input(f"{cam}: {exc}", f"{cam}:image")
            return None

    def _process(self, synced) -> None:
        if not self._ensure_mapper():
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
        pred = self.mapper.map(images, stamp_ns=synced.stamp_ns)
        stamp = synced.stamp_ns
        for ci, c in enumerate(self.classes):
            msg = make_occupancy_grid(self.factory, self.cfg.grid, pred.probs[ci], pred.known,
                                      stamp, self.cfg.base_frame)
            self._grid_pubs[c.name].publish(msg)
        picture = bev_picture(self.cfg.grid, pred.probs, self.classes, pred.known)
        self._image_pub.publish(make_image(self.factory, picture, "rgb8", stamp, self.cfg.base_frame))
        processing_ms = (time.perf_counter() - t0) * 1000.0
        latency_ms = (self._now_ns() - stamp) / 1e6
        self.stats.record_mapped(time.monotonic(), processing_ms, latency_ms, missing)

    # -------------------------------------------------------------- diagnostics
    def _publish_diagnostics(self) -> None:
        s = self.sync.stats
        dropped = self.slot.dropped + s.late + s.overflow + s.dropped_on_reset
        level, text, values = diagnostic_values(
            self.stats, time.monotonic(), max(self.cfg.diagnostics_period_s, 1.0), dropped)
        status = DiagnosticStatus(level=bytes([level]), name=f"{self.get_name()}: bev mapper",
                                  message=text, hardware_id=self.calibration.rig_name)
        status.values = [KeyValue(key=k, value=str(v)) for k, v in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self._diag_pub.publish(msg)

    def destroy_node(self) -> None:
        """Stop the worker before the node goes away."""
        self.worker.stop()
        super().destroy_node()


def main(args=None) -> int:
    """Entry point of ``mapper_node``: bad parameters exit 2 with ``error: ...``."""
    rclpy.init(args=args)
    node = None
    try:
        node = MapperNode()
    except (BevMapperError, ParameterException, NameValidationException) as exc:
        print(f"error: {exc}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
