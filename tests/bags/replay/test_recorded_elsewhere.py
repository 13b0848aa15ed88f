"""A drive recorded elsewhere (issue #25): a bag written by hand with the rosbags library, as
another team's recorder writes it: no bev_mapper metadata, nuScenes-like calibration at full
resolution (1600 x 900, no binning), camera frames named ``CAM_*``, and the six cameras firing
over 43 ms (a rolling trigger, as nuScenes' do). ``bev-bag replay --rig`` / ``--params-file``
maps it into whole sets, equal to the core's maps; nothing about it is silent.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from bags.cli.main import main
from bags.io.reader import BagReader
from bags.io.rig_source import RigChoice, matching_preset
from bags.replay import BAG_DIR
from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig, RigCamera, preset_rig
from bev_mapper_core.geometry.transforms import rot_to_quat
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES
from bev_mapper_core.mapper import MapperConfig, create_mapper
from msg_adapters import occupancy_grid_to_layer

pytestmark = [pytest.mark.slow]
pytest.importorskip("bev_mapper_core.synth")

REPO = Path(__file__).resolve().parents[3]
FRAMES, SPREAD_NS, PERIOD_NS = 3, 43_000_000, 100_000_000
T0_NS = 1_700_000_000 * 10**9
W, H = 1600, 900
TS = get_typestore(Stores.ROS2_JAZZY)


def _full_resolution_rig() -> Rig:
    """surround6's cameras as a full-resolution recorder calibrates them: binning 1."""
    cams = []
    for c in preset_rig("surround6").cameras:
        m = c.model
        cams.append(RigCamera(c.name, CameraModel(K=m.K, D=m.D, width=W, height=H), c.ego_from_cam_array,
                              f"CAM_{c.name.upper()}"))
    return Rig("surround6", tuple(cams))


@pytest.fixture(scope="module")
def label_frames(tmp_path_factory) -> list[dict[str, np.ndarray]]:
    """Label images of a short synthetic surround6 drive, nearest-upsampled to 1600 x 900."""
    bag = tmp_path_factory.mktemp("synth") / "drive"
    assert main(["synth", str(bag), "--frames", str(FRAMES), "--seed", "11"]) == 0
    with BagReader(bag) as r:
        frames = [f.labels for f in r.frames(rgb=False)]
    up = [{c: np.ascontiguousarray(np.repeat(np.repeat(img, 4, 0), 4, 1)) for c, img in f.items()} for f in frames]
    assert len(up) == FRAMES and all(img.shape == (H, W) for f in up for img in f.values())
    return up


def _stamp(ns: int):
    return TS.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(ns: int, frame: str):
    return TS.types["std_msgs/msg/Header"](stamp=_stamp(ns), frame_id=frame)


def _camera_info(cam: RigCamera, ns: int):
    K = np.asarray(cam.model.K, float)
    P = np.hstack([K, np.zeros((3, 1))])
    roi = TS.types["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return TS.types["sensor_msgs/msg/CameraInfo"](
        header=_header(ns, cam.frame_id), height=H, width=W, distortion_model="plumb_bob",
        d=np.zeros(5), k=K.ravel(), r=np.eye(3).ravel(), p=P.ravel(), binning_x=0, binning_y=0, roi=roi)


def _tf_static(rig: Rig, ns: int):
    G = TS.types
    out = []
    for cam in rig.cameras:
        T = cam.ego_from_cam_array
        qx, qy, qz, qw = rot_to_quat(T[:3, :3])
        out.append(G["geometry_msgs/msg/TransformStamped"](
            header=_header(ns, "base_link"), child_frame_id=cam.frame_id,
            transform=G["geometry_msgs/msg/Transform"](
                translation=G["geometry_msgs/msg/Vector3"](x=T[0, 3], y=T[1, 3], z=T[2, 3]),
                rotation=G["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))))
    return G["tf2_msgs/msg/TFMessage"](transforms=out)


def write_recorded_bag(path: Path, frames: list[dict[str, np.ndarray]], *, skip: tuple[str, ...] = (),
                       tf_static: bool = False) -> list[int]:
    """Write the bag by hand with rosbags; return each frame's mean camera stamp (ns).

    Camera ``i`` of the rig fires ``i * 43 / 5`` ms after camera 0; ``skip``: cameras whose
    images are not recorded (their CameraInfo is).
    """
    rig = _full_resolution_rig()
    means = []
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {}
        if tf_static:
            conns["tf"] = w.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=TS)
        for cam in rig.cameras:
            conns[cam.name, "info"] = w.add_connection(f"/cameras/{cam.name}/camera_info",
                                                       "sensor_msgs/msg/CameraInfo", typestore=TS)
            if cam.name not in skip:
                conns[cam.name, "img"] = w.add_connection(f"/cameras/{cam.name}/labels", "sensor_msgs/msg/Image",
                                                          typestore=TS)
        if tf_static:
            w.write(conns["tf"], T0_NS, TS.serialize_cdr(_tf_static(rig, T0_NS), "tf2_msgs/msg/TFMessage"))
        for k, labels in enumerate(frames):
            base = T0_NS + k * PERIOD_NS
            stamps = [base + i * SPREAD_NS // (len(rig.cameras) - 1) for i in range(len(rig.cameras))]
            means.append(sum(stamps) // len(stamps))
            for cam, ns in zip(rig.cameras, stamps):
                info = _camera_info(cam, ns)
                w.write(conns[cam.name, "info"], ns, TS.serialize_cdr(info, "sensor_msgs/msg/CameraInfo"))
                if cam.name in skip:
                    continue
                img = TS.types["sensor_msgs/msg/Image"](header=_header(ns, cam.frame_id), height=H, width=W,
                                                        encoding="mono8", is_bigendian=0, step=W,
                                                        data=labels[cam.name].ravel())
                w.write(conns[cam.name, "img"], ns + 1_000_000, TS.serialize_cdr(img, "sensor_msgs/msg/Image"))
    return means


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, label_frames):
    """The hand-written bag (named ``nus_binned``: the name says nothing) and its mean stamps."""
    bag = tmp_path_factory.mktemp("elsewhere") / "nus_binned"
    return bag, write_recorded_bag(bag, label_frames)


def _output_grids(out: Path, grid: BevGrid) -> dict[int, dict[str, tuple]]:
    got: dict[int, dict[str, tuple]] = {}
    with BagReader(out / BAG_DIR) as o:
        for m in o.messages([f"/bev/{c}" for c in BEV_CLASS_NAMES]):
            stamp = m.msg.header.stamp.sec * 10**9 + m.msg.header.stamp.nanosec
            got.setdefault(stamp, {})[m.topic.rsplit("/", 1)[1]] = (np.asarray(m.msg.data, np.int8), m.msg)
    return got


def _assert_equals_core(out: Path, frames, means) -> None:
    rig, grid = _full_resolution_rig(), BevGrid()
    mapper = create_mapper(rig, grid, MapperConfig(method="ipm"))
    got = _output_grids(out, grid)
    assert sorted(got) == sorted(means)
    for labels, stamp in zip(frames, means):
        pred = mapper.map(labels)
        for ci, name in enumerate(BEV_CLASS_NAMES):
            data, msg = got[stamp][name]
            np.testing.assert_array_equal(data, grid.to_occupancy(pred.probs[ci], pred.known))
            assert occupancy_grid_to_layer(msg, grid)[1].any()


def test_rig_flag_replays_whole_sets_equal_to_the_core(recorded, label_frames, tmp_path, capsys):
    bag, means = recorded
    out = tmp_path / "out"
    assert main(["replay", str(bag), "--out", str(out), "--quiet", "--method", "ipm", "--rig", "surround6",
                 "--no-pictures"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["complete"] and m["rig"] == {"name": "surround6", "cameras": list(preset_rig("surround6").names)}
    assert m["frames"] == FRAMES
    assert m["sync"]["sets"] == FRAMES and m["sync"]["partial_sets"] == 0 and m["sync"]["split_frames"] == 0
    assert "without some camera" not in capsys.readouterr().out
    _assert_equals_core(out, label_frames, means)


def test_params_file_gives_the_same_maps(recorded, label_frames, tmp_path):
    bag, means = recorded
    out = tmp_path / "out"
    assert main(["replay", str(bag), "--out", str(out), "--quiet", "--method", "ipm", "--no-pictures",
                 "--params-file", str(REPO / "config" / "surround6.yaml")]) == 0
    _assert_equals_core(out, label_frames, means)


def test_without_rig_the_error_names_the_flags(recorded, tmp_path, capsys):
    bag, _ = recorded
    assert main(["replay", str(bag), "--out", str(tmp_path / "out"), "--quiet", "--method", "ipm"]) != 0
    err = capsys.readouterr().err
    assert err.startswith("error:") and "--rig" in err and "--params-file" in err and "Traceback" not in err
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_a_narrow_window_splits_frames_and_says_so(recorded, tmp_path, capsys):
    """The old live window (20 ms) splits each 43 ms set in two: counted and said, not silent."""
    bag, _ = recorded
    out = tmp_path / "out"
    assert main(["replay", str(bag), "--out", str(out), "--quiet", "--method", "ipm", "--rig", "surround6",
                 "--no-pictures", "--sync-slop-ms", "20"]) == 0
    cap = capsys.readouterr()
    s = json.loads((out / "metrics.json").read_text())["sync"]
    assert s["sets"] > FRAMES and s["partial_sets"] == s["sets"] and s["split_frames"] >= FRAMES - 1
    assert sum(s["missing_by_camera"].values()) > 0 and s["window_ms"] == 20.0
    assert "split in two" in cap.err and "without some camera" in cap.out


def test_a_camera_that_never_appears_is_reported(label_frames, tmp_path, capsys):
    bag = tmp_path / "no_back"
    write_recorded_bag(bag, label_frames, skip=("back",))
    out = tmp_path / "out"
    assert main(["replay", str(bag), "--out", str(out), "--quiet", "--method", "ipm", "--rig", "surround6",
                 "--no-pictures"]) == 0
    cap = capsys.readouterr()
    s = json.loads((out / "metrics.json").read_text())["sync"]
    assert s["cameras_without_images"] == ["back"]
    assert s["missing_by_camera"]["back"] == s["sets"] == FRAMES
    assert all(n == 0 for c, n in s["missing_by_camera"].items() if c != "back")
    assert "back" in cap.err and "no image topic" in cap.err
    assert f"{FRAMES} set(s) without some camera" in cap.out


def test_a_bag_with_the_presets_calibration_takes_its_name(label_frames, tmp_path):
    """With /tf_static and full-resolution CameraInfo of surround6's calibration, a bag called
    anything is surround6: the shipped weights apply (Bi-Mapper starts on it)."""
    bag = tmp_path / "nus_binned"
    write_recorded_bag(bag, label_frames[:1], tf_static=True)
    with BagReader(bag) as r:
        rig = r.rig()
    assert rig.name == "surround6" and rig.names == preset_rig("surround6").names
    assert matching_preset(rig) == "surround6"
    create_mapper(rig, BevGrid(), MapperConfig(method="bimapper"))  # shipped weights accepted
    shifted = rig["front"].ego_from_cam_array.copy()
    shifted[0, 3] += 0.2
    moved = Rig("mine", tuple(RigCamera(c.name, c.model, shifted if c.name == "front" else c.ego_from_cam_array,
                                        c.frame_id) for c in rig.cameras))
    assert matching_preset(moved) is None  # one camera 20 cm off: not the preset


def test_params_file_errors(recorded, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("just text\n")
    for path, want in ((tmp_path / "none.yaml", "no such file"), (tmp_path, "not a regular file"),
                       (bad, "ros__parameters")):
        with pytest.raises(Exception, match=want):
            RigChoice(params_file=path).hints()


def test_evaluate_takes_the_rig_and_reports_the_missing_camera(label_frames, tmp_path, capsys):
    pytest.importorskip("ray")
    bag = tmp_path / "bags" / "no_back"
    bag.parent.mkdir()
    write_recorded_bag(bag, label_frames[:2], skip=("back",))
    out = tmp_path / "eval"
    assert main(["evaluate", str(bag), "--out", str(out), "--quiet", "--method", "ipm", "--rig", "surround6",
                 "--no-pictures", "--workers", "1"]) == 0
    cap = capsys.readouterr()
    entry = json.loads((out / "summary.json").read_text())["per_bag"][0]
    assert entry["status"] == "ok" and entry["sync"]["missing_by_camera"]["back"] == 2
    assert "no_back: 2 of 2 set(s) mapped without some camera (back: 2" in cap.err


def test_info_says_which_camera_has_no_images(label_frames, tmp_path, capsys):
    bag = tmp_path / "no_back"
    write_recorded_bag(bag, label_frames[:2], skip=("back",))
    assert main(["info", str(bag)]) == 0
    out = capsys.readouterr().out
    assert "camera 'back' has no labels images, the others up to 2" in out
    assert "camera 'front'" not in out.split("problem:", 1)[-1]
