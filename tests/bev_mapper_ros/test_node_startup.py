"""Start-up and shutdown of a learned node (issue #41), over real DDS and real processes: on an
empty export cache the node maps its first camera set with torch while the fast backend's model
is exported in a child process, then switches (log and ``/diagnostics``); SIGINT or SIGTERM at
any moment of the start-up (imports, set-up, first frames, export) exits 0 and leaves no partial
file in the cache. Bi-Mapper on surround6 (its export is the shortest of the learned methods).
"""

from __future__ import annotations

import re
import signal
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import OccupancyGrid
from rclpy.qos import QoSProfile, ReliabilityPolicy
from ros_helpers import REPO, rclpy, start_process, stop_process
from sensor_msgs.msg import CameraInfo, Image

from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.labels.classes import Label
from bev_mapper_core.nn.backends import installed_backends, resolve_backend
from msg_adapters import RclpyFactory, make_camera_info, make_image

NODE = "bev_mapper_ros.mapper_node"
PARAMS = ["--ros-args", "--params-file", str(REPO / "config" / "surround6.yaml"), "-p", "threads:=1"]
#: the brief's target: the first grid within 5 s of the first complete camera set (cold cache)
FIRST_GRID_S = 5.0


def _cache_files(cache) -> list[str]:
    onnx = cache / "onnx"
    return sorted(p.name for p in onnx.iterdir()) if onnx.is_dir() else []


def _no_partial_file(cache) -> None:
    names = _cache_files(cache)
    stems = {n[:-5] for n in names if n.endswith(".onnx")} & {n[:-5] for n in names if n.endswith(".json")}
    assert all(n.rsplit(".", 1)[0] in stems for n in names), names  # complete pairs only, no part file


class Cameras:
    """CameraInfo and constant road label images of surround6, and the grids that come back."""

    def __init__(self, domain: int):
        rclpy.init(domain_id=domain)
        self.node = rclpy.create_node("bev_startup_test")
        self.rig, self.factory = preset_rig("surround6"), RclpyFactory()
        qos = QoSProfile(depth=5, reliability=ReliabilityPolicy.RELIABLE)
        self.pubs = {c.name: self.node.create_publisher(Image, f"/cameras/{c.name}/labels", qos) for c in self.rig.cameras}
        self.infos = {c.name: self.node.create_publisher(CameraInfo, f"/cameras/{c.name}/camera_info", qos)
                      for c in self.rig.cameras}
        self.grids: list[float] = []
        self.diags: list[DiagnosticArray] = []
        self.node.create_subscription(OccupancyGrid, "/bev/drivable", lambda m: self.grids.append(time.monotonic()), 10)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diags.append, 10)
        self.labels = {c.name: np.full(c.model.image_size[::-1], Label.ROAD, np.uint8) for c in self.rig.cameras}
        self.k = 0

    def matched(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in (*self.pubs.values(), *self.infos.values()))

    def feed(self, until, timeout: float) -> float | None:
        """Publish a set every 0.1 s until ``until()``; the time of the first set sent after the
        node's subscriptions matched (None: they never did).
        """
        first, end = None, time.monotonic() + timeout
        while not until() and time.monotonic() < end:
            if first is None and self.matched():
                first = time.monotonic()
            stamp = time.time_ns()
            for cam in self.rig.cameras:
                self.infos[cam.name].publish(make_camera_info(self.factory, cam.model, stamp, cam.frame_id))
                self.pubs[cam.name].publish(make_image(self.factory, self.labels[cam.name], "mono8", stamp, cam.frame_id))
            self.k += 1
            tick = time.monotonic() + 0.1
            while time.monotonic() < tick and not until():
                rclpy.spin_once(self.node, timeout_sec=0.02)
        return first

    def close(self) -> None:
        self.node.destroy_node()
        rclpy.try_shutdown()


def _diag_value(msg: DiagnosticArray, key: str) -> str | None:
    return next((kv.value for kv in msg.status[0].values if kv.key == key), None)


@pytest.fixture()
def fast_backend():
    backend = resolve_backend("auto")
    if backend == "torch":
        pytest.skip(f"no exported backend installed ({installed_backends()})")
    return backend


def test_cold_start_maps_with_torch_at_once_then_switches(ros_domain, tmp_path, monkeypatch, fast_backend):
    cache = tmp_path / "cache"
    monkeypatch.setenv("BEV_MAPPER_CACHE", str(cache))
    log = tmp_path / "node.log"
    proc = start_process([NODE, *PARAMS, "-p", "diagnostics_period_s:=0.5"], ros_domain, log)
    cams = Cameras(ros_domain)
    try:
        first_set = cams.feed(lambda: bool(cams.grids), 60)
        assert cams.grids, log.read_text()
        assert first_set is not None and cams.grids[0] - first_set < FIRST_GRID_S, (cams.grids[0] - first_set)
        text = log.read_text()
        assert f"inference: mapping with torch (until the {fast_backend} model is ready)" in text
        assert not _cache_files(cache) or all(n.startswith(".") for n in _cache_files(cache))  # being exported
        switched = f"inference: switched from torch to {fast_backend}"
        cams.feed(lambda: switched in log.read_text(), 120)
        assert switched in log.read_text(), log.read_text()
        n = len(cams.diags)
        cams.feed(lambda: len(cams.diags) > n + 1, 10)
        assert _diag_value(cams.diags[-1], "backend") == fast_backend
        said = [_diag_value(d, "backend") for d in cams.diags]
        torch_first = f"torch (until the {fast_backend} model is ready)"
        assert torch_first in said and said.index(torch_first) < said.index(fast_backend), said
        grids = len(cams.grids)
        cams.feed(lambda: len(cams.grids) > grids + 2, 10)  # still mapping on the exported model
        assert len(cams.grids) > grids + 2
    finally:
        cams.close()
        code = stop_process(proc)
    assert code == 0, log.read_text()
    assert "Traceback" not in log.read_text() and "[ERROR]" not in log.read_text()
    _no_partial_file(cache)
    assert len(_cache_files(cache)) == 2  # the export, complete, for the next start


#: (signal, when): during the imports; once the node said it is set up (no camera yet); 1 s into
#: the first frames, while the model is exported
MOMENTS = [(signal.SIGINT, "imports"), (signal.SIGTERM, "set up"), (signal.SIGINT, "exporting")]


@pytest.mark.parametrize("sig, when", MOMENTS, ids=[f"{s.name}-{w}" for s, w in MOMENTS])
def test_a_signal_at_any_moment_of_the_start_up_exits_0_and_leaves_no_partial_file(
        ros_domain, tmp_path, monkeypatch, fast_backend, sig, when):
    cache = tmp_path / "cache"
    monkeypatch.setenv("BEV_MAPPER_CACHE", str(cache))
    log = tmp_path / "node.log"
    proc = start_process([NODE, *PARAMS], ros_domain, log)
    cams = Cameras(ros_domain) if when == "exporting" else None
    try:
        if when == "imports":
            time.sleep(0.15)
        elif when == "set up":
            end = time.monotonic() + 60
            while not re.search(r"mapping \[.*\] with", log.read_text()) and time.monotonic() < end:
                assert proc.poll() is None, log.read_text()
                time.sleep(0.05)
        else:
            cams.feed(lambda: bool(cams.grids), 60)
            assert cams.grids, log.read_text()
            cams.feed(lambda: False, 1.0)
            assert "switched from torch" not in log.read_text()  # the export is still running
            assert any(n.startswith(".") for n in _cache_files(cache)) or not _cache_files(cache)
        proc.send_signal(sig)
        code = proc.wait(30)
    finally:
        if cams is not None:
            cams.close()
        stop_process(proc)
    text = log.read_text()
    assert code == 0, text
    assert "Traceback" not in text and "terminate called" not in text and "[ERROR]" not in text, text
    _no_partial_file(cache)
    assert _cache_files(cache) == []  # nothing was cached: the export never finished
