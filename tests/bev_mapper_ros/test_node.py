"""The mapper node in its own process, driven over real DDS by rclpy publishers in this one."""

from __future__ import annotations

import pathlib
import threading
import time

import numpy as np
import pytest
import yaml
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import OccupancyGrid  # noqa: E402
from rclpy.qos import qos_profile_sensor_data  # noqa: E402
from rclpy.signals import uninstall_signal_handlers
from ros_helpers import REPO, core_map_as_received, loaded_torch, rclpy, spin_until, start_process, stop_process
from sensor_msgs.msg import CameraInfo, Image  # noqa: E402

from bev_mapper_core.geometry.grid import BevGrid, grid_preset
from bev_mapper_core.geometry.rig import Rig, RigCamera, preset_rig
from bev_mapper_core.mapper import MapperConfig, create_mapper
from bev_mapper_core.methods import WEIGHTS_DIR
from bev_mapper_core.methods.ipm.mapper import IpmMapper
from bev_mapper_core.synth import SynthConfig, generate_drive
from bev_mapper_ros import mapper_node
from bev_mapper_ros.config import node_config_from_params
from msg_adapters import RclpyFactory, camera_info_to_model, make_camera_info, make_image

GRID = BevGrid(x_min=-20, x_max=20, y_min=-10, y_max=10, resolution=0.25)
CLASSES = ("drivable", "ped_crossing", "vehicle")
PARAMS_FILE = REPO / "config" / "surround6.yaml"


def node_view_of_rig(rig: Rig, params_file: pathlib.Path = PARAMS_FILE) -> Rig:
    """The rig exactly as the node sees it: intrinsics via CameraInfo, extrinsics via the YAML."""
    params = yaml.safe_load(params_file.read_text())["/**"]["ros__parameters"]
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
def ros(tmp_path, request, ros_domain):
    """A running mapper_node process and a test node on a private domain.

    Parametrize indirectly with the node's ``sync_timeout_s`` (default 5 s: on a loaded machine a
    short timeout maps a set without an image that is merely slow).
    """
    timeout_s = getattr(request, "param", 5.0)
    domain = ros_domain
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
    """Publishers for every camera's labels + CameraInfo and subscribers to the outputs.

    ``log``: the node process's log, where it reports each camera's calibration (readiness).
    """

    def __init__(self, node, rig: Rig, log: pathlib.Path, kind: str = "labels", classes: tuple[str, ...] = CLASSES):
        self.node, self.rig, self.log, self.factory, self.kind = node, rig, log, RclpyFactory(), kind
        topic = "labels" if kind == "labels" else "image_raw"
        self.labels = {c: node.create_publisher(Image, f"/cameras/{c}/{topic}", qos_profile_sensor_data)
                       for c in rig.names}
        self.infos = {c: node.create_publisher(CameraInfo, f"/cameras/{c}/camera_info", 10)
                      for c in rig.names}
        self.grids: dict[str, dict[int, OccupancyGrid]] = {c: {} for c in classes}
        self.diags: list[DiagnosticArray] = []
        for c in classes:
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

    def calibrate(self, stamp_ns, timeout=30.0) -> bool:
        """Send every camera's CameraInfo, again every 50 ms until the node has logged each
        camera's calibration (CameraInfo goes best effort: one may be lost). Once calibrated: once."""
        want = [f"calibration of {c}:" for c in self.rig.names]
        end = time.monotonic() + timeout
        while True:
            self.send_info(stamp_ns)
            text = self.log.read_text()
            if all(w in text for w in want):
                return True
            if time.monotonic() > end:
                return False
            spin_until(self.node, lambda: False, 0.05)

    def send_frame(self, frame, override: dict | None = None):
        for name, cf in frame.cameras.items():
            img, enc = (cf.labels, "mono8") if self.kind == "labels" else (cf.rgb, "rgb8")
            msg = (override or {}).get(name) or make_image(self.factory, img, enc, frame.stamp_ns,
                                                            self.rig[name].frame_id)
            self.labels[name].publish(msg)
            spin_until(self.node, lambda: False, 0.01)  # paced like separate drivers: less loss under load

    def wait_for(self, stamp_ns, timeout=20.0):
        return spin_until(self.node, lambda: all(stamp_ns in self.grids[c] for c in self.grids), timeout)

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
    d = Driver(node, rig, log)
    expected_mapper = IpmMapper(node_view_of_rig(rig), GRID, MapperConfig(classes=CLASSES))
    complete = 0
    for f in frames:
        assert d.calibrate(f.stamp_ns), f"the node never reported its calibration:\n{log.read_text()}"
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
    assert loaded_torch(proc.pid) == []  # IPM runs without torch
    # The drive has road in view: the comparison is not between two empty maps.
    assert (np.asarray(d.grids["drivable"][frames[0].stamp_ns].data) == 100).sum() > 500


@pytest.mark.parametrize("ros", [1.0], indirect=True)  # rejected cameras make partial sets: wait 1 s
def test_node_survives_broken_input(ros, drive):
    proc, node, log = ros
    rig, frames = drive
    d = Driver(node, rig, log)
    f0, f1, f2 = frames
    assert d.calibrate(f0.stamp_ns), f"the node never reported its calibration:\n{log.read_text()}"
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
    # (The log is throttled; the counters are not.) Read diagnostics published after frame 2 was
    # counted (mapped_sets >= 3): an older one may come from between a set's decoding and its count.
    assert spin_until(node, lambda: int(d.diag_values().get("mapped_sets", 0)) >= 3
                      and int(d.diag_values().get("bad_input", 0)) >= 4, 5.0), d.diag_values()
    text = log.read_text()  # one line per camera and problem, throttled per problem
    assert "uncalibrated" in text and "'rgb8'" in text and "expected 200x112" in text  # size from camera_info
    assert int(d.diag_values()["sets_with_missing_cameras"]) >= 1
    # Frame 1 was mapped without its broken cameras: cells only the front camera sees are unknown.
    occ = np.asarray(d.grids["drivable"][f1.stamp_ns].data)
    r, c = GRID.metric_to_cell(15.0, 0.0)
    assert occ[r * GRID.width + c] == -1
    assert np.asarray(d.grids["drivable"][f2.stamp_ns].data)[r * GRID.width + c] != -1


BAD_PARAMETERS = [
    (["-p", "grid.resolution:=0.7"], "not a whole number"),
    (["-p", "cameras:=[front,front]"], "distinct"),
    (["-p", "method:=bimapper", "-p", "weights:=/nonexistent.safetensors"], "does not exist"),
    (["-p", "method:=ipm", "-p", "input_kind:=rgb"], "label images only"),
    (["-p", "input_kind:=rgb", "-p", "segmenter:=none"], "none shipped for rig 'surround6' / input 'rgb'"),
    (["-p", "method:=segipm"], "segipm maps RGB images"),
    (["-p", "grid.resolution:=0.25"], "weights were trained for grid"),
    (["-p", "rig:=mine", "-p", "input_kind:=rgb", "-p", "segmenter:=none"], "none shipped for rig 'mine'"),
    (["-p", "cameras:=[front,back]", "-p", "use_tf:=true", "-p",
      f"weights:={WEIGHTS_DIR / 'bimapper_surround6_labels.safetensors'}"], "weights were trained for cameras"),
    (["-p", "label_map:=cityscapes"], "label_map 'cityscapes' is no preset"),
    (["-p", "sync_slop_s:=fast"], "expecting type 'DOUBLE'"),
]


def run_main_in_process(overrides: list[str], capsys) -> tuple[int, str]:
    """``mapper_node``'s ``main()`` in this process with the shipped surround6 file plus
    ``overrides``: (exit status, stderr). A node that starts after all would spin forever: a
    watchdog shuts its context down after 60 s, main() then returns 0 and the test fails."""
    watchdog = threading.Timer(60.0, rclpy.try_shutdown)
    watchdog.start()
    try:
        code = mapper_node.main(["mapper_node", "--ros-args", "--params-file", str(PARAMS_FILE), *overrides])
    finally:
        watchdog.cancel()
        uninstall_signal_handlers()  # main()'s rclpy.init installed them; shutting down on error does not
    return code, capsys.readouterr().err


@pytest.mark.parametrize("overrides, message", BAD_PARAMETERS)
def test_node_rejects_bad_parameters_at_startup(overrides, message, ros_domain, monkeypatch, capsys):
    """Bad parameters: a clear one-line error and exit status 2 from main(), not an exception.

    In this process (each case in a real process cost 0.5-3 s); the exit status of the process
    itself is checked by test_node_process_exits_2_on_bad_parameters."""
    monkeypatch.setenv("ROS_DOMAIN_ID", str(ros_domain))
    code, err = run_main_in_process(overrides, capsys)
    assert code == 2, err
    assert "error: " in err and message in err and "Traceback" not in err


@pytest.mark.parametrize("overrides, message", [BAD_PARAMETERS[0], BAD_PARAMETERS[-1]], ids=["grid", "type"])
def test_node_process_exits_2_on_bad_parameters(tmp_path, overrides, message, ros_domain):
    """A real mapper_node process: exit status 2, the error line and no traceback, for an error
    of the node's configuration (BevMapperError) and one of rclpy's parameter parsing
    (ParameterException), main()'s two error branches."""
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(PARAMS_FILE),
                          *overrides], ros_domain, tmp_path / "bad.log")
    try:
        code = proc.wait(60)
    finally:
        stop_process(proc)
    text = (tmp_path / "bad.log").read_text()
    assert code == 2, text
    assert "error: " in text and message in text and "Traceback" not in text


def _run_shipped_node(tmp_path, domain, kind: str, seed: int, n_frames: int, params_file: pathlib.Path = PARAMS_FILE,
                      classes: tuple[str, ...] = CLASSES) -> tuple:
    """A mapper_node process started with a shipped parameter file (plus ``input_kind`` for RGB)
    fed ``n_frames`` synthetic frames of ``kind`` images of the file's rig, on the file's grid:
    (core mapper, frames, driver)."""
    log = tmp_path / "node.log"
    params = yaml.safe_load(params_file.read_text())["/**"]["ros__parameters"]
    extra = [] if kind == params["input_kind"] else ["-p", f"input_kind:={kind}"]
    # The node boots (torch, weights) while this process renders the drive and loads the weights.
    proc = start_process(["bev_mapper_ros.mapper_node", "--ros-args", "--params-file", str(params_file), *extra,
                          "-p", "threads:=1", "-p", "sync_timeout_s:=5.0", "-p", "backend:=torch"],  # no partial sets under load
                         domain, log)
    node = None
    try:
        rig, grid = preset_rig(params["rig"]), BevGrid.from_dict(params["grid"])
        frames = list(generate_drive(rig, grid, SynthConfig(frames=n_frames, seed=seed)))
        expected = create_mapper(node_view_of_rig(rig, params_file), grid,
                                 MapperConfig(method=params["method"], input_kind=kind, classes=classes, threads=1,
                                              backend="torch"))
        rclpy.init(domain_id=domain)
        node = rclpy.create_node(f"bev_test_{kind}")
        d = Driver(node, rig, log, kind=kind, classes=classes)
        for f in frames:
            assert d.calibrate(f.stamp_ns, 60.0), f"the node never reported its calibration:\n{log.read_text()}"
            d.send_frame(f)
            assert d.wait_for(f.stamp_ns, 60.0), f"no grids for frame {f.index}:\n{log.read_text()}"
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
        assert stop_process(proc) in (0, -2), log.read_text()
    complete = 0
    for f in frames:
        # (a camera's image lost by best-effort DDS under load is mapped as missing, by both)
        images = {n: (c.labels if kind == "labels" else c.rgb) for n, c in f.cameras.items()}
        pred, lost = core_map_as_received(expected, grid, images, d.grids[classes[0]][f.stamp_ns].data)
        complete += not lost
        for ci, c in enumerate(classes):
            got = np.asarray(d.grids[c][f.stamp_ns].data, dtype=np.int16)
            assert len(got) == grid.width * grid.height
            want = grid.to_occupancy(pred.probs[ci], pred.known).astype(np.int16)
            # same weights, same float32 ops: at most a rounding step at a few cells
            assert np.abs(got - want).max() <= 1 and (got == want).mean() > 0.999, c
    assert complete >= 1, "every set lost a camera"
    return expected, frames, d


def test_node_default_is_the_shipped_bimapper(tmp_path, ros_domain):
    """Started with only its rig's parameter file, the node runs Bi-Mapper with the shipped
    weights (the default method) on the default grid, and publishes exactly the core's maps."""
    expected, frames, d = _run_shipped_node(tmp_path, ros_domain, "labels", 12, 2)
    assert expected.name == "bimapper"
    assert (np.asarray(d.grids["vehicle"][frames[0].stamp_ns].data) == 100).sum() > 50


def test_node_maps_rgb_cameras_with_the_shipped_weights(tmp_path, ros_domain):
    """``input_kind:=rgb`` and nothing else: the shipped segmenter feeds the shipped label
    Bi-Mapper (chained), and the node publishes exactly the core's maps of the RGB images."""
    expected, frames, d = _run_shipped_node(tmp_path, ros_domain, "rgb", 13, 1)
    assert expected.stage is not None  # chained: segmenter, then the label weights
    assert (np.asarray(d.grids["drivable"][frames[0].stamp_ns].data) == 100).sum() > 500


def test_node_runs_s2g2_on_its_own_grid(tmp_path, ros_domain):
    """``--params-file config/front1_s2g2.yaml`` and nothing else: the node maps the front camera's
    RGB images with the shipped S2G2 weights onto the 32 m x 32 m grid ahead, exactly as the core."""
    expected, frames, d = _run_shipped_node(tmp_path, ros_domain, "rgb", 14, 2, REPO / "config" / "front1_s2g2.yaml",
                                            classes=("drivable", "sidewalk"))
    assert expected.name == "s2g2" and expected.grid == grid_preset("ahead")
    info = d.grids["drivable"][frames[0].stamp_ns].info
    assert (info.width, info.height) == (128, 128) and info.origin.position.x == 0.0
    assert (np.asarray(d.grids["drivable"][frames[0].stamp_ns].data) >= 50).sum() > 1000



def test_node_maps_cameras_that_fire_over_43_ms_as_whole_sets(ros, drive):
    """A rolling trigger (nuScenes' six cameras fire over ~43 ms): each frame is one set, stamped
    by its first camera, never split into two half-sets; /diagnostics says no set lacked a camera."""
    proc, node, log = ros
    rig, frames = drive
    d = Driver(node, rig, log)
    expected_mapper = IpmMapper(node_view_of_rig(rig), GRID, MapperConfig(classes=CLASSES))
    spread = 43_000_000 // (len(rig.names) - 1)
    complete = 0
    for f in frames:
        assert d.calibrate(f.stamp_ns), f"the node never reported its calibration:\n{log.read_text()}"
        override = {name: make_image(d.factory, f.cameras[name].labels, "mono8", f.stamp_ns + i * spread,
                                     rig[name].frame_id) for i, name in enumerate(rig.names)}
        d.send_frame(f, override)
        assert d.wait_for(f.stamp_ns), f"no grids for frame {f.index}:\n{log.read_text()}"
    for f in frames:
        pred, lost = core_map_as_received(expected_mapper, GRID, {n: c.labels for n, c in f.cameras.items()},
                                          d.grids[CLASSES[0]][f.stamp_ns].data)
        complete += not lost
    assert sorted(d.grids["drivable"]) == [f.stamp_ns for f in frames]  # no half-set of a split frame
    assert complete >= 1, "every set lost a camera"
    assert spin_until(node, lambda: d.diag_values().get("mapped_sets") == str(len(frames)), 10.0)
    values = d.diag_values()
    assert values["split_sets"] == "0" and values["sync_window_ms"] == "50.0"
    assert int(values["sets_with_missing_cameras"]) == len(frames) - complete
