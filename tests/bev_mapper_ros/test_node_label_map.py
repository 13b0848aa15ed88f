"""The mapper node with ``label_map``, over real DDS: a stream of Cityscapes ids (mono8) or of
Cam2BEV palette images (rgb8) gives the OccupancyGrids of the equivalent native-id stream, and a
label image of the wrong encoding is counted and skipped while the node keeps mapping."""

from __future__ import annotations

import time

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from label_map_helpers import equivalent_native, to_upstream
from nav_msgs.msg import OccupancyGrid  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from ros_helpers import REPO, core_map_as_received, rclpy, spin_until, start_process, stop_process
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig, RigCamera, preset_rig
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.synth import SynthConfig, generate_drive
from bev_mapper_ros.config import node_config_from_params
from msg_adapters import RclpyFactory, camera_info_to_model, make_camera_info, make_image

GRID = BevGrid(x_min=-20, x_max=20, y_min=-10, y_max=10, resolution=0.25)
CLASSES = ("drivable", "sidewalk", "vehicle")
PARAMS_FILE = REPO / "config" / "surround6.yaml"
BAD_CAM = "back"


def node_view_of_rig(rig: Rig) -> Rig:
    """The rig as the node sees it: intrinsics through CameraInfo, extrinsics from the YAML."""
    params = yaml.safe_load(PARAMS_FILE.read_text())["/**"]["ros__parameters"]
    cfg = node_config_from_params({"cameras": params["cameras"],
                                   **{f"extrinsics.{k}": v for k, v in params["extrinsics"].items()}})
    factory = RclpyFactory()
    return Rig(rig.name, tuple(
        RigCamera(c.name, camera_info_to_model(make_camera_info(factory, c.model, 0, c.frame_id)),
                  cfg.extrinsic(c.name), c.frame_id) for c in rig.cameras))


@pytest.fixture(scope="module")
def drive():
    rig = preset_rig("surround6").scaled(0.5)
    return rig, list(generate_drive(rig, GRID, SynthConfig(frames=3, seed=11)))


class Driver:
    """Label images and CameraInfo for every camera; grid and diagnostics subscribers."""

    def __init__(self, node, rig: Rig, log):
        self.node, self.rig, self.log, self.factory = node, rig, log, RclpyFactory()
        self.pubs = {c: node.create_publisher(Image, f"/cameras/{c}/labels", qos_profile_sensor_data) for c in rig.names}
        self.infos = {c: node.create_publisher(CameraInfo, f"/cameras/{c}/camera_info", 10) for c in rig.names}
        self.grids: dict[str, dict[int, OccupancyGrid]] = {c: {} for c in CLASSES}
        self.diags: list[DiagnosticArray] = []
        for c in CLASSES:
            node.create_subscription(OccupancyGrid, f"/bev/{c}", self._grid_cb(c), 10)
        node.create_subscription(DiagnosticArray, "/diagnostics", self.diags.append, 10)
        assert spin_until(node, lambda: all(p.get_subscription_count() > 0 for p in self.pubs.values()), 30.0), \
            log.read_text()

    def _grid_cb(self, cls):
        def cb(msg):
            self.grids[cls][msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec] = msg
        return cb

    def calibrate(self, stamp_ns, timeout=30.0) -> bool:
        """CameraInfo of every camera, again every 50 ms until the node logged each (best effort)."""
        want = [f"calibration of {c}:" for c in self.rig.names]
        end = time.monotonic() + timeout
        while True:
            for cam in self.rig.cameras:
                self.infos[cam.name].publish(make_camera_info(self.factory, cam.model, stamp_ns, cam.frame_id))
            if all(w in self.log.read_text() for w in want):
                return True
            if time.monotonic() > end:
                return False
            spin_until(self.node, lambda: False, 0.05)

    def send(self, images: dict, stamp_ns: int) -> None:
        """``images``: camera -> (array, encoding)."""
        for name, (arr, enc) in images.items():
            self.pubs[name].publish(make_image(self.factory, arr, enc, stamp_ns, self.rig[name].frame_id))
            spin_until(self.node, lambda: False, 0.01)  # paced like separate drivers

    def wait_for(self, stamp_ns, timeout=20.0) -> bool:
        return spin_until(self.node, lambda: all(stamp_ns in self.grids[c] for c in CLASSES), timeout)

    def diag(self) -> dict:
        return {kv.key: kv.value for kv in self.diags[-1].status[0].values} if self.diags else {}


@pytest.mark.parametrize("scheme", ["cityscapes_ids", "cam2bev"])
def test_node_maps_upstream_label_streams_like_native(scheme, drive, tmp_path, ros_domain):
    rig, frames = drive
    log = tmp_path / "node.log"
    proc = start_process([
        "bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS_FILE), "-p", "method:=ipm",
        "-p", f"label_map:={scheme}", "-p", "grid.x_min:=-20.0", "-p", "grid.x_max:=20.0",
        "-p", "grid.y_min:=-10.0", "-p", "grid.y_max:=10.0", "-p", "grid.resolution:=0.25",
        "-p", f"classes:={list(CLASSES)}".replace("'", '"'), "-p", "diagnostics_period_s:=0.3",
    ], ros_domain, log)
    enc, wrong = ("rgb8", "mono8") if scheme == "cam2bev" else ("mono8", "rgb8")
    rclpy.init(domain_id=ros_domain)
    node = rclpy.create_node("bev_label_map_driver")
    try:
        d = Driver(node, rig, log)
        for f in frames:
            assert d.calibrate(f.stamp_ns), log.read_text()
            images = {n: (to_upstream(c.labels, scheme), enc) for n, c in f.cameras.items()}
            if f.index == 1:  # one camera in the encoding the label map does not take
                bad = f.cameras[BAD_CAM]
                images[BAD_CAM] = (bad.labels, "mono8") if wrong == "mono8" else (bad.rgb, "rgb8")
            d.send(images, f.stamp_ns)
            assert d.wait_for(f.stamp_ns), f"no grids for frame {f.index}:\n{log.read_text()}"
        assert spin_until(node, lambda: int(d.diag().get("mapped_sets", 0)) >= 3
                          and int(d.diag().get("bad_input", 0)) >= 1, 5.0), d.diag()
        assert proc.poll() is None
    finally:
        node.destroy_node()
        rclpy.shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    text = log.read_text()
    assert f"label_map {scheme} ({enc})" in text
    assert f"for label_map '{scheme}', got '{wrong}'" in text  # the refusal, logged (throttled)
    # the grids are the core's on the equivalent native labels (what a Cityscapes-style segmenter
    # can say: markings as road, curbs as sidewalk) of the cameras the node had
    expected = IpmMapper(node_view_of_rig(rig), GRID, MapperConfig(classes=CLASSES))
    complete = 0
    for f in frames:
        native = {n: equivalent_native(c.labels) for n, c in f.cameras.items() if not (f.index == 1 and n == BAD_CAM)}
        pred, lost = core_map_as_received(expected, GRID, native, d.grids[CLASSES[0]][f.stamp_ns].data)
        complete += not lost
        for ci, c in enumerate(CLASSES):
            np.testing.assert_array_equal(np.asarray(d.grids[c][f.stamp_ns].data, np.int8),
                                          GRID.to_occupancy(pred.probs[ci], pred.known), err_msg=f"{c} frame {f.index}")
    assert complete >= 1, "every set lost a camera"
    first = frames[0].stamp_ns
    assert (np.asarray(d.grids["drivable"][first].data) == 100).sum() > 500
    assert (np.asarray(d.grids["sidewalk"][first].data) == 100).sum() > 50
