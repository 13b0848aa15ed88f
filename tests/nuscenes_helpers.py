"""A miniature nuScenes dataset written by the tests (and ``bench/bench_import.py``): the JSON tables
of one version, small JPEGs encoded with OpenCV and a map expansion, in nuScenes' layout.

Geometry (for hand-computed cells): the map of ``boston-seaport`` holds a straight road along +x
(``drivable_area`` and ``road_segment`` y in [95, 105], two ``lane`` halves), a road divider at
y = 100.3, a lane divider at y = 102.8, a crossing x in [120, 124], a walkway y in [105, 108], and a
drivable square with a hole at x in [200, 230]. Scene ``scene-0061`` drives along the road from
(100, 100) at 5 m/s, yaw 0; scene ``scene-0103`` turns at yaw 30 degrees from (205, 98). Each key
frame of scene-0061 has a car 10 m ahead (4 m x 2 m, visibility 4), a pedestrian at (5, 6) and a car
at (-12, -6) with visibility 1 and no lidar points (left out by the default filter).
"""

from __future__ import annotations

import functools
import json
import math
from pathlib import Path

import cv2
import numpy as np

from bev_mapper_core.geometry.rig import surround6
from bev_mapper_core.geometry.transforms import rot_to_quat

CHANNELS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_BACK_RIGHT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_FRONT_LEFT")
T0_US = 1532402927647951
IMG_W, IMG_H = 160, 90  # nuScenes' 1600 x 900 / 10


def _q(yaw: float) -> list[float]:
    """wxyz of a yaw rotation."""
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]


class _Tok:
    def __init__(self) -> None:
        self.n = 0

    def __call__(self, kind: str) -> str:
        self.n += 1
        return f"{kind}{self.n:06d}"


def _rect(x0, y0, x1, y1):
    return [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]


def write_map(root: Path, location: str = "boston-seaport", version: str = "1.3", clutter: int = 0) -> Path:
    """The map expansion ``maps/expansion/<location>.json`` (see the module docstring); ``clutter``
    adds that many random walkway octagons and as many lane dividers over 1 km x 1 km, for a map of
    a real one's size (``bench/bench_import.py``)."""
    tok = _Tok()
    m = {k: [] for k in ("polygon", "line", "node", "drivable_area", "road_segment", "road_block", "lane",
                         "ped_crossing", "walkway", "stop_line", "carpark_area", "road_divider", "lane_divider",
                         "traffic_light", "lane_connector")}
    m.update(version=version, canvas_edge=[3000.0, 3000.0], arcline_path_3={}, connectivity={})

    def nodes(pts):
        out = []
        for x, y in pts:
            t = tok("n")
            m["node"].append({"token": t, "x": float(x), "y": float(y)})
            out.append(t)
        return out

    def polygon(ext, holes=()):
        t = tok("p")
        m["polygon"].append({"token": t, "exterior_node_tokens": nodes(ext),
                             "holes": [{"node_tokens": nodes(h)} for h in holes]})
        return t

    def line(pts):
        t = tok("l")
        m["line"].append({"token": t, "node_tokens": nodes(pts)})
        return t

    road = _rect(0, 95, 1000, 105)
    square = _rect(200, 80, 230, 110)
    hole = _rect(210, 88, 220, 98)
    m["drivable_area"].append({"token": tok("da"), "polygon_tokens": [polygon(road), polygon(square, [hole])]})
    seg = tok("rs")
    m["road_segment"].append({"token": seg, "polygon_token": polygon(road), "is_intersection": False,
                              "drivable_area_token": ""})
    m["road_segment"].append({"token": tok("rs"), "polygon_token": polygon(square, [hole]), "is_intersection": True,
                              "drivable_area_token": ""})
    for y0, y1 in ((95, 100.3), (100.3, 105)):
        m["lane"].append({"token": tok("ln"), "polygon_token": polygon(_rect(0, y0, 1000, y1)), "lane_type": "CAR",
                          "from_edge_line_token": "", "to_edge_line_token": "", "left_lane_divider_segments": [],
                          "right_lane_divider_segments": []})
    m["ped_crossing"].append({"token": tok("pc"), "polygon_token": polygon(_rect(120, 95, 124, 105)),
                              "road_segment_token": seg})
    # a slanted crossing (not axis-aligned) for the devkit comparison
    m["ped_crossing"].append({"token": tok("pc"), "polygon_token": polygon([(212, 100), (218, 102), (216, 108), (210, 106)]),
                              "road_segment_token": seg})
    m["walkway"].append({"token": tok("ww"), "polygon_token": polygon(_rect(0, 105, 1000, 108))})
    m["road_divider"].append({"token": tok("rd"), "line_token": line([(0, 100.3), (500, 100.3), (1000, 100.3)]),
                              "road_segment_token": seg})
    m["lane_divider"].append({"token": tok("ld"), "line_token": line([(0, 102.8), (1000, 102.8)]),
                              "lane_divider_segments": []})
    m["lane_divider"].append({"token": tok("ld"), "line_token": line([(203, 82), (214, 84), (226, 109)]),
                              "lane_divider_segments": []})
    rng = np.random.default_rng(0)
    for _ in range(clutter):
        cx, cy = rng.uniform(-200, 800, 2)
        r = rng.uniform(1, 6)
        ang = np.linspace(0, 2 * np.pi, 8, endpoint=False)
        m["walkway"].append({"token": tok("ww"), "polygon_token": polygon(np.c_[cx + r * np.cos(ang), cy + r * np.sin(ang)])})
        pts = np.cumsum(rng.uniform(-5, 5, (6, 2)), axis=0) + (cx, cy)
        m["lane_divider"].append({"token": tok("ld"), "line_token": line(pts), "lane_divider_segments": []})
    path = root / "maps" / "expansion" / f"{location}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(m))
    return path


def _jpeg(seed: int) -> bytes:
    rng = np.random.default_rng(seed)
    img = np.zeros((IMG_H, IMG_W, 3), np.uint8)
    img[:] = rng.integers(0, 255, 3)
    img[IMG_H // 2:] = (90, 90, 90)
    ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
    assert ok
    return enc.tobytes()


def write_nuscenes(root: Path, version: str = "v1.0-mini", *, samples: int = 4, scenes: int = 2,
                   sweeps: bool = True, with_map: bool = True, image_size: tuple[int, int] = (IMG_W, IMG_H),
                   clutter: int = 0) -> Path:
    """Write the miniature dataset into ``root`` (see the module docstring); ``scenes`` beyond two
    repeat scene-0061's drive under the names scene-1000, scene-1001, ... Returns ``root``."""
    root = Path(root)
    tok = _Tok()
    t: dict[str, list] = {k: [] for k in ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor",
                                          "log", "sample_annotation", "instance", "category", "visibility",
                                          "attribute", "map")}
    t["visibility"] = [{"token": str(i), "level": lvl, "description": ""}
                       for i, lvl in enumerate(("v0-40", "v40-60", "v60-80", "v80-100"), 1)]
    cats = {}
    for name in ("vehicle.car", "human.pedestrian.adult", "movable_object.barrier"):
        cats[name] = tok("cat")
        t["category"].append({"token": cats[name], "name": name, "description": "", "index": len(cats)})
    w, h = image_size
    scale = w / 1600.0
    sensors = {}
    for ch in (*CHANNELS, "LIDAR_TOP"):
        sensors[ch] = tok("sen")
        t["sensor"].append({"token": sensors[ch], "channel": ch, "modality": "lidar" if ch == "LIDAR_TOP" else "camera"})
    rig = surround6()
    log_tok = tok("log")
    t["log"].append({"token": log_tok, "logfile": "n015-2018-07-24-11-22-45+0800", "vehicle": "n015",
                     "date_captured": "2018-07-24", "location": "boston-seaport"})
    t["map"].append({"token": tok("map"), "log_tokens": [log_tok], "category": "semantic_prior", "filename": ""})
    calib = {}
    for ch, cam in zip(CHANNELS, rig.cameras):
        T = cam.ego_from_cam_array
        x, y, z, qw = rot_to_quat(T[:3, :3])
        K = np.array(cam.model.K) * scale
        K[2, 2] = 1.0
        calib[ch] = tok("cs")
        t["calibrated_sensor"].append({"token": calib[ch], "sensor_token": sensors[ch], "translation": T[:3, 3].tolist(),
                                       "rotation": [qw, x, y, z], "camera_intrinsic": K.tolist()})
    calib["LIDAR_TOP"] = tok("cs")
    t["calibrated_sensor"].append({"token": calib["LIDAR_TOP"], "sensor_token": sensors["LIDAR_TOP"],
                                   "translation": [0.94, 0.0, 1.84], "rotation": [0.7071, 0.0, 0.0, -0.7071],
                                   "camera_intrinsic": []})
    names = ["scene-0061", "scene-0103"][:scenes] + [f"scene-{1000 + i}" for i in range(max(0, scenes - 2))]
    jpeg_no = 0
    for si, name in enumerate(names):
        start, yaw = ((205.0, 98.0), math.radians(30)) if name == "scene-0103" else ((100.0, 100.0), 0.0)
        t_us = T0_US + si * 100_000_000
        sc_tok = tok("sc")
        sample_toks = [tok("s") for _ in range(samples)]
        prev_sd: dict[str, str] = {}

        def ego(stamp_us, start=start, yaw=yaw, t_us=t_us):
            d = 5.0 * (stamp_us - t_us) * 1e-6
            ep = tok("ep")
            t["ego_pose"].append({"token": ep, "timestamp": stamp_us, "rotation": _q(yaw),
                                  "translation": [start[0] + d * math.cos(yaw), start[1] + d * math.sin(yaw), 0.0]})
            return ep

        for k, s_tok in enumerate(sample_toks):
            stamp = t_us + k * 500_000
            t["sample"].append({"token": s_tok, "timestamp": stamp, "scene_token": sc_tok,
                                "prev": sample_toks[k - 1] if k else "",
                                "next": sample_toks[k + 1] if k + 1 < samples else ""})
            frames = [("LIDAR_TOP", stamp, True)]
            for ci, ch in enumerate(CHANNELS):
                frames.append((ch, stamp - 8_000 * ci, True))  # the cameras fire over ~40 ms
                if sweeps and k + 1 < samples:
                    frames.append((ch, stamp + 250_000 - 8_000 * ci, False))  # a sweep between key frames
            for ch, st, key in frames:
                sd = tok("sd")
                folder = "samples" if key else "sweeps"
                if ch == "LIDAR_TOP":
                    fname = f"{folder}/LIDAR_TOP/{name}__LIDAR_TOP__{st}.pcd.bin"
                    fmt, ww, hh = "pcd", 0, 0
                else:
                    fname = f"{folder}/{ch}/{name}__{ch}__{st}.jpg"
                    fmt, ww, hh = "jpg", w, h
                    p = root / fname
                    p.parent.mkdir(parents=True, exist_ok=True)
                    p.write_bytes(_jpeg(jpeg_no) if (w, h) == (IMG_W, IMG_H) else _sized_jpeg(jpeg_no, w, h))
                    jpeg_no += 1
                t["sample_data"].append({"token": sd, "sample_token": s_tok, "ego_pose_token": ego(st),
                                         "calibrated_sensor_token": calib[ch], "timestamp": st, "fileformat": fmt,
                                         "is_key_frame": key, "height": hh, "width": ww, "filename": fname,
                                         "prev": prev_sd.get(ch, ""), "next": ""})
                prev_sd[ch] = sd
            if name != "scene-0103":
                d = 5.0 * k * 0.5
                for cat, (x, y), size, vis, pts in (("vehicle.car", (10, 0), [2.0, 4.0, 1.5], "4", 10),
                                                    ("human.pedestrian.adult", (5, 6), [0.6, 0.6, 1.7], "3", 3),
                                                    ("vehicle.car", (-12, -6), [2.0, 4.0, 1.5], "1", 0),
                                                    ("movable_object.barrier", (0, -8), [1.0, 1.0, 1.0], "4", 5)):
                    inst = tok("in")
                    t["instance"].append({"token": inst, "category_token": cats[cat], "nbr_annotations": 1,
                                          "first_annotation_token": "", "last_annotation_token": ""})
                    t["sample_annotation"].append({
                        "token": tok("an"), "sample_token": s_tok, "instance_token": inst, "visibility_token": vis,
                        "attribute_tokens": [], "translation": [start[0] + d + x, start[1] + y, 0.8], "size": size,
                        "rotation": _q(0.0), "prev": "", "next": "", "num_lidar_pts": pts, "num_radar_pts": 0})
        t["scene"].append({"token": sc_tok, "log_token": log_tok, "nbr_samples": samples,
                           "first_sample_token": sample_toks[0], "last_sample_token": sample_toks[-1],
                           "name": name, "description": f"miniature {name}"})
    # link the sample_data chains forward
    by_tok = {r["token"]: r for r in t["sample_data"]}
    for r in t["sample_data"]:
        if r["prev"]:
            by_tok[r["prev"]]["next"] = r["token"]
    folder = root / version
    folder.mkdir(parents=True, exist_ok=True)
    for name, records in t.items():
        (folder / f"{name}.json").write_text(json.dumps(records))
    if with_map:
        write_map(root, clutter=clutter)
    return root


@functools.lru_cache(maxsize=16)
def _sized(seed: int, w: int, h: int) -> bytes:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
    img = cv2.GaussianBlur(img, (0, 0), 3)  # photo-like entropy, not noise
    ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    assert ok
    return enc.tobytes()


def _sized_jpeg(seed: int, w: int, h: int) -> bytes:
    """A JPEG of ``w`` x ``h``: one of 12 encoded once each (the files differ by name only)."""
    return _sized(seed % 12, w, h)
