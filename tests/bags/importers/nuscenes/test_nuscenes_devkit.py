"""The importer's GT against the nuScenes devkit on the miniature dataset: the devkit's own rasteriser
(``NuScenesMapExplorer.get_map_mask``) for the filled layers, and HDMapNet's rasterisation (its code,
over the devkit's geometry) for the dividers and the road outline; the split lists against the
devkit's. Skipped where the devkit is not importable; ``BEV_DEVKIT_PATH`` (e.g. a
``pip install --target`` folder holding nuscenes-devkit and shapely) is searched after the venv.
"""

from __future__ import annotations

import json
import math
import os
import sys

import cv2
import numpy as np
import pytest
from nuscenes_helpers import write_nuscenes
from rosbags.highlevel import AnyReader

from bags.cli.main import main
from bags.importers.nuscenes.splits import split_scenes
from msg_adapters import occupancy_grid_to_layer

for _p in filter(None, os.environ.get("BEV_DEVKIT_PATH", "").split(os.pathsep)):
    if _p not in sys.path:
        sys.path.append(_p)  # after the venv: its numpy and OpenCV stay the ones used
map_api = pytest.importorskip("nuscenes.map_expansion.map_api", reason="nuscenes-devkit (and shapely) not installed")
splits = pytest.importorskip("nuscenes.utils.splits")
from shapely import affinity, ops  # noqa: E402  (the devkit's dependency, present when it imports)
from shapely.geometry import MultiLineString, MultiPolygon, box  # noqa: E402

CANVAS, PATCH = (200, 400), (30.0, 60.0)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = write_nuscenes(tmp_path_factory.mktemp("nus"), sweeps=False)
    out = tmp_path_factory.mktemp("bags")
    assert main(["import", "nuscenes", str(root), "--version", "v1.0-mini", "--scene", "scene-0061",
                 "--scene", "scene-0103", "--out", str(out)]) == 0
    nmap = map_api.NuScenesMap(dataroot=str(root), map_name="boston-seaport")
    tables = {n: json.loads((root / "v1.0-mini" / f"{n}.json").read_text())
              for n in ("sample_data", "ego_pose", "calibrated_sensor", "sensor")}
    return root, out, nmap, tables


def _frames(bag, tables):
    """``[(ego pose record of the key frame's LIDAR_TOP, {class: (present, known)})]`` of a bag."""
    lidar = {s["token"] for s in tables["sensor"] if s["channel"] == "LIDAR_TOP"}
    cs = {c["token"] for c in tables["calibrated_sensor"] if c["sensor_token"] in lidar}
    poses = {e["token"]: e for e in tables["ego_pose"]}
    by_stamp = {sd["timestamp"] * 1000: poses[sd["ego_pose_token"]] for sd in tables["sample_data"]
                if sd["calibrated_sensor_token"] in cs}
    layers: dict[int, dict] = {}
    with AnyReader([bag]) as r:
        for conn, log_ns, raw in r.messages():
            if conn.topic.startswith("/bev/gt/"):
                probs, known = occupancy_grid_to_layer(r.deserialize(raw, conn.msgtype))
                layers.setdefault(log_ns, {})[conn.topic.rsplit("/", 1)[1]] = (probs >= 0.5, known)
    return [(by_stamp[s], layers[s]) for s in sorted(layers)]


def _patch(pose):
    rot = np.array(pose["rotation"])  # wxyz
    w, x, y, z = rot
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))  # quaternion_yaw
    return (pose["translation"][0], pose["translation"][1], *PATCH), yaw / np.pi * 180


def _hdmapnet_lines(lines, thickness=5):
    """HDMapNet's ``line_geom_to_mask`` (data/rasterize.py), the semantic mask of its instance mask."""
    patch_h, patch_w = PATCH
    local = box(-patch_w / 2, -patch_h / 2, patch_w / 2, patch_h / 2)
    mask = np.zeros(CANVAS, np.uint8)
    for line in lines:
        new = line.intersection(local)
        if new.is_empty:
            continue
        new = affinity.affine_transform(new, [1.0, 0.0, 0.0, 1.0, patch_w / 2, patch_h / 2])
        new = affinity.scale(new, xfact=CANVAS[1] / patch_w, yfact=CANVAS[0] / patch_h, origin=(0, 0))
        for single in getattr(new, "geoms", [new]):
            coords = np.asarray(list(single.coords), np.int32).reshape((-1, 2))
            if len(coords) >= 2:
                cv2.polylines(mask, [coords], False, color=1, thickness=thickness)
    return mask.astype(bool)


def _hdmapnet_contours(nmap, patch_box, angle):
    """HDMapNet's ``poly_geoms_to_vectors``: the outline of road segments and lanes, 0.2 m off the border."""
    ex = nmap.explorer
    polys = ex._get_layer_polygon(patch_box, angle, "road_segment") + ex._get_layer_polygon(patch_box, angle, "lane")
    union = ops.unary_union(polys)
    if union.geom_type != "MultiPolygon":
        union = MultiPolygon([union])
    mx, my = PATCH[1] / 2, PATCH[0] / 2
    local = box(-mx + 0.2, -my + 0.2, mx - 0.2, my - 0.2)
    lines = []
    for poly in union.geoms:
        for ring in [poly.exterior, *poly.interiors]:
            part = ring.intersection(local)
            if isinstance(part, MultiLineString):
                part = ops.linemerge(part)
            lines.append(part)
    return _hdmapnet_lines(lines)


def _within_one_cell(a, b):
    """Every cell of ``a`` is in ``b`` or next to one of its cells."""
    return not (a & ~cv2.dilate(b.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)).any()


@pytest.mark.parametrize("scene", ["scene-0061", "scene-0103"])
def test_filled_layers_equal_the_devkits_get_map_mask(bags, scene):
    root, out, nmap, tables = bags
    for pose, layers in _frames(out / scene, tables):
        patch_box, angle = _patch(pose)
        masks = nmap.get_map_mask(patch_box, angle, ["drivable_area", "ped_crossing", "walkway"], CANVAS).astype(bool)
        for mask, cls in zip(masks, ("drivable", "ped_crossing", "sidewalk")):
            assert np.array_equal(layers[cls][0], mask), (scene, cls, int((layers[cls][0] != mask).sum()))
        assert masks[0].any()


@pytest.mark.parametrize("scene", ["scene-0061", "scene-0103"])
def test_dividers_equal_hdmapnets_and_the_road_outline_is_close(bags, scene):
    root, out, nmap, tables = bags
    for pose, layers in _frames(out / scene, tables):
        patch_box, angle = _patch(pose)
        lines = [*nmap.explorer._get_layer_line(patch_box, angle, "road_divider"),
                 *nmap.explorer._get_layer_line(patch_box, angle, "lane_divider")]
        want = _hdmapnet_lines(lines)
        got = layers["lane_divider"][0]
        # equal but for the float noise of the clipped ends (HDMapNet truncates 399.99999 to 399, the exact
        # clip gives 400), which tilts a line by a fraction of a cell: every differing cell touches the other mask
        assert _within_one_cell(got, want) and _within_one_cell(want, got), scene
        assert (got != want).sum() <= 0.1 * want.sum(), (scene, int((got != want).sum()))
        want = _hdmapnet_contours(nmap, patch_box, angle)
        got = layers["road_boundary"][0]
        iou = (got & want).sum() / max((got | want).sum(), 1)
        assert iou >= 0.85, (scene, iou)  # traced on a 4x finer canvas: within a quarter cell


def test_the_split_lists_equal_the_devkits():
    for split, version in (("val", "v1.0-trainval"), ("test", "v1.0-test"), ("mini_train", "v1.0-mini"),
                           ("mini_val", "v1.0-mini")):
        names = sorted(getattr(splits, split))
        assert sorted(split_scenes(split, version, names + ["scene-9999"])) == names
    trainval = sorted(splits.train + splits.val)
    assert sorted(split_scenes("train", "v1.0-trainval", trainval)) == sorted(splits.train)
