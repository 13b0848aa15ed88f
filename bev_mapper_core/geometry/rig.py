"""Camera rigs: named cameras with intrinsics and ``ego_from_cam`` extrinsics.

Presets carry published calibrations:

* ``surround6``: the six cameras of nuScenes (scene-0061 calibrated_sensor records), 1600x900,
  delivered with 4x binning (400x225) so synthetic drives render on a CPU.
* ``cam2bev4``: Cam2BEV's 1_FRLR rig (fx 278.283, fy 408.1295, cx 482, cy 302, 964x604),
  delivered with 2x binning (482x302).
* ``front1``: nuScenes' front camera alone, for the monocular methods.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ..errors import CalibrationError, ConfigError
from .camera import CameraModel
from .ego_mask import EgoMask
from .transforms import ego_from_optical, invert_transform, make_transform, quat_to_rot, validate_transform


@dataclass(frozen=True)
class RigCamera:
    """One camera of a rig.

    Args:
        name: short name used in topic names (``/cameras/<name>/...``).
        model: intrinsics.
        ego_from_cam: 4x4 transform from the optical frame into ``base_link``.
        frame_id: the optical frame's TF name.
        ego_mask: the pixels that show the ego vehicle itself (:mod:`.ego_mask`), at the
            delivered image size; ``None`` = none. Ground tables leave their cells out; a scaled
            copy of the camera keeps the mask (looked up proportionally).
    """

    name: str
    model: CameraModel
    ego_from_cam: tuple
    frame_id: str = ""
    ego_mask: EgoMask | None = None

    def __post_init__(self) -> None:
        if not self.name or "/" in self.name:
            raise CalibrationError(f"invalid camera name {self.name!r}")
        T = validate_transform(self.ego_from_cam, f"ego_from_cam of camera {self.name!r}")
        object.__setattr__(self, "ego_from_cam", tuple(map(tuple, T.tolist())))
        if not self.frame_id:
            object.__setattr__(self, "frame_id", f"{self.name}_optical_frame")

    @property
    def ego_from_cam_array(self) -> np.ndarray:
        """``ego_from_cam`` as a 4x4 float64 array."""
        return np.array(self.ego_from_cam, dtype=np.float64)

    @property
    def cam_from_ego(self) -> np.ndarray:
        """Inverse extrinsics: maps ego-frame points into the optical frame."""
        return invert_transform(self.ego_from_cam_array)


@dataclass(frozen=True)
class Rig:
    """An ordered set of cameras mounted on the ego vehicle."""

    name: str
    cameras: tuple[RigCamera, ...]

    def __post_init__(self) -> None:
        if not self.cameras:
            raise CalibrationError(f"rig {self.name!r} has no cameras")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise CalibrationError(f"rig {self.name!r} has duplicate camera names: {names}")
        object.__setattr__(self, "cameras", tuple(self.cameras))

    @property
    def names(self) -> tuple[str, ...]:
        """Camera names in rig order."""
        return tuple(c.name for c in self.cameras)

    def __getitem__(self, name: str) -> RigCamera:
        for cam in self.cameras:
            if cam.name == name:
                return cam
        raise KeyError(f"rig {self.name!r} has no camera {name!r}; cameras: {list(self.names)}")

    def with_camera(self, camera: RigCamera) -> "Rig":
        """A copy with ``camera`` replacing the camera of the same name (or appended)."""
        cams = [camera if c.name == camera.name else c for c in self.cameras]
        if camera.name not in self.names:
            cams.append(camera)
        return replace(self, cameras=tuple(cams))

    def scaled(self, factor: float) -> "Rig":
        """A copy whose cameras deliver images ``factor`` times the size (intrinsics rescaled)."""
        return replace(
            self, cameras=tuple(replace(c, model=c.model.scaled(factor)) for c in self.cameras)
        )


# --------------------------------------------------------------------- presets
def _nuscenes_cam(name, t, q_wxyz, f, cx, cy, binning=4) -> RigCamera:
    w, x, y, z = q_wxyz
    K = ((f, 0.0, cx), (0.0, f, cy), (0.0, 0.0, 1.0))
    model = CameraModel(K=K, D=(0.0,) * 5, width=1600, height=900, binning_x=binning, binning_y=binning)
    return RigCamera(name, model, make_transform(quat_to_rot(x, y, z, w), t))


def surround6() -> Rig:
    """nuScenes-like six-camera surround rig (published scene-0061 calibration)."""
    cams = (
        _nuscenes_cam("front", (1.70079, 0.01595, 1.51096),
                      (0.49980, -0.50303, 0.49978, -0.49737), 1266.417, 816.267, 491.507),
        _nuscenes_cam("front_right", (1.55085, -0.49340, 1.49575),
                      (0.20603, -0.20269, 0.68245, -0.67136), 1260.847, 807.968, 495.334),
        _nuscenes_cam("back_right", (1.01488, -0.48057, 1.56240),
                      (0.12281, -0.13240, -0.70043, 0.69050), 1259.514, 807.253, 501.196),
        _nuscenes_cam("back", (0.02833, 0.00345, 1.57910),
                      (0.50379, -0.49740, -0.49419, 0.50455), 809.221, 829.220, 481.778),
        _nuscenes_cam("back_left", (1.03569, 0.48480, 1.59097),
                      (0.69242, -0.70316, -0.11648, 0.11203), 1256.741, 792.113, 492.776),
        _nuscenes_cam("front_left", (1.52388, 0.49463, 1.50933),
                      (0.67573, -0.67363, 0.21214, -0.21123), 1272.598, 826.615, 479.752),
    )
    return Rig("surround6", cams)


def cam2bev4() -> Rig:
    """Cam2BEV 1_FRLR rig: front, rear, left, right; 964x604 delivered with 2x binning."""
    K = ((278.283, 0.0, 482.0), (0.0, 408.1295, 302.0), (0.0, 0.0, 1.0))
    model = CameraModel(K=K, D=(0.0,) * 5, width=964, height=604, binning_x=2, binning_y=2)
    mounts = (
        ("front", (1.7, 0.0, 1.4), 0.0),
        ("rear", (-0.6, 0.0, 1.4), math.pi),
        ("left", (0.5, 0.5, 1.5), math.pi / 2),
        ("right", (0.5, -0.5, 1.5), -math.pi / 2),
    )
    return Rig("cam2bev4", tuple(RigCamera(n, model, ego_from_optical(t, yaw=y)) for n, t, y in mounts))


def front1() -> Rig:
    """Monocular front camera (nuScenes CAM_FRONT), for S2G2 and FocusBEV."""
    return Rig("front1", (surround6()["front"],))


PRESETS = {"surround6": surround6, "cam2bev4": cam2bev4, "front1": front1}


def preset_rig(name: str) -> Rig:
    """Build a preset rig by name.

    Raises:
        ConfigError: unknown name.
    """
    try:
        return PRESETS[name]()
    except KeyError:
        raise ConfigError(f"unknown rig {name!r}; presets: {sorted(PRESETS)}") from None


def scaled_camera(camera: RigCamera, input_width: int) -> RigCamera:
    """``camera`` seen at the model's input width (intrinsics rescaled with ``model.scaled``)."""
    w, _ = camera.model.image_size
    return replace(camera, model=camera.model.scaled(input_width / w))
