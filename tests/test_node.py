"""The mapper node in its own process, driven over real DDS by rclpy publishers in this one."""

from __future__ import annotations


import numpy as np
import pytest
import yaml

from ros_helpers import REPO, core_map_as_received, free_domain_id, rclpy, spin_until, start_process, stop_process

from bev_mapper_core.grid import BevGrid
from bev_mapper_core.ipm import IpmMapper
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.rig import Rig, RigCamera, preset_rig
from bev_mapper_core.synth import SynthConfig, generate_drive
from bev_mapper_ros.config import node_config_from_params
from msg_adapters import RclpyFactory, camera_info_to_model, make_camera_info, make_image

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import OccupancyGrid  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

GRID = BevGrid(x_min=-20, x_max=20, y_min=-10, y_max=10, resolution=0.25)
CLASSES = ("drivable", "ped_crossing", "vehicle")
PARAMS_FILE = REPO / "config" / "surround6.yaml"


def node_view_of_rig(rig: Rig) -> Rig:
    """The rig exactly as the node sees it: intrinsics via CameraInfo, extrinsics via the YAML."""
    params = yaml.safe_load(PARAMS_FILE.read_text())["/**"]["ros__parameters"]
    flat = {"cameras": params["cameras"]}
    flat.update({f"extrinsics.{k}": v for k, v in params["extrinsics"].items()})
    cfg = node_config_from_params(flat)
    factory = RclpyFactory()
    cams = []
    for cam in rig.cameras:
        model = camera_info_to_model(make_camera_info(factory, cam.model, 0, cam.frame_id))
        cams.append(RigCamera(cam.name, model, cfg.extrinsic(cam.name), cam.frame_id))
    return Rig(rig.name, tuple(cams))


@pytest.fixture(scope="module")
def drive():
    rig = preset_rig("surround6").scaled(0.5)
    return rig, list(generate_drive(rig, GRID, SynthConfig(frames=3, seed=11)))


@pytest.fixture()
def ros(tmp_path, request):
    """A running mapper_node process and a test node on a private domain.

    Parametrize indirectly with the node's ``sync_timeout_s`` (default 5 s: on a loaded machine a
    short timeout maps a set without an image that is merely slow).
    """
    timeout_s = getattr(request, "param", 5.0)
    domain = free_domain_id()
    args = [
        "bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS_FILE), "-p", "method:=ipm",
        "-p", "grid.x_min:=-20.0", "-p", "grid.x_max:=20.0", "-p", "grid.y_min:=-10.0",
        "-p", "grid.y_max:=10.0", "-p", "grid.resolution:=0.25",
        "-p", f"classes:={list(CLASSES)}".replace("'", '"'),
        "-p", "diagnostics_period_s:=0.3", "-p", f"sync_timeout_s:={timeout_s}",
    ]
    proc = start_process(args, domain, tmp_path / "node.log")
    rclpy.init(domain_id=domain)
    node = rclpy.create_node("bev_test_driver")
    try:
        yield proc, node, tmp_path / "node.log"
    finally:
        node.destroy_node()
        rclpy.shutdown()
        code = stop_process(proc)
        assert code in (0, -2), (tmp_path / "node.log").read_text()


class Driver:
    """Publishers for every camera's labels + CameraInfo and subscribers to the outputs."""

    def __init__(self, node, rig: Rig):
        self.node, self.rig, self.factory = node, rig, RclpyFactory()
        self.labels = {c: node.create_publisher(Image, f"/cameras/{c}/labels", qos_profile_sensor_data)
                       for c in rig.names}
        self.infos = {c: node.create_publisher(CameraInfo, f"/cameras/{c}/camera_info", 10)
                      for c in rig.names}
        self.grids: dict[str, dict[int, OccupancyGrid]] = {c: {} for c in CLASSES}
        self.diags: list[DiagnosticArray] = []
        for c in CLASSES:
            node.create_subscription(OccupancyGrid, f"/bev/{c}", self._grid_cb(c), 10)
        node.create_subscription(DiagnosticArray, "/diagnostics", self.diags.append, 10)
        assert spin_until(node, lambda: all(p.get_subscription_count() > 0 for p in self.labels.values()), 30.0), \
            "mapper_node never subscribed to the label topics"

    def _grid_cb(self, cls):
        def cb(msg):
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            self.grids[cls][stamp] = msg
        return cb

    def send_info(self, stamp_ns, broken: str | None = None):
        for cam in self.rig.cameras:
            msg = make_camera_info(self.factory, cam.model, stamp_ns, cam.frame_id)
            if broken == cam.name:
                msg.k = [0.0] * 9
            self.infos[cam.name].publish(msg)

    def send_frame(self, frame, override: dict | None = None):
        for name, cf in frame.cameras.items():
            msg = (override or {}).get(name) or make_image(self.factory, cf.labels, "mono8", frame.stamp_ns,
                                                            self.rig[name].frame_id)
            self.labels[name].publish(msg)
            spin_until(self.node, lambda: False, 0.01)  # paced like separate drivers: less loss under load

    def wait_for(self, stamp_ns, timeout=20.0):
        return spin_until(self.node, lambda: all(stamp_ns in self.grids[c] for c in CLASSES), timeout)

    def diag_values(self):
        if not self.diags:
            return {}
        return {kv.key: kv.value for kv in self.diags[-1].status[0].values}


def test_core_map_as_received_finds_the_lost_camera(drive):
    """The comparison helper names the camera a node's grid lacked, and only that one."""
    rig, frames = drive
    mapper = IpmMapper(node_view_of_rig(rig), GRID, MapperConfig(classes=CLASSES))
    images = {n: c.labels for n, c in frames[0].cameras.items()}
    partial = mapper.map({n: im for n, im in images.items() if n != "back_left"})
    data = GRID.to_occupancy(partial.probs[0], partial.known)
    pred, lost = core_map_as_received(mapper, GRID, images, data)
    assert lost == ("back_left",)
    np.testing.assert_array_equal(pred.probs, partial.probs)
    full = mapper.map(images)
    assert core_map_as_received(mapper, GRID, images, GRID.to_occupancy(full.probs[0], full.known))[1] == ()
    with pytest.raises(AssertionError, match="match no set of cameras"):
        core_map_as_received(mapper, GRID, images, np.full(GRID.width * GRID.height, -1, np.int8))


def test_node_publishes_the_cores_grids(ros, drive):
    proc, node, log = ros
    rig, frames = drive
    d = Driver(node, rig)
    expected_mapper = IpmMapper(node_view_of_rig(rig), GRID, MapperConfig(classes=CLASSES))
    complete = 0
    for f in frames:
        for _ in range(3):
            d.send_info(f.stamp_ns)
            spin_until(node, lambda: False, 0.05)
        d.send_frame(f)
        assert d.wait_for(f.stamp_ns), f"no grids for frame {f.index}:\n{log.read_text()}"
    for f in frames:
        pred, lost = core_map_as_received(expected_mapper, GRID, {n: c.labels for n, c in f.cameras.items()},
                                          d.grids[CLASSES[0]][f.stamp_ns].data)
        complete += not lost
        for ci, c in enumerate(CLASSES):
            msg = d.grids[c][f.stamp_ns]
            assert msg.header.frame_id == "base_link"
            assert (msg.info.width, msg.info.height) == (GRID.width, GRID.height)
            assert msg.info.resolution == pytest.approx(GRID.resolution)
            assert (msg.info.origin.position.x, msg.info.origin.position.y) == GRID.origin_xy
            got = np.asarray(msg.data, dtype=np.int8)
            want = GRID.to_occupancy(pred.probs[ci], pred.known)
            np.testing.assert_array_equal(got, want, err_msg=f"class {c} frame {f.index}")
    assert complete >= 1, "every set lost a camera"
    # The drive has road in view: the comparison is not between two empty maps.
    assert (np.asarray(d.grids["drivable"][frames[0].stamp_ns].data) == 100).sum() > 500


@pytest.mark.parametrize("ros", [1.0], indirect=True)  # rejected cameras make partial sets: wait 1 s
def test_node_survives_broken_input(ros, drive):
    proc, node, log = ros
    rig, frames = drive
    d = Driver(node, rig)
    f0, f1, f2 = frames
    for _ in range(3):
        d.send_info(f0.stamp_ns)
        spin_until(node, lambda: False, 0.05)
    d.send_frame(f0)
    assert d.wait_for(f0.stamp_ns), log.read_text()
    front = rig["front"]
    bad = {
        # wrong encoding on a label topic, and a size that disagrees with camera_info
        "front": make_image(d.factory, f1.cameras["front"].rgb, "rgb8", f1.stamp_ns, front.frame_id),
        "back": make_image(d.factory, f1.cameras["back"].labels[:50, :60].copy(), "mono8", f1.stamp_ns,
                           rig["back"].frame_id),
    }
    # Truncated data: the adapter must refuse it, not crash the node.
    trunc = make_image(d.factory, f1.cameras["front_right"].labels, "mono8", f1.stamp_ns,
                       rig["front_right"].frame_id)
    trunc.data = trunc.data[:100]
    bad["front_right"] = trunc
    d.send_info(f1.stamp_ns, broken="front_left")  # uncalibrated CameraInfo: rejected, old one kept
    d.send_frame(f1, override=bad)
    assert d.wait_for(f1.stamp_ns), "a frame with some broken cameras must still be mapped"
    d.send_info(f2.stamp_ns)
    d.send_frame(f2)
    assert d.wait_for(f2.stamp_ns), f"node stopped publishing after bad input:\n{log.read_text()}"
    assert proc.poll() is None
    # Four rejections: rgb8 on a label topic, wrong size, uncalibrated CameraInfo, truncated data.
    # (The log is throttled; the counters are not.)
    assert spin_until(node, lambda: int(d.diag_values().get("bad_input", 0)) >= 4, 5.0), d.diag_values()
    text = log.read_text()  # one line per camera and problem, throttled per problem
    assert "uncalibrated" in text and "'rgb8'" in text and "expected 200x112" in text  # size from camera_info
    assert int(d.diag_values()["sets_with_missing_cameras"]) >= 1
    # Frame 1 was mapped without its broken cameras: cells only the front camera sees are unknown.
    occ = np.asarray(d.grids["drivable"][f1.stamp_ns].data)
    r, c = GRID.metric_to_cell(15.0, 0.0)
    assert occ[r * GRID.width + c] == -1
    assert np.asarray(d.grids["drivable"][f2.stamp_ns].data)[r * GRID.width + c] != -1


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["-p", "grid.resolution:=0.7"], "not a whole number"),
        (["-p", "cameras:=[front,front]"], "distinct"),
        (["-p", "method:=bimapper", "-p", "weights:=/nonexistent.safetensors"], "does not exist"),
        (["-p", "method:=ipm", "-p", "input_kind:=rgb"], "label images only"),
        (["-p", "input_kind:=rgb"], "none shipped for rig 'surround6' / input 'rgb'"),
        (["-p", "grid.resolution:=0.25"], "weights were trained for grid"),
        (["-p", "rig:=mine"], "none shipped for rig 'mine'"),
        (["-p", "cameras:=[front,back]", "-p", "use_tf:=true"], "weights were trained for cameras"),
        (["-p", "sync_slop_s:=fast"], "expecting type 'DOUBLE'"),
    ],
)
def test_node_rejects_bad_parameters_at_startup(tmp_path, overrides, message):
    """Bad parameters: a clear one-line error and exit status 2, not a traceback."""
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS_FILE),
                          *overrides], free_domain_id(7), tmp_path / "bad.log")
    try:
        code = proc.wait(60)
    finally:
        stop_process(proc)
    text = (tmp_path / "bad.log").read_text()
    assert code == 2, text
    assert "error: " in text and message in text and "Traceback" not in text


def test_node_default_is_the_shipped_bimapper(tmp_path):
    """Started with only its rig's parameter file, the node runs Bi-Mapper with the shipped
    weights (the default method) on the default grid, and publishes exactly the core's maps."""
    rig, grid = preset_rig("surround6"), BevGrid()
    frames = list(generate_drive(rig, grid, SynthConfig(frames=2, seed=12)))
    domain = free_domain_id(3)
    log = tmp_path / "node.log"
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS_FILE),
                          "-p", "threads:=1", "-p", "sync_timeout_s:=5.0"], domain, log)  # no partial sets under load
    rclpy.init(domain_id=domain)
    node = rclpy.create_node("bev_test_default")
    try:
        d = Driver(node, rig)
        for f in frames:
            for _ in range(3):
                d.send_info(f.stamp_ns)
                spin_until(node, lambda: False, 0.05)
            d.send_frame(f)
            assert d.wait_for(f.stamp_ns, 60.0), f"no grids for frame {f.index}:\n{log.read_text()}"
    finally:
        node.destroy_node()
        rclpy.shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    expected = create_mapper(node_view_of_rig(rig), grid, MapperConfig(classes=CLASSES, threads=1))
    assert expected.name == "bimapper"
    complete = 0
    for f in frames:
        # (a camera's image lost by best-effort DDS under load is mapped as missing, by both)
        pred, lost = core_map_as_received(expected, grid, {n: c.labels for n, c in f.cameras.items()},
                                          d.grids[CLASSES[0]][f.stamp_ns].data)
        complete += not lost
        for ci, c in enumerate(CLASSES):
            got = np.asarray(d.grids[c][f.stamp_ns].data, dtype=np.int16)
            want = grid.to_occupancy(pred.probs[ci], pred.known).astype(np.int16)
            # same weights, same float32 ops: at most a rounding step at a few cells
            assert np.abs(got - want).max() <= 1 and (got == want).mean() > 0.999, c
    assert complete >= 1, "every set lost a camera"
    assert (np.asarray(d.grids["vehicle"][frames[0].stamp_ns].data) == 100).sum() > 50
