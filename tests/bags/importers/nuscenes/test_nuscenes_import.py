"""``bev-bag import nuscenes`` on a miniature dataset the tests write (``tests/nuscenes_helpers.py``):
the bag's layout, the GT against hand-computed cells, bad input, and a round trip into ``bev-bag replay``.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from nuscenes_helpers import CHANNELS, IMG_H, IMG_W, T0_US, write_nuscenes
from rosbags.highlevel import AnyReader

from bags.cli.main import main
from bags.importers.nuscenes.scene import CAMERAS
from msg_adapters import occupancy_grid_to_layer


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return write_nuscenes(tmp_path_factory.mktemp("nus"))


@pytest.fixture(scope="module")
def imported(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("bags")
    assert main(["import", "nuscenes", str(dataset), "--version", "v1.0-mini", "--split", "mini_train",
                 "--out", str(out)]) == 0
    return out / "scene-0061"


def _read(bag: Path) -> tuple[dict, dict]:
    """``(topic -> [(log_ns, msg)], custom_data)``."""
    out: dict[str, list] = {}
    with AnyReader([bag]) as r:
        for conn, log_ns, raw in r.messages():
            out.setdefault(conn.topic, []).append((log_ns, r.deserialize(raw, conn.msgtype)))
    meta = (bag / "metadata.yaml").read_text()
    return out, meta


def _layer(msg) -> tuple[np.ndarray, np.ndarray]:
    probs, known = occupancy_grid_to_layer(msg)
    return probs >= 0.5, known


def test_the_bag_holds_the_six_cameras_jpegs_as_they_are_at_their_own_stamps(imported, dataset):
    topics, meta = _read(imported)
    sd = json.loads((dataset / "v1.0-mini" / "sample_data.json").read_text())
    for ch in CHANNELS:
        cam = CAMERAS[ch]
        msgs = topics[f"/cameras/{cam}/image_raw/compressed"]
        recs = sorted((r for r in sd if r["is_key_frame"] and f"/{ch}/" in r["filename"]
                       and "scene-0061" in r["filename"]), key=lambda r: r["timestamp"])
        assert len(msgs) == len(recs) == 4
        for (log_ns, m), r in zip(msgs, recs):
            assert m.format == "jpeg" and m.header.frame_id == f"{cam}_optical_frame"
            assert log_ns == r["timestamp"] * 1000 == m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
            assert bytes(m.data) == (dataset / r["filename"]).read_bytes()  # copied, not re-encoded
        info = topics[f"/cameras/{cam}/camera_info"][0][1]
        assert (info.width, info.height) == (IMG_W, IMG_H) and info.k[0] > 0
    assert len(topics["/tf_static"][0][1].transforms) == 6
    assert "bev_mapper.rig: surround6" in meta and "CC BY-NC-SA 4.0" in meta
    odom = topics["/odom"]
    assert [t for t, _ in odom] == sorted({t for t, _ in odom})  # one pose per stamp, in order
    assert odom[-1][1].twist.twist.linear.x == pytest.approx(5.0)  # 5 m/s forward, from the poses
    assert len(topics["/tf"]) == len(odom)


def test_gt_layers_at_the_key_frames_equal_hand_computed_cells(imported):
    topics, _ = _read(imported)
    stamps = [t for t, _ in topics["/bev/gt/drivable"]]
    assert stamps == [(T0_US + k * 500_000) * 1000 for k in range(4)]
    drivable, known = _layer(topics["/bev/gt/drivable"][0][1])
    assert known.all()
    # the road y in [95, 105] seen from y = 100: rows (10 / 0.15 = 66.67 -> 67) .. (20 / 0.15 = 133.33 -> 133)
    assert np.array_equal(np.flatnonzero(drivable.any(axis=1)), np.arange(67, 134)) and drivable[67:134].all()
    # the car 10 m ahead, 4 m x 2 m: corners x 8 .. 12 -> columns 253.3 .. 280 -> 253 .. 280, rows 93 .. 107
    vehicle, vknown = _layer(topics["/bev/gt/vehicle"][0][1])
    want = np.zeros_like(vehicle)
    want[93:108, 253:281] = True
    assert np.array_equal(vehicle, want)
    # the car of visibility 1 with no lidar points at (-12, -6) is left out: -1, not 0
    hidden = ~vknown
    assert hidden[[r for r in range(200) if hidden[r].any()]].any() and not vehicle[hidden].any()
    assert np.array_equal(np.argwhere(hidden).min(0), [53, 107]) and np.array_equal(np.argwhere(hidden).max(0), [67, 133])
    ped, pknown = _layer(topics["/bev/gt/pedestrian"][0][1])
    assert pknown.all() and np.array_equal(np.argwhere(ped).min(0), [138, 231])  # (5, 6) - 0.3 m: round(140 - 2) ...
    # the road divider y = 100.3 (row 102) and the lane divider y = 102.8 (row 118.67 -> 118), cv2's 5-thick lines
    div, _ = _layer(topics["/bev/gt/lane_divider"][0][1])
    assert set(np.flatnonzero(div[:, 200])) == set(range(98, 105)) | set(range(115, 122))
    # the road's outline: its two edges, not where it leaves the patch
    bound, _ = _layer(topics["/bev/gt/road_boundary"][0][1])
    assert set(np.flatnonzero(bound[:, 200])) == set(range(63, 70)) | set(range(130, 137))
    side, _ = _layer(topics["/bev/gt/sidewalk"][0][1])
    assert np.array_equal(np.flatnonzero(side[:, 200]), np.arange(133, 154))  # y 105 .. 108
    cross, _ = _layer(topics["/bev/gt/ped_crossing"][0][1])
    assert np.array_equal(np.flatnonzero(cross.any(axis=0)), np.arange(333, 361))  # x 120 .. 124 from x = 100


def test_sweeps_add_the_frames_between_key_frames(dataset, tmp_path):
    assert main(["import", "nuscenes", str(dataset), "--version", "v1.0-mini", "--scene", "scene-0103",
                 "--sweeps", "--out", str(tmp_path)]) == 0
    topics, meta = _read(tmp_path / "scene-0103")
    assert len(topics["/cameras/front/image_raw/compressed"]) == 4 + 3
    assert len(topics["/bev/gt/drivable"]) == 4
    assert "/bev/gt/vehicle" in topics  # the version has boxes; this scene has none in view: all 0


def _fails(capsys, *argv) -> str:
    assert main(["import", "nuscenes", *argv]) == 1
    return capsys.readouterr().err


def test_bad_input_is_a_clear_error_and_writes_nothing(dataset, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["--scene", "scene-0061", "--out", str(out)]
    err = _fails(capsys, str(dataset), "--version", "v1.0-trainval", *args)
    assert "error:" in err and "holds v1.0-mini, not v1.0-trainval" in err
    err = _fails(capsys, str(dataset), "--version", "v1.0-mini", "--scene", "scene-9999", "--out", str(out))
    assert "no scene scene-9999" in err and "scene-0061" in err
    err = _fails(capsys, str(dataset), "--version", "v1.0-mini", "--split", "val", "--out", str(out))
    assert "split 'val' is a split of v1.0-trainval" in err
    broken = tmp_path / "broken"
    shutil.copytree(dataset / "v1.0-mini", broken / "v1.0-mini")
    (broken / "v1.0-mini" / "ego_pose.json").unlink()
    err = _fails(capsys, str(broken), "--version", "v1.0-mini", *args)
    assert "lacks the table(s) ego_pose.json" in err
    (broken / "v1.0-mini" / "ego_pose.json").write_text("[{")
    err = _fails(capsys, str(broken), "--version", "v1.0-mini", *args)
    assert "ego_pose.json: not valid JSON" in err
    # no image at all: the scene fails, nothing is left under its name or a temporary one
    shutil.copy(dataset / "v1.0-mini" / "ego_pose.json", broken / "v1.0-mini" / "ego_pose.json")
    err = _fails(capsys, str(broken), "--version", "v1.0-mini", *args)
    assert "scene-0061: no image could be read (24 missing" in err
    assert not out.exists() or not any(out.iterdir())


def test_missing_and_corrupt_images_are_skipped_and_counted(dataset, tmp_path, capsys):
    data = tmp_path / "nus"
    shutil.copytree(dataset, data)
    jpgs = sorted((data / "samples" / "CAM_FRONT").glob("scene-0061__*.jpg"))
    jpgs[0].unlink()
    jpgs[1].write_bytes(jpgs[1].read_bytes()[:300])  # truncated
    raw = bytearray(jpgs[2].read_bytes())
    dht = raw.index(b"\xff\xc4") + 5  # a Huffman table: header and end marker intact, the decoder refuses it
    raw[dht:dht + 16] = b"\xff" * 16
    jpgs[2].write_bytes(bytes(raw))
    assert main(["import", "nuscenes", str(data), "--version", "v1.0-mini", "--scene", "scene-0061",
                 "--out", str(tmp_path / "out")]) == 0
    cap = capsys.readouterr()
    assert "21 images" in cap.out and "(1 missing, 2 corrupt images skipped)" in cap.out
    assert cap.err.count("note: skipped") == 3
    topics, _ = _read(tmp_path / "out" / "scene-0061")
    assert len(topics["/cameras/front/image_raw/compressed"]) == 1


def test_without_the_map_expansion_the_map_classes_are_unscored_with_a_note(dataset, tmp_path, capsys):
    data = tmp_path / "nus"
    shutil.copytree(dataset, data, ignore=shutil.ignore_patterns("maps"))
    assert main(["import", "nuscenes", str(data), "--version", "v1.0-mini", "--scene", "scene-0061",
                 "--out", str(tmp_path / "out")]) == 0
    assert "note: no map expansion" in capsys.readouterr().err
    topics, meta = _read(tmp_path / "out" / "scene-0061")
    assert sorted(t for t in topics if t.startswith("/bev/gt/")) == ["/bev/gt/pedestrian", "/bev/gt/vehicle"]
    assert '\\"unscored\\": [\\"drivable\\"' in meta or '"unscored": ["drivable"' in meta


def test_an_existing_bag_is_not_replaced_without_force(imported, dataset, capsys):
    err = _fails(capsys, str(dataset), "--version", "v1.0-mini", "--scene", "scene-0061", "--out", str(imported.parent))
    assert "exists; pass --force" in err


def test_round_trip_into_replay(imported, tmp_path, capsys):
    """import -> ``bev-bag replay`` scores the imported drive (where the reader reads compressed images)."""
    status = main(["replay", str(imported), "--out", str(tmp_path / "r"), "--quiet", "--method", "segipm",
                   "--input", "rgb", "--no-report", "--frames-every", "100"])
    err = capsys.readouterr().err
    if status != 0 and "no image topics" in err:
        pytest.skip("this checkout's bag reader does not read <image_topic>/compressed yet")
    assert status == 0, err
    metrics = json.loads((tmp_path / "r" / "metrics.json").read_text())
    assert metrics["complete"] is True
    # the HDMapNet protocol's table: IoU per class on the whole grid, and by 10 m range band
    # (the surround grid's cells reach 33.5 m: four bands)
    gt = ["drivable", "ped_crossing", "sidewalk", "lane_divider", "road_boundary", "vehicle", "pedestrian"]
    assert set(gt) <= set(metrics["classes"])
    assert list(metrics["iou_by_range"]) == ["0-10", "10-20", "20-30", "30-40"]
    assert all(set(gt) <= set(row) for row in metrics["iou_by_range"].values())
