"""Live calibration state of the node: intrinsics from CameraInfo, extrinsics from TF or parameters.

No rclpy import: the TF lookup is a callable injected by the node (None without tf2_ros).
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.rig import Rig, RigCamera

# (target_frame, source_frame) -> 4x4 target_from_source, or None when unknown
TfLookup = Callable[[str, str], "np.ndarray | None"]


class LiveCalibration:
    """Thread-safe per-camera calibration that yields a :class:`Rig` once complete.

    Extrinsics: TF first (looked up until found, then kept: camera mounts are static), else
    the ``extrinsics.<cam>`` parameters.

    Intrinsics arrive continuously with CameraInfo; only a *change* bumps :attr:`version`, so
    the mapper recomputes its lookup tables only when the calibration really changes.
    """

    def __init__(self, rig_name: str, cameras, base_frame: str, param_extrinsics: dict,
                 tf_lookup: TfLookup | None = None) -> None:
        self.rig_name = rig_name or "live"
        self.cameras = tuple(cameras)
        self.base_frame = base_frame
        self._param_ext = {k: np.asarray(v, float) for k, v in param_extrinsics.items()}
        self._tf_lookup = tf_lookup
        self._lock = threading.Lock()
        self._models: dict[str, CameraModel] = {}
        self._frames: dict[str, str] = {}
        self._ext: dict[str, np.ndarray] = {}
        self._ext_source: dict[str, str] = {}
        self.version = 0
        self._rig: Rig | None = None
        self._rig_version = -1

    def update_intrinsics(self, camera: str, model: CameraModel, frame_id: str) -> bool:
        """Store a camera model; returns True if it differs from the stored one."""
        with self._lock:
            if self._models.get(camera) == model and self._frames.get(camera) == frame_id:
                return False
            self._models[camera] = model
            self._frames[camera] = frame_id
            self.version += 1
            return True

    def _resolve_extrinsic(self, camera: str) -> None:
        """Look the camera's extrinsic up in TF (preferred) or take the parameter; lock held."""
        frame = self._frames.get(camera)
        if self._tf_lookup is not None and frame and self._ext_source.get(camera) != "tf":
            T = self._tf_lookup(self.base_frame, frame)
            if T is not None:
                if camera not in self._ext or not np.allclose(self._ext[camera], T, atol=1e-9):
                    self._ext[camera] = T
                    self.version += 1
                self._ext_source[camera] = "tf"
                return
        if camera not in self._ext and camera in self._param_ext:
            self._ext[camera] = self._param_ext[camera]
            self._ext_source[camera] = "parameter"
            self.version += 1

    def missing(self) -> tuple[str, ...]:
        """Human-readable list of what is still missing (``'front: camera_info'`` ...)."""
        with self._lock:
            out = []
            for cam in self.cameras:
                if cam not in self._models:
                    out.append(f"{cam}: camera_info")
                    continue
                self._resolve_extrinsic(cam)
                if cam not in self._ext:
                    out.append(f"{cam}: extrinsics ({self.base_frame} <- {self._frames[cam]})")
            return tuple(out)

    def rig(self) -> Rig | None:
        """The current rig when every camera is calibrated, else None. Cached per version."""
        if self.missing():
            return None
        with self._lock:
            if self._rig_version != self.version:
                cams = tuple(
                    RigCamera(c, self._models[c], self._ext[c], self._frames[c] or "") for c in self.cameras
                )
                self._rig = Rig(self.rig_name, cams)
                self._rig_version = self.version
            return self._rig

    def sources(self) -> dict[str, str]:
        """Where each camera's extrinsic came from (``tf`` / ``parameter``)."""
        with self._lock:
            return dict(self._ext_source)
