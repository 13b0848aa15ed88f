"""Node configuration, generated rig configs and the latest-set worker (no ROS graph needed)."""

import threading
import time

import numpy as np
import pytest
import yaml

from bev_mapper_core.errors import ConfigError, GridError
from bev_mapper_core.geometry.grid import grid_preset
from bev_mapper_core.geometry.rig import PRESETS, preset_rig
from bev_mapper_core.geometry.transforms import quat_to_rot
from bev_mapper_ros.calibration import LiveCalibration
from bev_mapper_ros.config import NodeConfigError, node_config_from_params
from bev_mapper_ros.rig_params import CONFIG_DIR, METHOD_CONFIGS, write_configs
from bev_mapper_ros.tf_source import TfLookupError
from bev_mapper_ros.worker import LatestSlot, Worker


def test_params_map_onto_dataclasses():
    cfg = node_config_from_params({
        "cameras": ["a", "b"], "input_kind": "rgb", "method": "ipm", "classes": ["drivable"],
        "grid.x_min": 0.0, "grid.x_max": 10.0, "grid.y_min": -5.0, "grid.y_max": 5.0,
        "grid.resolution": 0.5, "extrinsics.a": [1, 2, 3, 0, 0, 0, 1], "compressed": True,
    })
    assert cfg.grid.shape == (20, 20) and cfg.mapper.input_kind == "rgb"
    assert cfg.mapper.classes == ("drivable",)
    assert cfg.image_topic_for("a") == "/cameras/a/image_raw/compressed"
    assert cfg.camera_info_topic_for("b") == "/cameras/b/camera_info"
    np.testing.assert_allclose(cfg.extrinsic("a")[:3, 3], [1, 2, 3])
    assert cfg.extrinsic("b") is None


@pytest.mark.parametrize(
    "params, error, message",
    [
        ({"cameras": []}, NodeConfigError, "cameras"),
        ({"cameras": ["a", "a/b"]}, NodeConfigError, "without '/'"),
        ({"cameras": ["a"], "extrinsics.a": [1, 2, 3]}, NodeConfigError, "7 finite numbers"),
        ({"cameras": ["a"], "extrinsics.a": [0, 0, 0, 0, 0, 0, 0]}, NodeConfigError, "quaternion"),
        ({"cameras": ["a"], "sync_slop_s": 0.5, "sync_timeout_s": 0.1}, NodeConfigError, "timeout"),
        ({"cameras": ["a"], "image_topic": "/img"}, NodeConfigError, "{camera}"),
        ({"cameras": ["a"], "grid.resolution": -1.0}, GridError, "resolution"),
        ({"cameras": ["a"], "input_kind": "depth"}, ConfigError, "input_kind"),
        ({"cameras": ["a"], "classes": ["unicorn"]}, ConfigError, "unknown BEV class"),
    ],
)
def test_bad_params_are_rejected_with_a_clear_message(params, error, message):
    with pytest.raises(error, match=message):
        node_config_from_params(params)


def test_shipped_configs_match_the_rig_presets(tmp_path):
    """config/*.yaml are generated from the presets; a stale file would map with wrong extrinsics."""
    written = write_configs(tmp_path)
    assert sorted(p.name for p in written) == sorted(f"{n}.yaml" for n in (*PRESETS, *METHOD_CONFIGS))
    for path in written:
        assert (CONFIG_DIR / path.name).read_text() == path.read_text(), f"regenerate {path.name}"
    doc = yaml.safe_load((CONFIG_DIR / "front1_s2g2.yaml").read_text())["/**"]["ros__parameters"]
    flat = {k: v for k, v in doc.items() if k not in ("grid", "extrinsics")}
    flat.update({f"grid.{k}": v for k, v in doc["grid"].items()})
    s2g2 = node_config_from_params(flat)
    assert s2g2.mapper.method == "s2g2" and s2g2.mapper.input_kind == "rgb" and s2g2.grid == grid_preset("ahead")
    # And the parameters really describe the preset's extrinsics.
    params = yaml.safe_load((CONFIG_DIR / "surround6.yaml").read_text())["/**"]["ros__parameters"]
    rig = preset_rig("surround6")
    for cam in rig.cameras:
        x, y, z, qx, qy, qz, qw = params["extrinsics"][cam.name]
        np.testing.assert_allclose(quat_to_rot(qx, qy, qz, qw), cam.ego_from_cam_array[:3, :3], atol=1e-8)
        np.testing.assert_allclose([x, y, z], cam.ego_from_cam_array[:3, 3], atol=1e-8)


def test_latest_slot_keeps_only_the_newest_and_counts_drops():
    slot = LatestSlot()
    assert slot.put(1) is False
    assert slot.put(2) is True and slot.put(3) is True
    assert slot.dropped == 2
    assert slot.take(0) == 3 and slot.take(0.01) is None


def test_worker_survives_a_failing_item():
    slot, done, errors = LatestSlot(), [], []
    event = threading.Event()

    def handle(item):
        if item == "bad":
            raise ValueError("boom")
        done.append(item)
        event.set()

    w = Worker(slot, handle, errors.append)
    w.start()
    slot.put("bad")
    time.sleep(0.2)
    slot.put("good")
    assert event.wait(5)
    w.stop()
    assert done == ["good"] and len(errors) == 1 and "boom" in str(errors[0])


class _TfAnswers:
    """A :class:`~bev_mapper_ros.tf_source.TfSource`: answers set by the test (a transform, or an error)."""

    def __init__(self) -> None:
        self.answer = TfLookupError("no_path", "no transform yet")

    def lookup(self, target, source, stamp_ns=None):
        if isinstance(self.answer, TfLookupError):
            raise self.answer
        return self.answer


def test_live_calibration_prefers_tf_and_bumps_version_only_on_change():
    rig = preset_rig("front1")
    cam = rig.cameras[0]
    tf, problems = _TfAnswers(), []
    calib = LiveCalibration("front1", ["front"], "base_link", {"front": cam.ego_from_cam_array},
                            tf=tf, on_problem=lambda kind, text: problems.append(kind))
    assert calib.rig() is None and calib.missing() == ("front: camera_info",)
    assert calib.update_intrinsics("front", cam.model, cam.frame_id) is True
    assert calib.update_intrinsics("front", cam.model, cam.frame_id) is False
    first = calib.rig()
    assert calib.sources() == {"front": "parameter"} and problems == []  # no TF yet: the fallback, no error
    np.testing.assert_allclose(first["front"].ego_from_cam_array, cam.ego_from_cam_array)
    v = calib.version
    lifted = cam.ego_from_cam_array.copy()
    lifted[2, 3] += 0.4
    tf.answer = lifted
    second = calib.rig()
    assert calib.version > v and calib.sources() == {"front": "tf"}
    assert "front: TF (base_link <- front_optical_frame)" in calib.describe_sources()
    np.testing.assert_allclose(second["front"].ego_from_cam_array, lifted)
    assert calib.rig() is second  # cached while nothing changes


def test_live_calibration_refuses_tf_jumps_and_keeps_the_last_good_extrinsic():
    rig = preset_rig("front1")
    cam = rig.cameras[0]
    tf, problems = _TfAnswers(), []
    calib = LiveCalibration("front1", ["front"], "base_link", {"front": cam.ego_from_cam_array},
                            tf=tf, max_jump_m=0.5, on_problem=lambda kind, text: problems.append(kind))
    calib.update_intrinsics("front", cam.model, cam.frame_id)
    tf.answer = cam.ego_from_cam_array.copy()
    good = calib.rig()
    assert calib.sources() == {"front": "tf"}
    jumped = cam.ego_from_cam_array.copy()
    jumped[0, 3] += 3.0  # metres: a broken transform, not a mount
    tf.answer = jumped
    assert calib.rig() is good and problems == ["extrinsic_jump"]
    for kind in ("extrapolation", "cycle", "no_path"):  # TF lost after it had the camera: counted, kept
        tf.answer = TfLookupError(kind, "gone")
        assert calib.rig() is good
    assert problems == ["extrinsic_jump", "extrapolation", "cycle", "no_path"]
    np.testing.assert_allclose(good["front"].ego_from_cam_array, cam.ego_from_cam_array)


@pytest.mark.parametrize("params, message", [
    ({"pose_source": "gps"}, "pose_source must be one of"),
    ({"pose_source": "tf", "use_tf": False}, "pose_source tf needs use_tf true"),
    ({"odom_frame": "base_link"}, "odom_frame must be a frame other than base_frame"),
    ({"tf_extrinsic_jump_m": 0.0}, "tf_extrinsic_jump_m must be > 0"),
])
def test_tf_parameters_are_checked(params, message):
    with pytest.raises(NodeConfigError, match=message):
        node_config_from_params({"rig": "front1", **params})
    assert node_config_from_params({"rig": "front1"}).pose_source == "auto"


def test_inference_threads_leave_a_core_to_the_callbacks(monkeypatch):
    """One rule in the node, replay and the benchmarks: every CPU but one (the environment
    variable overrides it); the node's ``threads`` 0 leaves the choice to that rule.
    """
    import os

    from bev_mapper_core.nn.runtime import THREADS_ENV, inference_threads

    cpus = len(os.sched_getaffinity(0))
    monkeypatch.delenv(THREADS_ENV, raising=False)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    assert inference_threads() == max(1, cpus - 1)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # e.g. a Ray task of one CPU
    assert inference_threads() == 1
    monkeypatch.setenv(THREADS_ENV, "3")
    assert inference_threads() == 3
    assert node_config_from_params({"cameras": ["a"]}).mapper.threads == 0
    assert node_config_from_params({"cameras": ["a"], "threads": 3}).mapper.threads == 3
    from bev_mapper_core.mapper import MapperConfig

    with pytest.raises(ConfigError, match="threads"):
        MapperConfig(threads=-1)
