"""bev-bag replay and info: offline mapping of bags, outputs, metrics, damage, determinism."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from bag_helpers import SMALL_DRIVE_FRAMES, replay_ipm, synth_small

from bags.cli.main import main
from bags.io import topics as T
from bags.io.reader import BagReader
from bags.io.writer import BagWriter
from bags.replay import BAG_DIR, FRAMES_DIR, IMAGE_TOPIC, METRICS_FILE
from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, bev_picture
from bev_mapper_core.mapper import MapperConfig, create_mapper
from msg_adapters import image_to_rgb, occupancy_grid_to_layer

pytest.importorskip("bev_mapper_core.synth")

GRID = BevGrid(-20.0, 20.0, -10.0, 10.0, 0.25)
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
N = SMALL_DRIVE_FRAMES  # frames of the shared drive


replay = replay_ipm  # bev-bag replay with IPM: these bags use a small grid no shipped weights fit


def load_metrics(out: Path) -> dict:
    return json.loads((out / METRICS_FILE).read_text())


def without_run_details(m: dict) -> dict:
    m = dict(m)
    for key in ("latency_ms", "score_process", "bag"):
        m.pop(key)
    return m


def read_grids(bag: Path) -> dict[str, dict[int, np.ndarray]]:
    """topic -> stamp -> int8 data of every OccupancyGrid in an output bag."""
    out: dict[str, dict[int, np.ndarray]] = {}
    with BagReader(bag) as r:
        topics = [t for t, s in r.topics.items() if s.msgtype == T.GRID_TYPE]
        for m in r.messages(topics):
            stamp = m.msg.header.stamp.sec * 1_000_000_000 + m.msg.header.stamp.nanosec
            out.setdefault(m.topic, {})[stamp] = np.asarray(m.msg.data, np.int8).copy()
    return out


def no_partials(*dirs: Path) -> list[Path]:
    return [p for d in dirs for p in d.rglob("*partial*")]


@pytest.fixture(scope="module")
def drive(small_drive_mcap, small_drive_sqlite3):
    """The shared drive as MCAP and sqlite3 bags, replayed (mcap with pictures and a GIF).

    (roots, bags, outs); the bags and outputs are shared with other modules: read-only.
    """
    (mcap, out_mcap), (sqlite3, out_sqlite3) = small_drive_mcap, small_drive_sqlite3
    roots = (mcap.parent, sqlite3.parent)
    return roots, {"mcap": mcap, "sqlite3": sqlite3}, {"mcap": out_mcap, "sqlite3": out_sqlite3}


def test_mcap_and_sqlite3_replays_agree(drive):
    roots, bags, outs = drive
    a, b = load_metrics(outs["mcap"]), load_metrics(outs["sqlite3"])
    assert without_run_details(a) == without_run_details(b)
    assert _grids_equal(read_grids(outs["mcap"] / BAG_DIR), read_grids(outs["sqlite3"] / BAG_DIR))


def _grids_equal(x, y) -> bool:
    return x.keys() == y.keys() and all(
        x[t].keys() == y[t].keys() and all(np.array_equal(x[t][s], y[t][s]) for s in x[t])
        for t in x)


def test_two_replays_are_identical(drive, tmp_path):
    roots, bags, outs = drive
    assert replay(bags["mcap"], tmp_path / "again", "--no-pictures") == 0
    assert without_run_details(load_metrics(tmp_path / "again")) == \
        without_run_details(load_metrics(outs["mcap"]))
    assert _grids_equal(read_grids(tmp_path / "again" / BAG_DIR), read_grids(outs["mcap"] / BAG_DIR))


def test_metrics_schema_and_ipm_sanity(drive, capsys):
    roots, bags, outs = drive
    m = load_metrics(outs["mcap"])
    assert m["method"] == "ipm" and m["frames"] == N and m["frames_scored"] == N
    assert m["scope"] == "visible" and m["complete"] is True and m["damage"] is None
    assert list(m["classes"]) == list(BEV_CLASS_NAMES)
    for name, c in m["classes"].items():
        assert set(c) >= {"iou", "cd_p", "cd_l", "cd"}, name
    assert m["classes"]["drivable"]["iou"] > 0.8
    assert 0.0 < m["miou"] <= 1.0
    assert m["iou_by_range"] and all("miou" in row for row in m["iou_by_range"].values())
    lat = m["latency_ms"]
    assert 0 < lat["p50"] <= lat["p95"]
    assert m["grid"] == {"x_min": -20.0, "x_max": 20.0, "y_min": -10.0, "y_max": 10.0,
                         "resolution": 0.25}
    json.dumps(m, allow_nan=False)


def test_ground_scope(drive, tmp_path, capsys):
    roots, bags, outs = drive
    assert replay(bags["mcap"], tmp_path / "g", "--no-pictures", "--scope", "ground") == 0
    assert "scope: ground" in capsys.readouterr().out
    g, v = load_metrics(tmp_path / "g"), load_metrics(outs["mcap"])
    assert g["scope_used"] == "ground"
    # IPM cannot see the road under parked cars: scoring only seen ground helps drivable
    assert g["classes"]["drivable"]["iou"] >= v["classes"]["drivable"]["iou"]
    assert g["classes"]["vehicle"] == v["classes"]["vehicle"]  # objects keep the visible scope


def test_output_bag_equals_core_mapper(drive):
    roots, bags, outs = drive
    out_bag = outs["mcap"] / BAG_DIR
    with BagReader(bags["mcap"]) as r:
        rig, grid = r.rig(), r.grid()
        mapper = create_mapper(rig, grid, MapperConfig(method="ipm"))
        expected = {f.stamp_ns: mapper.map(f.labels) for f in r.frames(rgb=False)}
        cams = r.camera_names
    assert grid == GRID and len(expected) == N
    with BagReader(out_bag) as o:
        counts = {t: s.count for t, s in o.topics.items()}
        want = {f"/bev/{c}": N for c in BEV_CLASS_NAMES}
        want.update({IMAGE_TOPIC: N, T.TF_STATIC: 1})
        want.update({T.camera_info_topic(c): N for c in cams})
        assert counts == want
        out_rig = o.rig()  # the copied calibration rebuilds the same rig
        assert out_rig.names == rig.names
        for a, b in zip(out_rig.cameras, rig.cameras):
            assert a.model == b.model
            np.testing.assert_allclose(a.ego_from_cam_array, b.ego_from_cam_array, atol=1e-12)
        for m in o.messages([f"/bev/{c}" for c in BEV_CLASS_NAMES] + [IMAGE_TOPIC]):
            stamp = m.msg.header.stamp.sec * 1_000_000_000 + m.msg.header.stamp.nanosec
            pred = expected[stamp]
            assert m.msg.header.frame_id == "base_link"
            if m.topic == IMAGE_TOPIC:
                want_img = bev_picture(grid, pred.probs, known=pred.known)
                np.testing.assert_array_equal(image_to_rgb(m.msg), want_img)
                continue
            probs, known = occupancy_grid_to_layer(m.msg, grid)
            ci = BEV_CLASS_NAMES.index(m.topic.rsplit("/", 1)[1])
            np.testing.assert_array_equal(
                np.asarray(m.msg.data, np.int8), grid.to_occupancy(pred.probs[ci], pred.known))
            np.testing.assert_array_equal(known, pred.known)


def test_pictures_are_pngs(drive):
    roots, bags, outs = drive
    pics = sorted((outs["mcap"] / FRAMES_DIR).iterdir())
    assert [p.name for p in pics] == [f"frame_{i:04d}.png" for i in range(N)]
    for p in pics:
        assert p.read_bytes()[:8] == PNG_MAGIC
        img = cv2.imread(str(p))
        assert img is not None and img.shape[0] >= 360 and img.shape[1] > img.shape[0] // 2
    gif = outs["mcap"] / "replay.gif"
    if gif.exists():  # Pillow or an OpenCV with a GIF encoder
        assert gif.read_bytes()[:6] in (b"GIF89a", b"GIF87a")
    assert not (outs["sqlite3"] / FRAMES_DIR).exists()
    assert no_partials(*roots) == []


@pytest.mark.slow  # synthesizes and replays a 6-frame drive
def test_truncated_bag_replays_up_to_the_damage(tmp_path, capsys):
    bag = synth_small(tmp_path / "long", frames=6, seed=2)  # ~3.9 MB: several 1 MiB mcap chunks
    data = (bag / "long.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    intact = []
    with pytest.raises(BevMapperError):
        with BagReader(cut) as r:
            intact.extend(f.stamp_ns for f in r.frames(rgb=False))
    assert 1 <= len(intact) < 6
    out = tmp_path / "out"
    assert replay(cut, out, "--picture-every", "1") == 1
    err = capsys.readouterr().err
    assert "error: " in err and "damaged" in err and "Traceback" not in err
    m = load_metrics(out)
    assert m["frames"] == m["frames_scored"] == len(intact)
    assert m["complete"] is False and "damaged" in m["damage"]
    grids = read_grids(out / BAG_DIR)
    assert set(grids) == {f"/bev/{c}" for c in BEV_CLASS_NAMES}
    assert all(sorted(g) == intact for g in grids.values())
    assert len(list((out / FRAMES_DIR).glob("*.png"))) == len(intact)
    assert no_partials(tmp_path) == []
    # stopping before the damage is a complete replay
    assert replay(cut, tmp_path / "first", "--max-frames", "1", "--no-pictures") == 0
    m = load_metrics(tmp_path / "first")
    assert m["frames"] == 1 and m["complete"] is True


def test_bag_without_gt_uses_grid_flags(drive, tmp_path, capsys):
    roots, bags, outs = drive
    src = bags["mcap"]
    nogt = tmp_path / "nogt"
    with BagReader(src) as r, BagWriter(nogt) as w:
        keep = [t for t in r.topics if t.startswith(T.CAMERA_PREFIX) or t == T.TF_STATIC]
        for t in keep:
            w.add_topic(t, r.topics[t].msgtype, latched=t == T.TF_STATIC)
        for m in r.messages(keep):
            w.write(m.topic, m.msg, m.log_ns)
    assert replay(nogt, tmp_path / "o", "--no-pictures", "--grid-res", "0.5",
                  "--classes", "drivable", "vehicle") == 0
    m = load_metrics(tmp_path / "o")
    assert m["frames"] == N and m["frames_scored"] == 0 and m["classes"] == {}
    assert m["grid"]["resolution"] == 0.5
    assert set(read_grids(tmp_path / "o" / BAG_DIR)) == {"/bev/drivable", "/bev/vehicle"}
    assert "no GT layers" in capsys.readouterr().err


def test_replay_errors(drive, tmp_path, capsys):
    roots, bags, outs = drive
    assert replay(tmp_path / "missing", tmp_path / "o") == 1
    assert "error: " in capsys.readouterr().err
    assert replay(bags["mcap"], outs["mcap"]) == 1  # outputs exist, no --force
    err = capsys.readouterr().err
    assert "--force" in err and "Traceback" not in err
    assert replay(bags["mcap"], tmp_path / "o", "--input", "rgb") == 1  # IPM needs labels
    assert "labels" in capsys.readouterr().err
    assert replay(bags["mcap"], tmp_path / "o", "--grid-res", "0.5") == 1  # bag has GT
    assert "grid" in capsys.readouterr().err
    # the default method (Bi-Mapper, shipped weights) does not fit this bag's small grid
    assert main(["replay", str(bags["mcap"]), "--out", str(tmp_path / "o"), "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "error: " in err and "grid" in err and "ipm (label images, any calibrated rig)" in err and "Traceback" not in err
    assert not (tmp_path / "o" / METRICS_FILE).exists() and no_partials(tmp_path) == []


@pytest.mark.parametrize("which", ["mcap", "sqlite3", "file"])
def test_info_lists_cameras_calibration_gt(drive, capsys, which):
    roots, bags, outs = drive
    bag = bags["mcap"] / "drive_mcap.mcap" if which == "file" else bags[which]
    assert main(["info", str(bag)]) == 0
    text = capsys.readouterr().out
    for cam in ("front", "front_right", "back_right", "back", "back_left", "front_left"):
        assert f"  {cam} " in text
    assert text.count("extrinsics in /tf_static") == 6 and "NO extrinsics" not in text
    assert "200x112 plumb_bob" in text
    assert "GT layers (7): " + ", ".join(BEV_CLASS_NAMES) in text
    assert "160x80 cells at 0.25 m" in text and "ground visibility layer: yes" in text
    assert "/cameras/front/labels" in text and "10.00" in text
    assert f"duration:   {(N - 1) / 10:.3f} s" in text


def test_info_json_and_damage(drive, tmp_path, capsys):
    roots, bags, outs = drive
    assert main(["info", "--json", str(outs["mcap"] / BAG_DIR)]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["gt_layers"] == [] and d["storage"] == "mcap"
    counts = {t["topic"]: t["count"] for t in d["topics"]}
    assert counts["/bev/drivable"] == N and counts[IMAGE_TOPIC] == N
    assert all(c["extrinsics"] is not None for c in d["cameras"])
    data = (bags["mcap"] / "drive_mcap.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: int(len(data) * 0.7)])
    assert main(["info", str(tmp_path / "cut.mcap")]) == 1
    captured = capsys.readouterr()
    assert "DAMAGED" in captured.out and captured.err.startswith("error: ")


def test_replay_rgb_with_segipm_equals_the_core(drive, tmp_path):
    """``--input rgb --method segipm`` (the shipped segmenter, then IPM) on the RGB topics: the
    output grids are the core mapper's on the bag's RGB images, scored against the bag's GT."""
    roots, bags, outs = drive
    assert replay(bags["mcap"], tmp_path / "rgb", "--input", "rgb", "--method", "segipm", "--no-pictures") == 0
    m = load_metrics(tmp_path / "rgb")
    assert m["input"] == "rgb" and m["method"] == "segipm" and 0.0 < m["miou"] <= 1.0
    with BagReader(bags["mcap"]) as r:
        mapper = create_mapper(r.rig(), r.grid(), MapperConfig(method="segipm", input_kind="rgb"))
        expected = {f.stamp_ns: mapper.map(f.rgb) for f in r.frames(labels=False)}
    got = read_grids(tmp_path / "rgb" / BAG_DIR)
    for ci, c in enumerate(BEV_CLASS_NAMES):
        for stamp, pred in expected.items():
            np.testing.assert_array_equal(got[f"/bev/{c}"][stamp], GRID.to_occupancy(pred.probs[ci], pred.known))
