"""``sensor_msgs/CameraInfo`` <-> :class:`bev_mapper_core.camera.CameraModel`.

Reading takes ``K`` (``msg.k``, 9 values), ``D`` (``msg.d``), ``distortion_model``, the
full-resolution ``width``/``height``, ``binning_x/y`` and ``roi``. ``R`` and ``P`` are ignored
when reading (the mapper works on raw, distorted images); when writing, ``R`` is the identity
and ``P = [K | 0]``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bev_mapper_core.camera import DISTORTION_MODELS, CameraModel, Roi
from bev_mapper_core.errors import CalibrationError

from .errors import CalibrationMessageError
from .factory import MessageFactory, make_header


def _floats(values: Any, what: str) -> np.ndarray:
    try:
        return np.asarray(values, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise CalibrationMessageError(f"CameraInfo {what} is not numeric: {exc}") from None


def camera_info_to_model(msg: Any) -> CameraModel:
    """Convert a ``sensor_msgs/CameraInfo`` (rclpy or rosbags) into a :class:`CameraModel`.

    An empty ``distortion_model`` with no (or all-zero) coefficients is read as an undistorted
    ``plumb_bob`` camera; an empty ``d`` means zero distortion for any model.

    Raises:
        CalibrationMessageError: uncalibrated (``K`` all zero), non-finite values, ``K`` not of
            9 values, unsupported distortion model, ``D`` of the wrong length for the model, or
            any inconsistency :class:`CameraModel` rejects (size, ROI, ...).
    """
    frame = getattr(getattr(msg, "header", None), "frame_id", "?")
    where = f"CameraInfo of frame {frame!r}"
    K = _floats(msg.k, "K")
    if K.size != 9:
        raise CalibrationMessageError(f"{where}: K must have 9 values, got {K.size}")
    if not np.all(np.isfinite(K)):
        raise CalibrationMessageError(f"{where}: K has non-finite values {K.tolist()}")
    if not np.any(K):
        raise CalibrationMessageError(f"{where}: K is all zero, the camera is uncalibrated")
    D = _floats(msg.d, "D")
    if not np.all(np.isfinite(D)):
        raise CalibrationMessageError(f"{where}: D has non-finite values {D.tolist()}")
    model = str(msg.distortion_model)
    if model == "" and not np.any(D):
        model = "plumb_bob"
    if model not in DISTORTION_MODELS:
        raise CalibrationMessageError(
            f"{where}: unsupported distortion model {model!r}; supported: {sorted(DISTORTION_MODELS)}"
        )
    n = DISTORTION_MODELS[model]
    if D.size not in (0, n):
        raise CalibrationMessageError(
            f"{where}: distortion model {model!r} takes {n} coefficients, got {D.size}"
        )
    roi = msg.roi
    try:
        return CameraModel(
            K=K.reshape(3, 3),  # row-major 9 -> 3x3
            D=tuple(D.tolist()),
            distortion_model=model,
            width=int(msg.width),
            height=int(msg.height),
            binning_x=int(msg.binning_x),
            binning_y=int(msg.binning_y),
            roi=Roi(int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height)),
        )
    except CalibrationError as exc:
        raise CalibrationMessageError(f"{where}: {exc}") from None


def camera_info_fields(model: CameraModel) -> dict[str, Any]:
    """Plain-python CameraInfo fields of ``model`` (``k``, ``d``, ``r``, ``p`` as float64 arrays).

    ``roi`` is returned as a dict (``x_offset, y_offset, width, height, do_rectify``).
    """
    K = model.K_array
    P = np.zeros((3, 4))
    P[:, :3] = K  # P = [K | 0]
    return {
        "height": int(model.height),
        "width": int(model.width),
        "distortion_model": model.distortion_model,
        "d": np.asarray(model.D, dtype=np.float64),
        "k": K.reshape(9),
        "r": np.eye(3).reshape(9),
        "p": P.reshape(12),
        "binning_x": int(model.binning_x),
        "binning_y": int(model.binning_y),
        "roi": {
            "x_offset": int(model.roi.x_offset),
            "y_offset": int(model.roi.y_offset),
            "height": int(model.roi.height),
            "width": int(model.roi.width),
            "do_rectify": False,
        },
    }


def make_camera_info(
    factory: MessageFactory, model: CameraModel, stamp_ns: int, frame_id: str
) -> Any:
    """Build a ``sensor_msgs/CameraInfo`` for ``model`` (R = identity, P = [K|0])."""
    f = camera_info_fields(model)
    roi = factory.msg("sensor_msgs/msg/RegionOfInterest", **f.pop("roi"))
    return factory.msg(
        "sensor_msgs/msg/CameraInfo",
        header=make_header(factory, stamp_ns, frame_id),
        height=f["height"],
        width=f["width"],
        distortion_model=f["distortion_model"],
        d=factory.float64_seq(f["d"]),
        k=factory.float64_fixed(f["k"], 9),
        r=factory.float64_fixed(f["r"], 9),
        p=factory.float64_fixed(f["p"], 12),
        binning_x=f["binning_x"],
        binning_y=f["binning_y"],
        roi=roi,
    )
