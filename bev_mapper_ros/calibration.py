"""Live calibration state of the node: intrinsics from CameraInfo, extrinsics from TF or parameters.

No rclpy import: TF comes through the small :class:`~bev_mapper_ros.tf_source.TfSource`
interface (None without tf2_ros), so this is unit-testable with any object that has its
``lookup``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.rig import Rig, RigCamera

from .tf_source import TfLookupError, TfSource

#: Called with ``(kind, message)`` for each TF problem (a :data:`~.tf_source.TF_ERROR_KINDS` entry).
TfProblem = Callable[[str, str], None]


class LiveCalibration:
    """Thread-safe per-camera calibration that yields a :class:`Rig` once complete.

    Extrinsics: TF (``base_frame <- the camera's CameraInfo frame_id``, the latest transform,
    looked up again with every call of :meth:`missing`, i.e. every frame) when TF has it, else
    the ``extrinsics.<cam>`` parameters (the preset rig's by default). A TF extrinsic that moves
    a camera by more than ``max_jump_m`` from the one in use is refused (``extrinsic_jump``):
    mounts do not move by metres between frames, a broken transform does. A TF extrinsic that
    cannot be looked up keeps the last one in use. Each problem goes to ``on_problem``; a
    missing path is one only once the camera had TF (else it is the parameter fallback).

    Intrinsics arrive continuously with CameraInfo; only a *change* bumps :attr:`version`, so
    the mapper recomputes its lookup tables only when the calibration really changes.
    """

    def __init__(self, rig_name: str, cameras, base_frame: str, param_extrinsics: dict,
                 tf: TfSource | None = None, max_jump_m: float = 0.5,
                 on_problem: TfProblem | None = None) -> None:
        self.rig_name = rig_name or "live"
        self.cameras = tuple(cameras)
        self.base_frame = base_frame
        self._param_ext = {k: np.asarray(v, float) for k, v in param_extrinsics.items()}
        self._tf = tf
        self._max_jump_m = float(max_jump_m)
        self._on_problem = on_problem or (lambda kind, message: None)
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

    def _from_tf(self, camera: str, frame: str) -> bool:
        """Take the camera's extrinsic from TF when TF has a good one; lock held. True if TF applies."""
        had_tf = self._ext_source.get(camera) == "tf"
        try:
            T = self._tf.lookup(self.base_frame, frame)
        except TfLookupError as exc:
            if had_tf or exc.kind != "no_path":
                self._on_problem(exc.kind, f"extrinsics of {camera}: {exc}")
            return had_tf
        if had_tf:
            jump = float(np.linalg.norm(T[:3, 3] - self._ext[camera][:3, 3]))
            if jump > self._max_jump_m:
                self._on_problem("extrinsic_jump", f"extrinsics of {camera}: TF moves {frame} by {jump:.2f} m "
                                 f"(more than tf_extrinsic_jump_m {self._max_jump_m:g}); the previous "
                                 "extrinsic stays in use")
                return True
        if camera not in self._ext or not np.allclose(self._ext[camera], T, atol=1e-9):
            self._ext[camera] = T
            self.version += 1
        self._ext_source[camera] = "tf"
        return True

    def _resolve_extrinsic(self, camera: str) -> None:
        """Look the camera's extrinsic up in TF (preferred) or take the parameter; lock held."""
        frame = self._frames.get(camera)
        if self._tf is not None and frame and self._from_tf(camera, frame):
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
        """Where each camera's extrinsic comes from (``tf`` / ``parameter``)."""
        with self._lock:
            return dict(self._ext_source)

    def describe_sources(self) -> str:
        """``front: tf (base_link <- front_optical_frame), rear: parameter`` for a log line."""
        with self._lock:
            parts = []
            for cam in self.cameras:
                src = self._ext_source.get(cam)
                if src == "tf":
                    parts.append(f"{cam}: TF ({self.base_frame} <- {self._frames.get(cam)})")
                elif src:
                    parts.append(f"{cam}: parameter extrinsics.{cam}")
            return ", ".join(parts)
