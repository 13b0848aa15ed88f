"""One Argoverse 2 sensor log (``<split>/<log_id>/``) as a bag.

* Images: the seven ring cameras' JPEGs (``sensors/cameras/<camera>/<timestamp_ns>.jpg``, ~20 Hz)
  at their stamps, copied; CameraInfo from ``calibration/intrinsics.feather`` (the distortion
  k1..k3 as plumb_bob), mounts from ``calibration/egovehicle_SE3_sensor.feather``.
* Poses: ``city_SE3_egovehicle.feather``.
* Key frames: the annotated lidar sweeps (``annotations.feather``'s stamps, 10 Hz), the grid placed
  at that pose (yaw only, as for nuScenes). From the log's vector map (``map/log_map_archive_*.json``):
  ``drivable`` (``drivable_areas``, filled), ``ped_crossing`` (``pedestrian_crossings``: ``edge1`` then
  ``edge2`` reversed, filled), ``lane_divider`` (lane boundaries with a painted mark, i.e. a
  ``*_mark_type`` other than ``NONE``, 5 cells wide) and ``road_boundary`` (the outline of the
  drivable areas, 5 cells wide); ``vehicle`` and ``pedestrian`` from the cuboids (boxes with at
  least one lidar point; the others -1). Argoverse 2 has no sidewalk layer: ``sidewalk`` is unscored.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.transforms import make_transform, quat_to_rot

from ..drive import ImageRef, ImportCounts, ImportedCamera, ImportedDrive, KeyFrame, write_imported_drive
from ..errors import DatasetLayoutError, MissingDevkitError
from ..raster import HDMAPNET_THICKNESS, MapPolygon, Patch, draw_boundaries, draw_lines, fill_polygons, overlapping

RING_CAMERAS = ("ring_front_center", "ring_front_right", "ring_rear_right", "ring_side_right", "ring_rear_left",
                "ring_side_left", "ring_front_left")
VEHICLES = frozenset({"REGULAR_VEHICLE", "LARGE_VEHICLE", "BUS", "SCHOOL_BUS", "ARTICULATED_BUS", "BOX_TRUCK",
                      "TRUCK", "TRUCK_CAB", "VEHICULAR_TRAILER", "MOTORCYCLE", "BICYCLE"})
PEDESTRIANS = frozenset({"PEDESTRIAN", "STROLLER", "WHEELCHAIR", "OFFICIAL_SIGNALER"})
#: the sensor dataset's splits, the folder a log lies in (``sensor/<split>/<log_id>/``), recorded in its bag
AV2_SPLITS = ("train", "val", "test")
CLASSES = ("drivable", "lane_divider", "ped_crossing", "road_boundary", "vehicle", "pedestrian")
LICENSE = ("Argoverse 2 (Argo AI), CC BY-NC-SA 4.0: non-commercial use, share alike, attribution; this bag is "
           "derived from it and under the same terms (https://www.argoverse.org/about.html#terms-of-use)")


def _feather(path: Path) -> dict[str, list]:
    try:
        from pyarrow import feather
    except ImportError:
        raise MissingDevkitError("bev-bag import av2 reads Argoverse 2's .feather tables with pyarrow: "
                                 "pip install 'bev_mapper_ros[av2]'") from None
    if not path.is_file():
        raise DatasetLayoutError(f"{path} not found (an Argoverse 2 sensor log holds it)")
    try:
        return feather.read_table(path).to_pydict()
    except Exception as exc:  # noqa: BLE001 - pyarrow's errors vary by version
        raise DatasetLayoutError(f"{path}: not a readable Feather table ({exc})") from None


def _se3(row: dict, i: int) -> np.ndarray:
    return make_transform(quat_to_rot(row["qx"][i], row["qy"][i], row["qz"][i], row["qw"][i]),
                          [row["tx_m"][i], row["ty_m"][i], row["tz_m"][i]])


def _xy(points: list[dict]) -> np.ndarray:
    return np.array([(float(p["x"]), float(p["y"])) for p in points], dtype=np.float64).reshape(-1, 2)  # (N, 2)


class VectorMap:
    """The log's vector map, its layers with bounding boxes for the patch query."""

    def __init__(self, path: Path) -> None:
        try:
            obj = json.loads(path.read_text())
            self.drivable = [MapPolygon(_xy(a["area_boundary"])) for a in obj["drivable_areas"].values()]
            self.crossings = [MapPolygon(np.concatenate([_xy(c["edge1"]), _xy(c["edge2"])[::-1]]))
                              for c in obj["pedestrian_crossings"].values()]
            self.dividers = [_xy(ln[f"{side}_lane_boundary"]) for ln in obj["lane_segments"].values()
                             for side in ("left", "right") if ln.get(f"{side}_lane_mark_type", "NONE") != "NONE"]
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise DatasetLayoutError(f"{path}: not a readable Argoverse 2 vector map ({type(exc).__name__}: {exc})") from None

        def boxes(items):
            pts = [p.exterior if isinstance(p, MapPolygon) else p for p in items]
            return np.array([(q[:, 0].min(), q[:, 1].min(), q[:, 0].max(), q[:, 1].max()) for q in pts]).reshape(-1, 4)

        self._boxes = {n: boxes(getattr(self, n)) for n in ("drivable", "crossings", "dividers")}

    def near(self, name: str, patch: Patch) -> list:
        """The items of layer ``name`` whose bounding box meets the patch."""
        items = getattr(self, name)
        return [items[i] for i in overlapping(self._boxes[name], patch.bounds())]

    def masks(self, patch: Patch, thickness: int = HDMAPNET_THICKNESS) -> dict[str, np.ndarray]:
        """``class -> (H, W) bool`` of the map classes (see the module docstring)."""
        drivable = self.near("drivable", patch)
        return {"drivable": fill_polygons(patch, drivable).astype(bool),
                "lane_divider": draw_lines(patch, self.near("dividers", patch), thickness).astype(bool),
                "ped_crossing": fill_polygons(patch, self.near("crossings", patch)).astype(bool),
                "road_boundary": draw_boundaries(patch, drivable, thickness).astype(bool)}


def _boxes(ann: dict, rows: list[int], grid: BevGrid) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    import cv2

    from ..nuscenes.objects import to_cells
    present = {c: np.zeros(grid.shape, np.uint8) for c in ("vehicle", "pedestrian")}
    hidden = {c: np.zeros(grid.shape, np.uint8) for c in ("vehicle", "pedestrian")}
    for i in rows:
        cat = ann["category"][i]
        cls = "vehicle" if cat in VEHICLES else "pedestrian" if cat in PEDESTRIANS else None
        if cls is None:
            continue
        half_l, half_w = ann["length_m"][i] / 2, ann["width_m"][i] / 2
        corners = np.array([[half_l, half_w, 0, 1], [half_l, -half_w, 0, 1], [-half_l, -half_w, 0, 1],
                            [-half_l, half_w, 0, 1]])  # (4, 4) homogeneous, in the cuboid's frame
        xy = (_se3(ann, i) @ corners.T).T[:, :2]  # cuboids are in the ego frame of their sweep
        kept = int(ann.get("num_interior_pts", [1] * (i + 1))[i]) >= 1
        cv2.fillPoly((present if kept else hidden)[cls], [to_cells(grid, xy)], 1)
    return {c: (present[c].astype(bool), present[c].astype(bool) | ~hidden[c].astype(bool)) for c in present}


def import_av2_log(logdir: str | Path, out: str | Path, *, grid: BevGrid | None = None,
                   force: bool = False) -> tuple[ImportCounts, list[str]]:
    """Write the log at ``logdir`` as the bag ``out`` (see the module docstring); returns the counts
    and the notes.

    Raises:
        MissingDevkitError: pyarrow is not installed.
        DatasetLayoutError: a table is missing or unreadable, or no ring camera has images.
    """
    logdir, grid = Path(logdir), grid or BevGrid()
    notes: list[str] = []
    ext = _feather(logdir / "calibration" / "egovehicle_SE3_sensor.feather")
    intr = _feather(logdir / "calibration" / "intrinsics.feather")
    poses_t = _feather(logdir / "city_SE3_egovehicle.feather")
    ann_path = logdir / "annotations.feather"
    ann = _feather(ann_path) if ann_path.is_file() else None
    cams, images = [], []
    for name in RING_CAMERAS:
        folder = logdir / "sensors" / "cameras" / name
        if name not in intr["sensor_name"] or name not in ext["sensor_name"] or not folder.is_dir():
            continue
        i, j = intr["sensor_name"].index(name), ext["sensor_name"].index(name)
        K = ((intr["fx_px"][i], 0.0, intr["cx_px"][i]), (0.0, intr["fy_px"][i], intr["cy_px"][i]), (0.0, 0.0, 1.0))
        model = CameraModel(K=K, D=(intr["k1"][i], intr["k2"][i], 0.0, 0.0, intr["k3"][i]),
                            width=int(intr["width_px"][i]), height=int(intr["height_px"][i]))
        cams.append(ImportedCamera(name, f"{name}_optical_frame", model, _se3(ext, j)))
        images += [ImageRef(int(p.stem), name, p) for p in sorted(folder.glob("*.jpg")) if p.stem.isdigit()]
    if not cams:
        raise DatasetLayoutError(f"{logdir}: no ring camera with calibration and images under sensors/cameras/")
    poses = [(int(s), _se3(poses_t, i)) for i, s in enumerate(poses_t["timestamp_ns"])]
    pose_at = dict(poses)
    maps = sorted((logdir / "map").glob("log_map_archive_*.json"))
    vmap = VectorMap(maps[0]) if maps else None
    if vmap is None:
        notes.append(f"no map/log_map_archive_*.json in {logdir}: the map classes are left unscored")
    classes = tuple(c for c in CLASSES[:4] if vmap is not None) + (CLASSES[4:] if ann is not None else ())
    if ann is None:
        notes.append(f"no {ann_path.name}: vehicle and pedestrian are left unscored")
    stamps = sorted(set(ann["timestamp_ns"])) if ann is not None else sorted(pose_at)[::2]
    rows_at: dict[int, list[int]] = {}
    for i, s in enumerate(ann["timestamp_ns"] if ann is not None else []):
        rows_at.setdefault(int(s), []).append(i)
    keyframes = []
    for s in stamps:
        if int(s) not in pose_at:
            continue

        def layers(s=int(s)):
            outl = {}
            if vmap is not None:
                outl.update({c: (m, None) for c, m in vmap.masks(Patch.at(grid, pose_at[s])).items()})
            if ann is not None:
                outl.update(_boxes(ann, rows_at.get(s, []), grid))
            return outl

        keyframes.append(KeyFrame(int(s), layers))
    info = {"dataset": "Argoverse 2 sensor", "log": logdir.name, "key_frames": len(keyframes),
            "unscored": [c for c in (*CLASSES, "sidewalk") if c not in classes], "license": LICENSE}
    custom = {"bev_mapper.rig": "av2_ring7" if len(cams) == 7 else "av2_ring", "bev_mapper.grid": json.dumps(grid.to_dict()),
              "bev_mapper.source": json.dumps(info), "bev_mapper.license": LICENSE}
    split = logdir.resolve().parent.name  # the dataset's layout: sensor/<split>/<log_id>/
    if split in AV2_SPLITS:
        info["split"] = custom["bev_mapper.split"] = split
        custom["bev_mapper.source"] = json.dumps(info)
    drive = ImportedDrive(logdir.name, tuple(cams), images, poses, keyframes, classes, grid, custom)
    return write_imported_drive(out, drive, force=force), notes


__all__ = ["AV2_SPLITS", "CLASSES", "LICENSE", "RING_CAMERAS", "VectorMap", "import_av2_log"]
