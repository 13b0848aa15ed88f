"""Rigid transforms, quaternions and the REP 103 camera mounting conventions.

Transforms are 4x4 homogeneous matrices named by direction: ``ego_from_cam`` maps points
expressed in the camera frame into the ego frame (``p_ego = ego_from_cam @ p_cam``).
Quaternions follow ROS order ``(x, y, z, w)``.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import CalibrationError

#: Rotation taking optical-frame vectors (z forward, x right, y down) into the body frame of the
#: same sensor (x forward, y left, z up). Columns are the optical axes expressed in body axes.
BODY_FROM_OPTICAL = np.array(
    [
        [0.0, 0.0, 1.0],
        [-1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
    ]
)


def make_transform(rotation: np.ndarray, translation) -> np.ndarray:
    """Build a 4x4 transform from a 3x3 rotation and a 3-vector translation."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(rotation, dtype=np.float64)
    T[:3, 3] = np.asarray(translation, dtype=np.float64).reshape(3)
    return T


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (uses R^T rather than a general inverse)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[:3, :3]
    t = T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to ``(N, 3)`` points; returns ``(N, 3)``."""
    points = np.asarray(points, dtype=np.float64)
    return points @ T[:3, :3].T + T[:3, 3]


def quat_to_rot(x: float, y: float, z: float, w: float) -> np.ndarray:
    """Rotation matrix of a quaternion in ROS order; the quaternion is normalised first.

    Raises:
        CalibrationError: the quaternion is non-finite or (near) zero.
    """
    q = np.array([x, y, z, w], dtype=np.float64)
    n = float(np.linalg.norm(q))
    if not np.all(np.isfinite(q)) or n < 1e-9:
        raise CalibrationError(f"invalid quaternion (x, y, z, w) = {tuple(q)}")
    x, y, z, w = q / n
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rot_to_quat(R: np.ndarray) -> tuple[float, float, float, float]:
    """Quaternion ``(x, y, z, w)`` of a rotation matrix, with ``w >= 0``."""
    R = np.asarray(R, dtype=np.float64)
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x = 0.25 * s, (R[2, 1] - R[1, 2]) / s
        y, z = (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2]) * 2
        w, x = (R[2, 1] - R[1, 2]) / s, 0.25 * s
        y, z = (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s
    elif R[1, 1] > R[2, 2]:
        s = math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2]) * 2
        w, x = (R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s
        y, z = 0.25 * s, (R[1, 2] + R[2, 1]) / s
    else:
        s = math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1]) * 2
        w, x = (R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s
        y, z = (R[1, 2] + R[2, 1]) / s, 0.25 * s
    q = np.array([x, y, z, w])
    q /= np.linalg.norm(q)
    if q[3] < 0:
        q = -q
    return tuple(float(v) for v in q)


def rpy_to_rot(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Rotation ``Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (REP 103 fixed-axis roll, pitch, yaw)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def yaw_of(T: np.ndarray) -> float:
    """Heading (rad) of the x axis of a transform's rotation, projected on the xy plane."""
    return math.atan2(T[1, 0], T[0, 0])


def ego_from_optical(xyz, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> np.ndarray:
    """``ego_from_cam`` for a camera mounted at ``xyz`` with body yaw/pitch/roll in radians.

    The camera body looks along its +x; yaw turns it left, positive pitch tilts it down
    (REP 103: a positive rotation about +y points +x towards -z). The returned transform
    maps points in the camera *optical* frame (z forward, x right, y down) into the ego frame.
    """
    R = rpy_to_rot(roll, pitch, yaw) @ BODY_FROM_OPTICAL
    return make_transform(R, xyz)


def validate_transform(T, name: str = "transform") -> np.ndarray:
    """Check a 4x4 rigid transform (finite, orthonormal rotation, det +1); return it as float64.

    Raises:
        CalibrationError: with a message naming ``name``.
    """
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4):
        raise CalibrationError(f"{name} must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise CalibrationError(f"{name} has non-finite entries")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0:
        raise CalibrationError(f"{name} rotation is not a proper rotation matrix")
    if not np.allclose(T[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{name} last row must be [0, 0, 0, 1]")
    return T
