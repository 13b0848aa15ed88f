"""``sensor_msgs/CameraInfo`` <-> :class:`bev_mapper_core.geometry.camera.CameraModel`.

Reading takes ``K`` (``msg.k``, 9 values), ``D`` (``msg.d``), ``distortion_model``, the
full-resolution ``width``/``height``, ``binning_x/y`` and ``roi``, and checks them against the
plausibility bounds of :mod:`msg_adapters.limits`. ``R`` and ``P`` are neither read nor
validated (the mapper works on raw, distorted images, so they are never used); when writing,
``R`` is the identity and ``P = [K | 0]``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bev_mapper_core.errors import CalibrationError
from bev_mapper_core.geometry.camera import DISTORTION_MODELS, CameraModel, Roi

from ._fields import as_floats, as_int, as_str, field, short_repr
from .errors import CalibrationMessageError
from .factory import MessageFactory, make_header
from .limits import DEFAULT_LIMITS, AdapterLimits


def camera_info_key(msg: Any) -> tuple | None:
    """A hashable key of everything :func:`camera_info_to_model` reads from ``msg`` (size, K,
    distortion model and D, binning, ROI) and its ``frame_id``: two messages with the same key
    give the same model, so a node converts a camera's CameraInfo only when its key changes.
    ``None`` when a field cannot be read (then convert, to get the error).
    """
    try:
        roi = msg.roi
        return (str(msg.header.frame_id), int(msg.width), int(msg.height), str(msg.distortion_model),
                tuple(float(v) for v in msg.k), tuple(float(v) for v in msg.d), int(msg.binning_x),
                int(msg.binning_y), int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height),
                bool(roi.do_rectify))
    except (AttributeError, TypeError, ValueError):
        return None


def camera_info_to_model(msg: Any, *, limits: AdapterLimits = DEFAULT_LIMITS) -> CameraModel:
    """Convert a ``sensor_msgs/CameraInfo`` (rclpy or rosbags) into a :class:`CameraModel`.

    An empty ``distortion_model`` with no (or all-zero) coefficients is read as an undistorted
    ``plumb_bob`` camera; an empty ``d`` means zero distortion for any model. A ROI of all
    zeros means the full image (as ROS ``image_geometry``); any other ROI must be a non-empty
    region inside the sensor. Binning 0 means 1.

    Every model returned is usable: its delivered image (:attr:`CameraModel.image_size`, after
    ROI and binning) is at least 1x1 px and at most ``limits.max_image_pixels``, and its
    intrinsics are within the plausibility bounds of ``limits`` (:class:`AdapterLimits`:
    focal lengths, principal point, skew, distortion magnitudes, sizes).

    Args:
        msg: the CameraInfo.
        limits: plausibility bounds (default :data:`DEFAULT_LIMITS`).

    Raises:
        CalibrationMessageError: a field is missing or of the wrong type; uncalibrated (``K``
            all zero); non-finite values; ``K`` not of 9 values; unsupported distortion model;
            ``D`` of the wrong length for the model; a value outside ``limits``; binning or ROI
            giving an empty image or a ROI outside the sensor; or any inconsistency
            :class:`CameraModel` rejects.
    """
    err = CalibrationMessageError
    frame = getattr(getattr(msg, "header", None), "frame_id", "?")
    where = f"CameraInfo of frame {short_repr(frame)}"
    max_side = limits.max_image_side

    K = as_floats(field(msg, "k", err, where), "K", err, where)
    if K.size != 9:
        raise err(f"{where}: K must have 9 values, got {K.size}")
    if not np.all(np.isfinite(K)):
        raise err(f"{where}: K has non-finite values {K.tolist()}")
    if not np.any(K):
        raise err(f"{where}: K is all zero, the camera is uncalibrated")
    W = as_int(field(msg, "width", err, where), "width", err, where)
    H = as_int(field(msg, "height", err, where), "height", err, where)
    if not (1 <= W <= max_side and 1 <= H <= max_side):
        raise err(f"{where}: image size {W}x{H} is outside 1..{max_side} px per side")
    fx, skew, cx, _, fy, cy = K[:6].tolist()
    if fx <= 0 or fy <= 0:
        raise err(f"{where}: focal lengths must be > 0 (fx={fx}, fy={fy}): camera is uncalibrated")
    lo, hi = limits.min_focal_per_size, limits.max_focal_per_size
    for name, f, size, side in (("fx", fx, W, "width"), ("fy", fy, H, "height")):
        if not lo * size <= f <= hi * size:
            raise err(
                f"{where}: {name} = {f:g} px is implausible for a {side} of {size} px "
                f"(allowed {lo:g}..{hi:g} x {side} = {lo * size:g}..{hi * size:g} px)"
            )
    m = limits.principal_point_margin
    for name, c, size, side in (("cx", cx, W, "width"), ("cy", cy, H, "height")):
        if not -m * size <= c <= (1 + m) * size:
            raise err(
                f"{where}: principal point {name} = {c:g} px lies too far off the {size} px "
                f"sensor {side} (allowed {-m * size:g}..{(1 + m) * size:g} px)"
            )
    if abs(skew) > limits.max_skew_per_focal * fx:
        raise err(f"{where}: skew K[0][1] = {skew:g} exceeds {limits.max_skew_per_focal:g} x fx")

    D = as_floats(field(msg, "d", err, where), "D", err, where)
    if not np.all(np.isfinite(D)):
        raise err(f"{where}: D has non-finite values {D.tolist()}")
    if D.size and np.max(np.abs(D)) > limits.max_abs_distortion:
        raise err(
            f"{where}: distortion coefficient {np.max(np.abs(D)):g} exceeds the plausible "
            f"magnitude {limits.max_abs_distortion:g}"
        )
    model = as_str(field(msg, "distortion_model", err, where), "distortion_model", err, where)
    if model == "" and not np.any(D):
        model = "plumb_bob"
    if model not in DISTORTION_MODELS:
        raise err(
            f"{where}: unsupported distortion model {short_repr(model)}; supported: {sorted(DISTORTION_MODELS)}"
        )
    n = DISTORTION_MODELS[model]
    if D.size not in (0, n):
        raise err(f"{where}: distortion model {model!r} takes {n} coefficients, got {D.size}")

    bx = as_int(field(msg, "binning_x", err, where), "binning_x", err, where) or 1
    by = as_int(field(msg, "binning_y", err, where), "binning_y", err, where) or 1
    roi = Roi(*(as_int(field(msg, f"roi.{k}", err, where), f"roi.{k}", err, where)
                for k in ("x_offset", "y_offset", "width", "height")))
    if roi != Roi():
        if roi.width == 0 or roi.height == 0:
            raise err(f"{where}: ROI {roi} is empty (only an all-zero ROI means the full image)")
        if roi.x_offset + roi.width > W or roi.y_offset + roi.height > H:
            raise err(f"{where}: ROI {roi} lies outside the {W}x{H} sensor")
        rw, rh = roi.width, roi.height
    else:
        rw, rh = W, H
    ew, eh = rw // bx, rh // by  # the delivered image, as CameraModel.effective computes it
    if ew < 1 or eh < 1:
        raise err(
            f"{where}: binning {bx}x{by} of the {rw}x{rh} px {'ROI' if roi != Roi() else 'image'} "
            f"leaves an empty {ew}x{eh} image"
        )
    if ew * eh > limits.max_image_pixels:
        raise err(f"{where}: delivered image {ew}x{eh} exceeds {limits.max_image_pixels} pixels")
    try:
        cam = CameraModel(
            K=K.reshape(3, 3),  # row-major 9 -> 3x3
            D=tuple(D.tolist()),
            distortion_model=model,
            width=W,
            height=H,
            binning_x=bx,
            binning_y=by,
            roi=roi,
        )
        if cam.image_size != (ew, eh):  # the core's own reading of binning and ROI
            raise CalibrationError(f"delivered image is {cam.image_size}, expected {(ew, eh)}")
    except CalibrationError as exc:
        raise err(f"{where}: {exc}") from None
    return cam


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
