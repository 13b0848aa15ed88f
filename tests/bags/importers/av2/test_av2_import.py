"""``bev-bag import av2`` on a miniature Argoverse 2 sensor log written by the test (Feather tables via
pyarrow, small JPEGs, a vector map). Skipped without pyarrow (``BEV_DEVKIT_PATH`` is searched too)."""

from __future__ import annotations

import json
import os
import sys

import cv2
import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from bags.cli.main import main
from msg_adapters import occupancy_grid_to_layer

for _p in filter(None, os.environ.get("BEV_DEVKIT_PATH", "").split(os.pathsep)):
    if _p not in sys.path:
        sys.path.append(_p)
feather = pytest.importorskip("pyarrow.feather", reason="pyarrow not installed")
pa = pytest.importorskip("pyarrow")

T0 = 315967376859506000
CAMS = ("ring_front_center", "ring_front_left")


def _table(path, cols):
    path.parent.mkdir(parents=True, exist_ok=True)
    feather.write_feather(pa.table(cols), str(path))


def _log(root):
    log = root / "val" / "0c6e62d7-bdfa-3061-8d3d-03b13aa21f68"  # the dataset's layout: <split>/<log_id>/
    ident = dict(qw=[1.0] * 2, qx=[0.0] * 2, qy=[0.0] * 2, qz=[0.0] * 2)
    # optical frame: z forward = ego x, x right = ego -y, y down = ego -z
    _table(log / "calibration" / "egovehicle_SE3_sensor.feather",
           dict(sensor_name=list(CAMS), qw=[0.5] * 2, qx=[-0.5] * 2, qy=[0.5] * 2, qz=[-0.5] * 2,
                tx_m=[1.6, 1.5], ty_m=[0.0, 0.3], tz_m=[1.4] * 2))
    _table(log / "calibration" / "intrinsics.feather",
           dict(sensor_name=list(CAMS), fx_px=[100.0] * 2, fy_px=[100.0] * 2, cx_px=[80.0] * 2, cy_px=[45.0] * 2,
                k1=[0.0] * 2, k2=[0.0] * 2, k3=[0.0] * 2, height_px=[90] * 2, width_px=[160] * 2))
    stamps = [T0 + k * 100_000_000 for k in range(3)]
    _table(log / "city_SE3_egovehicle.feather", dict(timestamp_ns=stamps, qw=[1.0] * 3, qx=[0.0] * 3, qy=[0.0] * 3,
                                                     qz=[0.0] * 3, tx_m=[100.0 + k for k in range(3)],
                                                     ty_m=[100.0] * 3, tz_m=[0.0] * 3))
    _table(log / "annotations.feather",
           dict(timestamp_ns=[stamps[0], stamps[0]], track_uuid=["a", "b"], category=["REGULAR_VEHICLE", "PEDESTRIAN"],
                length_m=[4.0, 0.6], width_m=[2.0, 0.6], height_m=[1.5, 1.7], tx_m=[10.0, 5.0], ty_m=[0.0, 6.0],
                tz_m=[0.8, 0.8], num_interior_pts=[20, 0], **ident))
    ok, jpg = cv2.imencode(".jpg", np.full((90, 160, 3), 120, np.uint8))
    for cam in CAMS:
        for s in stamps:
            p = log / "sensors" / "cameras" / cam / f"{s + 5_000_000}.jpg"
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(jpg.tobytes())

    def pts(*xy):
        return [{"x": x, "y": y, "z": 0.0} for x, y in xy]

    vmap = {"drivable_areas": {"1": {"id": 1, "area_boundary": pts((0, 95), (1000, 95), (1000, 105), (0, 105))}},
            "pedestrian_crossings": {"2": {"id": 2, "edge1": pts((120, 95), (120, 105)), "edge2": pts((124, 95), (124, 105))}},
            "lane_segments": {"3": {"id": 3, "left_lane_boundary": pts((0, 100.3), (1000, 100.3)),
                                    "right_lane_boundary": pts((0, 95), (1000, 95)),
                                    "left_lane_mark_type": "DASHED_WHITE", "right_lane_mark_type": "NONE"}}}
    (log / "map").mkdir()
    (log / "map" / f"log_map_archive_{log.name}____PIT_city_31785.json").write_text(json.dumps(vmap))
    return log


def test_an_av2_log_imports_with_its_ground_truth(tmp_path, capsys):
    log = _log(tmp_path)
    assert main(["import", "av2", str(log), "--out", str(tmp_path / "out")]) == 0
    assert "CC BY-NC-SA 4.0" in capsys.readouterr().out
    bag = tmp_path / "out" / log.name
    topics: dict[str, list] = {}
    with AnyReader([bag]) as r:
        for conn, t, raw in r.messages():
            topics.setdefault(conn.topic, []).append((t, r.deserialize(raw, conn.msgtype)))
    assert len(topics["/cameras/ring_front_center/image_raw/compressed"]) == 3
    assert sorted(t[len("/bev/gt/"):] for t in topics if t.startswith("/bev/gt/")) == [
        "drivable", "lane_divider", "ped_crossing", "pedestrian", "road_boundary", "vehicle"]
    assert [t for t, _ in topics["/bev/gt/drivable"]] == [T0]  # the annotated sweeps are the key frames
    layer = {k: occupancy_grid_to_layer(topics[f"/bev/gt/{k}"][0][1]) for k in ("drivable", "vehicle", "pedestrian",
                                                                                "lane_divider", "ped_crossing")}
    assert np.array_equal(np.flatnonzero((layer["drivable"][0] >= 0.5).any(axis=1)), np.arange(67, 134))
    veh = layer["vehicle"][0] >= 0.5
    want = np.zeros_like(veh)
    want[93:108, 253:281] = True
    assert np.array_equal(veh, want)
    assert not layer["pedestrian"][1].all() and not (layer["pedestrian"][0] >= 0.5).any()  # no lidar point: -1
    assert set(np.flatnonzero(layer["lane_divider"][0][:, 200] >= 0.5)) <= set(range(98, 106))  # only the painted one
    assert np.array_equal(np.flatnonzero((layer["ped_crossing"][0] >= 0.5).any(axis=0)), np.arange(333, 361))
    meta = (bag / "metadata.yaml").read_text()
    assert "sidewalk" in meta and "Argoverse 2" in meta
    assert "bev_mapper.split: val" in meta  # the folder it lies in, for bev-train --split


def test_a_log_without_calibration_is_an_error(tmp_path, capsys):
    log = _log(tmp_path)
    (log / "calibration" / "intrinsics.feather").unlink()
    assert main(["import", "av2", str(log), "--out", str(tmp_path / "out")]) == 1
    assert "intrinsics.feather not found" in capsys.readouterr().err
    assert not (tmp_path / "out" / log.name).exists()
