"""Pinhole camera model with the distortion models of ``sensor_msgs/CameraInfo``.

Supported ``distortion_model`` values (the ROS names, with OpenCV's formulas):

* ``plumb_bob``: ``D = (k1, k2, p1, p2, k3)``
* ``rational_polynomial``: ``D = (k1, k2, p1, p2, k3, k4, k5, k6)``
* ``equidistant``: ``D = (k1, k2, k3, k4)`` (OpenCV's fisheye model)

``K`` refers to the full-resolution sensor, as in CameraInfo; ``binning_x/y`` and ``roi`` describe
the image actually delivered. :meth:`CameraModel.effective` folds them into ``K`` and all
projection functions work in the delivered image's pixels.

Points are in the camera optical frame: z forward, x right, y down.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from ..errors import CalibrationError

DISTORTION_MODELS = {"plumb_bob": 5, "rational_polynomial": 8, "equidistant": 4}
_MIN_DEPTH = 1e-6


@dataclass(frozen=True)
class Roi:
    """Region of interest of CameraInfo, in full-resolution pixels; all zero = full image."""

    x_offset: int = 0
    y_offset: int = 0
    width: int = 0
    height: int = 0

    @property
    def is_full(self) -> bool:
        """True when the ROI means 'the whole image'."""
        return self.width == 0 or self.height == 0


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera.

    Args:
        K: 3x3 intrinsic matrix (full resolution), stored as a nested tuple.
        D: distortion coefficients; shorter tuples are zero-padded to the model's length.
        distortion_model: one of :data:`DISTORTION_MODELS`.
        width, height: full-resolution image size in pixels.
        binning_x, binning_y: CameraInfo binning (0 is treated as 1).
        roi: CameraInfo region of interest.
    """

    K: tuple
    D: tuple = ()
    distortion_model: str = "plumb_bob"
    width: int = 0
    height: int = 0
    binning_x: int = 1
    binning_y: int = 1
    roi: Roi = field(default_factory=Roi)

    def __post_init__(self) -> None:
        K = np.asarray(self.K, dtype=np.float64)
        if K.shape != (3, 3):
            raise CalibrationError(f"K must be 3x3, got shape {K.shape}")
        if not np.all(np.isfinite(K)):
            raise CalibrationError("K has non-finite entries")
        if K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(
                f"focal lengths must be > 0 (fx={K[0, 0]}, fy={K[1, 1]}): camera is uncalibrated"
            )
        if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise CalibrationError(f"K last row must be [0, 0, 1], got {K[2].tolist()}")
        if self.distortion_model not in DISTORTION_MODELS:
            raise CalibrationError(
                f"unsupported distortion model {self.distortion_model!r}; "
                f"expected one of {sorted(DISTORTION_MODELS)}"
            )
        n = DISTORTION_MODELS[self.distortion_model]
        D = np.asarray(self.D, dtype=np.float64).ravel()
        if D.size > n and np.any(D[n:] != 0):
            raise CalibrationError(
                f"{self.distortion_model} takes {n} coefficients, got {D.size}: {D.tolist()}"
            )
        if not np.all(np.isfinite(D)):
            raise CalibrationError("distortion coefficients are non-finite")
        D = np.concatenate([D[:n], np.zeros(max(0, n - D.size))])
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"image size must be positive, got {self.width}x{self.height}")
        if self.binning_x < 0 or self.binning_y < 0:
            raise CalibrationError("binning must be >= 0")
        r = self.roi
        if not r.is_full and (
            r.x_offset < 0 or r.y_offset < 0 or r.x_offset + r.width > self.width
            or r.y_offset + r.height > self.height
        ):
            raise CalibrationError(f"roi {r} lies outside the {self.width}x{self.height} image")
        object.__setattr__(self, "K", tuple(map(tuple, K.tolist())))
        object.__setattr__(self, "D", tuple(D.tolist()))
        object.__setattr__(self, "binning_x", max(1, int(self.binning_x)))
        object.__setattr__(self, "binning_y", max(1, int(self.binning_y)))

    # ------------------------------------------------------------- accessors
    @property
    def K_array(self) -> np.ndarray:
        """``K`` as a float64 3x3 array."""
        return np.array(self.K, dtype=np.float64)

    @property
    def D_array(self) -> np.ndarray:
        """``D`` as a float64 array of the model's length."""
        return np.array(self.D, dtype=np.float64)

    @property
    def image_size(self) -> tuple[int, int]:
        """``(width, height)`` of the delivered image (after ROI and binning)."""
        e = self.effective()
        return e.width, e.height

    def effective(self) -> "CameraModel":
        """The same camera with ROI and binning folded into ``K`` (binning 1, full ROI)."""
        if self.roi.is_full and self.binning_x == 1 and self.binning_y == 1:
            return self
        K = self.K_array
        w, h = self.width, self.height
        if not self.roi.is_full:
            K[0, 2] -= self.roi.x_offset
            K[1, 2] -= self.roi.y_offset
            w, h = self.roi.width, self.roi.height
        bx, by = self.binning_x, self.binning_y
        # Same convention as ROS image_geometry: fx, cx (and fy, cy) are divided by binning.
        K[0, :] /= bx
        K[1, :] /= by
        return replace(self, K=K, width=w // bx, height=h // by, binning_x=1, binning_y=1, roi=Roi())

    def scaled(self, factor: float) -> "CameraModel":
        """The camera seen at ``factor`` times its (effective) resolution, e.g. 0.5 for half."""
        e = self.effective()
        K = e.K_array
        K[:2, :2] *= factor
        K[:2, 2] = (K[:2, 2] + 0.5) * factor - 0.5
        return replace(
            e, K=K, width=int(round(e.width * factor)), height=int(round(e.height * factor))
        )

    # ------------------------------------------------------------ projection
    def distort(self, xn: np.ndarray) -> np.ndarray:
        """Apply the distortion model to normalised coordinates ``(N, 2)`` (x/z, y/z)."""
        k = self.D
        x, y = xn[:, 0], xn[:, 1]
        r2 = x * x + y * y
        if self.distortion_model == "equidistant":
            r = np.sqrt(r2)
            theta = np.arctan(r)
            t2 = theta * theta
            theta_d = theta * (1 + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))))
            scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-12), 1.0)
            return xn * scale[:, None]
        k1, k2, p1, p2, k3 = k[:5]
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        if self.distortion_model == "rational_polynomial":
            k4, k5, k6 = k[5:8]
            radial = radial / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=1)

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project optical-frame points ``(N, 3)`` to pixels of the delivered image.

        Returns:
            ``uv`` of shape ``(N, 2)`` (pixel centres at integers) and a boolean ``in_front``
            mask (z > 0). ``uv`` of points behind the camera is NaN.
        """
        e = self.effective()
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        z = points[:, 2]
        in_front = z > _MIN_DEPTH
        safe_z = np.where(in_front, z, 1.0)
        xn = points[:, :2] / safe_z[:, None]
        xd = e.distort(xn)
        K = e.K_array
        u = K[0, 0] * xd[:, 0] + K[0, 1] * xd[:, 1] + K[0, 2]
        v = K[1, 1] * xd[:, 1] + K[1, 2]
        uv = np.stack([u, v], axis=1)
        uv[~in_front] = np.nan
        return uv, in_front

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Mask of pixel coordinates inside the delivered image (pixel edges at -0.5, w-0.5)."""
        w, h = self.image_size
        u, v = uv[:, 0], uv[:, 1]
        with np.errstate(invalid="ignore"):
            return (
                (u >= -0.5 + margin) & (u < w - 0.5 - margin)
                & (v >= -0.5 + margin) & (v < h - 0.5 - margin)
            )

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """Rays through pixels ``(N, 2)`` as optical-frame directions ``(N, 3)`` with z = 1.

        Distortion is inverted iteratively by OpenCV to 1e-12 (not its 5-iteration default).
        """
        e = self.effective()
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        if e.distortion_model == "equidistant":
            xn = cv2.fisheye.undistortPoints(uv, e.K_array, e.D_array, criteria=crit)
        else:
            eye = np.eye(3)
            if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
                xn = cv2.undistortPointsIter(uv, e.K_array, e.D_array, eye, eye, crit)
            else:  # OpenCV 5: undistortPoints takes the criteria itself
                xn = cv2.undistortPoints(uv, e.K_array, e.D_array, None, eye, eye, crit)
        xn = xn.reshape(-1, 2)  # (N, 1, 2) -> (N, 2)
        return np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)

    def pixel_rays(self) -> np.ndarray:
        """Rays (z = 1) through every pixel centre of the delivered image, ``(H, W, 3)``."""
        w, h = self.image_size
        us, vs = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        rays = self.unproject(np.stack([us.ravel(), vs.ravel()], axis=1))
        return rays.reshape(h, w, 3)  # (H*W, 3) -> (H, W, 3)

    def undistort_maps(self, new_K: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``cv2.remap`` maps producing an undistorted pinhole image of the same size."""
        e = self.effective()
        size = e.image_size
        new_K = e.K_array if new_K is None else np.asarray(new_K, dtype=np.float64)
        if e.distortion_model == "equidistant":
            return cv2.fisheye.initUndistortRectifyMap(
                e.K_array, e.D_array, np.eye(3), new_K, size, cv2.CV_32FC1
            )
        return cv2.initUndistortRectifyMap(e.K_array, e.D_array, np.eye(3), new_K, size, cv2.CV_32FC1)
