"""One nuScenes scene as an :class:`~bags.importers.drive.ImportedDrive`: its six cameras, ego poses
and key frames with their ground-truth layers.

* Images: the six cameras' key frames (``is_key_frame``), and with ``sweeps`` their other frames,
  at their own ``timestamp``; CameraInfo from ``calibrated_sensor`` (``camera_intrinsic``, the
  record's image size, no distortion: nuScenes' images are undistorted), the mounts
  (``base_link`` -> ``<camera>_optical_frame``) on ``/tf_static``.
* Poses: the ``ego_pose`` of every image written and of each key frame's ``LIDAR_TOP``.
* Key frames: at the sample's ``timestamp``, on the grid placed at the ego pose of the sample's
  ``LIDAR_TOP`` data (HDMapNet's reference pose), the map layers (:mod:`.maps`) and the boxes
  (:mod:`.objects`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from dataclasses import field as dc_field

import numpy as np

from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.transforms import make_transform, quat_to_rot

from ..drive import ImageRef, ImportedCamera, ImportedDrive, KeyFrame
from ..errors import DatasetLayoutError
from ..raster import HDMAPNET_THICKNESS, Patch
from .maps import MAP_SOURCES, NuScenesMap
from .objects import OBJECT_CLASSES, BoxFilter, object_layers
from .splits import scene_split
from .tables import NuScenesTables, field

#: nuScenes channel -> the ``surround6`` preset's camera name, in the preset's order
CAMERAS = {"CAM_FRONT": "front", "CAM_FRONT_RIGHT": "front_right", "CAM_BACK_RIGHT": "back_right",
           "CAM_BACK": "back", "CAM_BACK_LEFT": "back_left", "CAM_FRONT_LEFT": "front_left"}
LICENSE = ("nuScenes (Motional), CC BY-NC-SA 4.0: non-commercial use, share alike, attribution; "
           "this bag is derived from it and under the same terms (https://www.nuscenes.org/terms-of-use)")


@dataclass(frozen=True)
class SceneOptions:
    """How a scene is imported.

    Args:
        grid: the BEV grid of the GT layers.
        sweeps: also the cameras' frames between key frames (about 12 Hz instead of 2 Hz).
        boxes: which annotation boxes are scored.
        thickness: width in cells of the line classes (HDMapNet: 5).
    """

    grid: BevGrid = dc_field(default_factory=BevGrid)
    sweeps: bool = False
    boxes: BoxFilter = dc_field(default_factory=BoxFilter)
    thickness: int = HDMAPNET_THICKNESS


def _pose(tables: NuScenesTables, sample_data: dict) -> tuple[int, np.ndarray]:
    ep = tables.get("ego_pose", field(sample_data, "ego_pose_token", "sample_data"))
    w, x, y, z = (float(v) for v in field(ep, "rotation", "ego_pose"))
    T = make_transform(quat_to_rot(x, y, z, w), [float(v) for v in field(ep, "translation", "ego_pose")])
    return int(field(sample_data, "timestamp", "sample_data")) * 1000, T


def _camera(tables: NuScenesTables, name: str, sample_data: dict) -> ImportedCamera:
    cs = tables.get("calibrated_sensor", field(sample_data, "calibrated_sensor_token", "sample_data"))
    K = np.asarray(field(cs, "camera_intrinsic", "calibrated_sensor"), dtype=np.float64)
    if K.shape != (3, 3):
        raise DatasetLayoutError(f"calibrated_sensor {cs['token']}: camera_intrinsic is not 3x3")
    w, x, y, z = (float(v) for v in field(cs, "rotation", "calibrated_sensor"))
    ego_from_cam = make_transform(quat_to_rot(x, y, z, w), [float(v) for v in field(cs, "translation", "calibrated_sensor")])
    model = CameraModel(K=tuple(map(tuple, K.tolist())), D=(0.0,) * 5, width=int(field(sample_data, "width", "sample_data")),
                        height=int(field(sample_data, "height", "sample_data")))
    return ImportedCamera(name, f"{name}_optical_frame", model, ego_from_cam)


def scene_drive(tables: NuScenesTables, scene: dict, options: SceneOptions,
                nmap: NuScenesMap | None) -> tuple[ImportedDrive, dict]:
    """The drive of ``scene`` and a summary of its sources (for ``custom_data`` and the report);
    ``nmap`` None: the map layers are left unscored.
    """
    samples = tables.scene_samples(scene)
    cams: dict[str, ImportedCamera] = {}
    images: list[ImageRef] = []
    poses: list[tuple[int, np.ndarray]] = []
    keyframes: list[KeyFrame] = []
    has_boxes = len(tables.table("sample_annotation")) > 0
    classes = tuple(c for c in MAP_SOURCES if nmap is not None) + (OBJECT_CLASSES if has_boxes else ())
    left_out = [0]
    for sample in samples:
        lidar = None
        for sd in tables.sample_data_by_sample.get(sample["token"], []):
            channel = tables.channel(sd)
            key = bool(sd.get("is_key_frame"))
            if channel == "LIDAR_TOP" and key:
                lidar = sd
            if channel not in CAMERAS or not (key or options.sweeps):
                continue
            name = CAMERAS[channel]
            if name not in cams and key:
                cams[name] = _camera(tables, name, sd)
            stamp, T = _pose(tables, sd)
            images.append(ImageRef(stamp, name, tables.dataroot / field(sd, "filename", "sample_data")))
            poses.append((stamp, T))
        if lidar is None:
            raise DatasetLayoutError(f"sample {sample['token']} of {scene['name']} has no LIDAR_TOP key frame "
                                     "(the reference pose of its ground truth)")
        _, world_from_ego = _pose(tables, lidar)
        poses.append((int(field(sample, "timestamp", "sample")) * 1000, world_from_ego))
        anns = tables.annotations_by_sample.get(sample["token"], [])

        def layers(T=world_from_ego, anns=anns):
            out = {}
            if nmap is not None:
                patch = Patch.at(options.grid, T)
                for c, mask in nmap.layer_masks(patch, tuple(MAP_SOURCES), options.thickness).items():
                    out[c] = (mask, None)
            if has_boxes:
                objs, n = object_layers(tables, anns, options.grid, T, options.boxes)
                out.update(objs)
                left_out[0] += n
            return out

        keyframes.append(KeyFrame(int(field(sample, "timestamp", "sample")) * 1000, layers))
    ordered = tuple(cams[n] for n in CAMERAS.values() if n in cams)
    images = [im for im in images if im.camera in cams]  # a sweep of a camera without key frames
    log = tables.get("log", field(scene, "log_token", "scene"))
    info = {
        "dataset": "nuScenes", "version": tables.version, "scene": scene["name"],
        "description": scene.get("description", ""), "location": log.get("location", ""),
        "split": scene_split(tables.version, scene["name"]),
        "key_frames": len(keyframes), "sweeps": options.sweeps,
        "gt": {c: f"map expansion {MAP_SOURCES[c][0]} of {', '.join(MAP_SOURCES[c][1])}" for c in MAP_SOURCES
               if nmap is not None} | ({c: "sample_annotation boxes" for c in OBJECT_CLASSES} if has_boxes else {}),
        "unscored": [c for c in (*MAP_SOURCES, *OBJECT_CLASSES) if c not in classes],
        "box_filter": {"min_visibility": options.boxes.min_visibility, "min_points": options.boxes.min_points},
        "license": LICENSE,
    }
    custom = {
        "bev_mapper.grid": json.dumps(options.grid.to_dict()),
        "bev_mapper.source": json.dumps(info),
        "bev_mapper.license": LICENSE,
    }
    if info["split"] is not None:
        custom["bev_mapper.split"] = info["split"]
    if len(ordered) == len(CAMERAS):
        custom["bev_mapper.rig"] = "surround6"
    drive = ImportedDrive(scene["name"], ordered, images, poses, keyframes, classes, options.grid, custom)
    return drive, {"info": info, "left_out_boxes": left_out}


__all__ = ["CAMERAS", "LICENSE", "SceneOptions", "scene_drive"]
