"""Transforms (``geometry_msgs/TransformStamped``, ``tf2_msgs/TFMessage``) and odometry.

A ``TransformStamped`` with ``header.frame_id = parent`` and ``child_frame_id = child`` gives
``parent_from_child`` (it maps points in the child frame into the parent frame). A camera's
``ego_from_cam`` is therefore the transform ``base_link -> <camera optical frame>``, possibly
chained through intermediate frames (``base_link -> camera_link -> camera_optical_frame``);
:class:`TfTree` does the chaining. Frame names are compared without a leading ``/``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from bev_mapper_core.errors import CalibrationError
from bev_mapper_core.geometry.transforms import invert_transform, make_transform, quat_to_rot, rot_to_quat

from ._fields import as_float, as_str, field
from .errors import StampError, TransformError
from .factory import (
    MessageFactory,
    header_stamp_ns,
    make_header,
    make_point,
    make_quaternion,
    make_vector3,
)

#: tf2 rejects quaternions whose norm is further than this from 1.
QUATERNION_TOLERANCE = 1e-2


def _frame(name: Any, what: str = "frame_id") -> str:
    return as_str(name, what, TransformError, "transform").lstrip("/")


def _floats(obj: Any, keys: str, what: str, finite: bool = True) -> np.ndarray:
    """``[obj.<k> for k in keys]`` as float64, each a number (finite unless ``finite=False``)."""
    return np.array([as_float(field(obj, k, TransformError, what), k, TransformError, what, finite)
                     for k in keys], dtype=np.float64)


def _stamp_ns(msg: Any, what: str) -> int:
    try:
        return header_stamp_ns(msg)
    except StampError as exc:
        raise TransformError(f"{what}: {exc}") from None


@dataclass(frozen=True)
class StampedTransform:
    """``parent_from_child`` (4x4 float64) at ``stamp_ns``."""

    parent: str
    child: str
    matrix: np.ndarray
    stamp_ns: int = 0


def quaternion_to_rotation(q: Any, what: str = "quaternion") -> np.ndarray:
    """3x3 rotation of a ``geometry_msgs/Quaternion``; rejects non-finite / non-unit ones.

    Raises:
        TransformError: a field is missing or not a number, or the quaternion is not unit
            (within :data:`QUATERNION_TOLERANCE`).
    """
    xyzw = _floats(q, "xyzw", what, finite=False)
    norm = math.sqrt(math.fsum(v * v for v in xyzw.tolist()))  # 1e300 components: inf; NaN stays NaN
    if not math.isfinite(norm) or abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise TransformError(f"{what} (x, y, z, w) = {tuple(xyzw.tolist())} is not a unit quaternion")
    try:
        return quat_to_rot(*xyzw)
    except CalibrationError as exc:
        raise TransformError(f"{what}: {exc}") from None


def pose_to_matrix(position: Any, orientation: Any, what: str = "pose") -> np.ndarray:
    """4x4 transform of a position (``x, y, z``) and orientation quaternion.

    Raises:
        TransformError: a field is missing or not a number, a non-finite translation, or a
            quaternion :func:`quaternion_to_rotation` refuses.
    """
    t = _floats(position, "xyz", f"{what} translation", finite=False)
    if not np.all(np.isfinite(t)):
        raise TransformError(f"{what} translation {t.tolist()} is not finite")
    return make_transform(quaternion_to_rotation(orientation, f"{what} rotation"), t)


def transform_to_matrix(transform: Any, what: str = "transform") -> np.ndarray:
    """4x4 matrix of a ``geometry_msgs/Transform`` (``translation`` + ``rotation``)."""
    return pose_to_matrix(field(transform, "translation", TransformError, what),
                          field(transform, "rotation", TransformError, what), what)


def transform_stamped_to_matrix(msg: Any) -> StampedTransform:
    """Parse a ``geometry_msgs/TransformStamped`` into a :class:`StampedTransform`.

    Raises:
        TransformError: a field is missing or of the wrong type, an empty or identical frame
            pair, a non-finite translation, a non-unit quaternion or an invalid stamp.
    """
    parent = _frame(field(msg, "header.frame_id", TransformError, "transform"), "header.frame_id")
    child = _frame(field(msg, "child_frame_id", TransformError, "transform"), "child_frame_id")
    if not parent or not child:
        raise TransformError(f"transform with empty frame name: {parent!r} -> {child!r}")
    if parent == child:
        raise TransformError(f"transform from frame {parent!r} to itself")
    what = f"transform {parent} -> {child}"
    T = transform_to_matrix(field(msg, "transform", TransformError, what), what)
    return StampedTransform(parent, child, T, _stamp_ns(msg, what))


def tf_message_transforms(msg: Any) -> list[StampedTransform]:
    """All transforms of a ``tf2_msgs/TFMessage``.

    Raises:
        TransformError: ``transforms`` is missing or not a sequence, or one transform is refused
            (the whole message is: TF messages are published as one consistent set).
    """
    transforms = field(msg, "transforms", TransformError, "TFMessage")
    if isinstance(transforms, (str, bytes)) or not hasattr(transforms, "__iter__"):
        raise TransformError(f"TFMessage transforms must be a sequence, got {type(transforms).__name__}")
    return [transform_stamped_to_matrix(t) for t in transforms]


class TfTree:
    """A static transform tree: each child has one parent; lookups chain through the tree."""

    def __init__(self, transforms: Iterable[StampedTransform] = ()) -> None:
        self._parent: dict[str, StampedTransform] = {}
        self.add(transforms)

    def add(self, transforms: Iterable[StampedTransform]) -> None:
        """Add (or replace) transforms; a child frame keeps its latest parent."""
        for t in transforms:
            self._parent[t.child] = t

    def add_message(self, msg: Any) -> None:
        """Add all transforms of a ``tf2_msgs/TFMessage``."""
        self.add(tf_message_transforms(msg))

    @property
    def frames(self) -> set[str]:
        """Every frame name the tree knows."""
        return set(self._parent) | {t.parent for t in self._parent.values()}

    def _chain(self, frame: str) -> list[tuple[str, np.ndarray]]:
        """``[(frame, I), (parent, parent_from_frame), (grandparent, gp_from_frame), ...]``."""
        chain = [(frame, np.eye(4))]
        seen = {frame}
        while frame in self._parent:
            t = self._parent[frame]
            if t.parent in seen:
                raise TransformError(f"transform tree has a cycle through {t.parent!r}")
            seen.add(t.parent)
            chain.append((t.parent, t.matrix @ chain[-1][1]))
            frame = t.parent
        return chain

    def lookup(self, target: str, source: str) -> np.ndarray:
        """``target_from_source``: maps points in ``source`` into ``target`` (4x4 float64).

        Raises:
            TransformError: a frame is unknown or the two frames are not connected.
        """
        target, source = _frame(target), _frame(source)
        if target == source:
            return np.eye(4)
        known = self.frames
        for f in (target, source):
            if f not in known:
                raise TransformError(f"unknown frame {f!r}; known frames: {sorted(known)}")
        up_src = dict(self._chain(source))  # ancestor -> ancestor_from_source
        for frame, anc_from_target in self._chain(target):
            if frame in up_src:
                return invert_transform(anc_from_target) @ up_src[frame]
        raise TransformError(f"frames {target!r} and {source!r} are not connected")


def ego_from_camera(tree: TfTree, ego_frame: str, camera_frame: str) -> np.ndarray:
    """``ego_from_cam`` 4x4 of a camera optical frame, chained through the tree."""
    return tree.lookup(ego_frame, camera_frame)


# ---------------------------------------------------------------- building
def make_transform_stamped(
    factory: MessageFactory, parent: str, child: str, matrix: np.ndarray, stamp_ns: int
) -> Any:
    """``geometry_msgs/TransformStamped`` for ``parent_from_child`` = ``matrix``."""
    T = np.asarray(matrix, dtype=np.float64)
    transform = factory.msg(
        "geometry_msgs/msg/Transform",
        translation=make_vector3(factory, T[:3, 3]),
        rotation=make_quaternion(factory, rot_to_quat(T[:3, :3])),
    )
    return factory.msg(
        "geometry_msgs/msg/TransformStamped",
        header=make_header(factory, stamp_ns, parent),
        child_frame_id=str(child),
        transform=transform,
    )


def make_tf_message(factory: MessageFactory, transforms: Iterable[StampedTransform]) -> Any:
    """``tf2_msgs/TFMessage`` holding ``transforms``."""
    items = [
        make_transform_stamped(factory, t.parent, t.child, t.matrix, t.stamp_ns) for t in transforms
    ]
    return factory.msg("tf2_msgs/msg/TFMessage", transforms=items)


# ---------------------------------------------------------------- odometry
@dataclass(frozen=True)
class OdometryState:
    """Pose and twist of a ``nav_msgs/Odometry``.

    ``world_from_ego`` maps ``child_frame_id`` (base_link) points into ``frame_id`` (odom);
    velocities are expressed in ``child_frame_id``, as in ROS.
    """

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    world_from_ego: np.ndarray
    linear_velocity: np.ndarray
    angular_velocity: np.ndarray
    #: the pose's 6x6 covariance as sent (row-major, 36 values; None: not read). Not checked here:
    #: the temporal memories count a non-finite one (bev_mapper_core.temporal.OdometryCheck).
    pose_covariance: np.ndarray | None = None


def _vec(v: Any, what: str) -> np.ndarray:
    out = _floats(v, "xyz", what, finite=False)
    if not np.all(np.isfinite(out)):
        raise TransformError(f"{what} {out.tolist()} is not finite")
    return out


def odometry_to_state(msg: Any) -> OdometryState:
    """Parse a ``nav_msgs/Odometry`` (pose, twist and the pose covariance as sent).

    Raises:
        TransformError: a field is missing or of the wrong type, a non-finite pose or twist, a
            non-unit orientation or an invalid stamp.
    """
    what = "odometry"

    def get(path: str) -> Any:
        return field(msg, path, TransformError, what)

    return OdometryState(
        stamp_ns=_stamp_ns(msg, what),
        frame_id=_frame(get("header.frame_id"), "header.frame_id"),
        child_frame_id=_frame(get("child_frame_id"), "child_frame_id"),
        world_from_ego=pose_to_matrix(get("pose.pose.position"), get("pose.pose.orientation"),
                                      "odometry pose"),
        linear_velocity=_vec(get("twist.twist.linear"), "odometry linear velocity"),
        angular_velocity=_vec(get("twist.twist.angular"), "odometry angular velocity"),
        pose_covariance=_covariance(msg),
    )


def _covariance(msg: Any) -> np.ndarray | None:
    """``pose.covariance`` as 36 floats (NaN allowed), or None when absent or not 36 numbers."""
    try:
        cov = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(-1)
    except (AttributeError, TypeError, ValueError):
        return None
    return cov if cov.size == 36 else None


def make_odometry(
    factory: MessageFactory,
    world_from_ego: np.ndarray,
    linear_velocity: Any,
    angular_velocity: Any,
    stamp_ns: int,
    frame_id: str = "odom",
    child_frame_id: str = "base_link",
) -> Any:
    """``nav_msgs/Odometry`` with zero covariances."""
    T = np.asarray(world_from_ego, dtype=np.float64)
    pose = factory.msg(
        "geometry_msgs/msg/Pose",
        position=make_point(factory, T[:3, 3]),
        orientation=make_quaternion(factory, rot_to_quat(T[:3, :3])),
    )
    twist = factory.msg(
        "geometry_msgs/msg/Twist",
        linear=make_vector3(factory, linear_velocity),
        angular=make_vector3(factory, angular_velocity),
    )
    zeros = np.zeros(36)
    return factory.msg(
        "nav_msgs/msg/Odometry",
        header=make_header(factory, stamp_ns, frame_id),
        child_frame_id=str(child_frame_id),
        pose=factory.msg(
            "geometry_msgs/msg/PoseWithCovariance",
            pose=pose,
            covariance=factory.float64_fixed(zeros, 36),
        ),
        twist=factory.msg(
            "geometry_msgs/msg/TwistWithCovariance",
            twist=twist,
            covariance=factory.float64_fixed(zeros, 36),
        ),
    )
