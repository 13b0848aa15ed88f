"""Plausibility bounds of the message adapters: the one place they are written.

A message that passes the adapters' structural checks can still describe something no real
camera delivers (a focal length of 1e-300 px, a principal point at 1e20 px, a 2^32-1 px wide
sensor) or ask for an allocation no node survives (a 100-byte PNG whose header claims
40000x40000 px). :class:`AdapterLimits` bounds those values; :data:`DEFAULT_LIMITS` is what every
adapter uses unless a caller passes its own ``limits=``.

The bounds are deliberately generous: they reject the impossible, not the unusual.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from bev_mapper_core.errors import ConfigError


@dataclass(frozen=True)
class AdapterLimits:
    """Bounds on what a camera message may describe.

    Sizes (``sensor_msgs/CameraInfo``, ``Image``, ``CompressedImage``):

    Args:
        max_image_side: largest width or height, in pixels, of a sensor (CameraInfo's
            full-resolution ``width``/``height``) or of a delivered image. 16384 px is beyond
            any camera a vehicle carries.
        max_image_pixels: largest number of pixels of a *delivered* image (after ROI and
            binning; an Image, or a CompressedImage once decoded). 2^25 = 33,554,432 px holds
            8K UHD (7680 x 4320); decoding one to 16-bit RGBA takes 256 MiB, the worst case
            a single message can cost.

    Intrinsics (``CameraInfo.k``), relative to the full-resolution sensor ``W x H`` that ``K``
    refers to:

    Args:
        min_focal_per_size, max_focal_per_size: ``fx / W`` and ``fy / H`` must lie in
            ``[min, max]``. The field of view of ``W`` pixels is ``2 * atan(W / (2 fx))`` for a
            pinhole lens and ``W / fx`` rad for an equidistant (fisheye) one, so 0.05 means a
            "field of view" of 20 rad (about 1150 degrees, beyond any lens: every fisheye has
            ``fx >= W / (2 pi) ~ 0.16 W``) and 100 means 0.57 degrees (a 1/100 rad telescope).
            Outside this range the calibration is garbage: with ``fx = 1e-300`` one pixel
            spans the whole half-space in front of the camera.
        principal_point_margin: ``cx`` must lie in ``[-m W, (1 + m) W]`` and ``cy`` in
            ``[-m H, (1 + m) H]``: the optical axis meets the sensor plane within one sensor
            size (m = 1) of the sensor. Real cameras have it near the centre.
        max_skew_per_focal: ``|K[0][1]| <= max_skew_per_focal * fx`` (skew; 0 for every modern
            camera, 1 is a 45 degree pixel shear).
        max_abs_distortion: every distortion coefficient ``|d_i|`` must be at most this.
            Real lenses stay far below (the rational model's ``k4..k6`` of a wide lens reach
            tens); 1e4 only keeps out values that overflow the polynomial.

    Raises:
        ConfigError: a bound is not a positive finite number, or min > max.
    """

    max_image_side: int = 16384
    max_image_pixels: int = 2**25
    min_focal_per_size: float = 0.05
    max_focal_per_size: float = 100.0
    principal_point_margin: float = 1.0
    max_skew_per_focal: float = 1.0
    max_abs_distortion: float = 1e4

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
                    or value < 0 or (value == 0 and f.name != "principal_point_margin"):
                raise ConfigError(f"adapter limit {f.name} must be a positive finite number, got {value!r}")
        for name in ("max_image_side", "max_image_pixels"):
            if not isinstance(getattr(self, name), int):
                raise ConfigError(f"adapter limit {name} must be an integer, got {getattr(self, name)!r}")
        if self.min_focal_per_size > self.max_focal_per_size:
            raise ConfigError(
                f"min_focal_per_size {self.min_focal_per_size} > max_focal_per_size {self.max_focal_per_size}"
            )


#: The limits every adapter applies unless given others.
DEFAULT_LIMITS = AdapterLimits()
