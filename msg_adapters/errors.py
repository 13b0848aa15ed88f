"""Exception types of the message-adapter layer.

All of them derive from :class:`AdapterError`, itself a
:class:`bev_mapper_core.errors.BevMapperError` (and a ``ValueError``), so the ROS node and the
bag tool can catch one type for "this message cannot be used", log it and keep going.
"""

from __future__ import annotations

from bev_mapper_core.errors import BevMapperError


class AdapterError(BevMapperError, ValueError):
    """A ROS message cannot be converted to / from the core types."""


class EncodingError(AdapterError):
    """An image message has an unsupported or ambiguous encoding, or inconsistent size fields."""


class CalibrationMessageError(AdapterError):
    """A ``sensor_msgs/CameraInfo`` is uncalibrated, non-finite or inconsistent."""


class TransformError(AdapterError):
    """A transform is invalid (bad quaternion, non-finite) or cannot be looked up."""


class GridMessageError(AdapterError):
    """A ``nav_msgs/OccupancyGrid`` does not match the expected BEV grid."""


class StampError(AdapterError):
    """A ``builtin_interfaces/Time`` stamp is missing, not integers, or outside its field ranges."""


class MessageFactoryError(AdapterError):
    """A message type is unknown to the factory (package not installed, typo in the name)."""


class SyncConfigError(AdapterError):
    """The synchronizer was configured with invalid values (negative slop, no cameras, ...)."""
