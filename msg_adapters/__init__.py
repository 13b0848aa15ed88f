"""msg_adapters: pure conversions between ROS 2 messages and bev_mapper_core / numpy types.

No rclpy (or any ROS package) is imported here: reading is duck-typed and works on rclpy
messages and on rosbags-deserialized messages alike; building goes through a factory
(:class:`RclpyFactory` imports message classes lazily, :class:`RosbagsFactory` uses a
rosbags typestore).
"""

from .camera_info import camera_info_fields, camera_info_key, camera_info_to_model, make_camera_info
from .errors import (
    AdapterError,
    CalibrationMessageError,
    EncodingError,
    GridMessageError,
    MessageFactoryError,
    StampError,
    SyncConfigError,
    TransformError,
)
from .factory import (
    MessageFactory,
    RclpyFactory,
    RosbagsFactory,
    header_stamp_ns,
    make_header,
    make_time,
    ns_to_sec_nanosec,
    stamp_to_ns,
)
from .grid import check_grid_info, grid_from_info, make_occupancy_grid, occupancy_grid_to_layer
from .image import (
    ENCODINGS,
    array_to_image_fields,
    check_image_size,
    compressed_to_array,
    compressed_to_rgb,
    format_problem,
    image_to_array,
    image_to_rgb,
    make_compressed_image,
    make_image,
)
from .image_header import CompressedHeader, compressed_image_header
from .labels import LABEL_IMAGE_ENCODINGS, compressed_to_labels, image_to_labels
from .limits import DEFAULT_LIMITS, AdapterLimits
from .sync import FrameSynchronizer, SyncConfig, SyncedSet, SyncStats
from .tf import (
    OdometryState,
    StampedTransform,
    TfTree,
    ego_from_camera,
    make_odometry,
    make_tf_message,
    make_transform_stamped,
    odometry_to_state,
    tf_message_transforms,
    transform_stamped_to_matrix,
)

__all__ = [
    "DEFAULT_LIMITS",
    "ENCODINGS",
    "LABEL_IMAGE_ENCODINGS",
    "AdapterError",
    "AdapterLimits",
    "CalibrationMessageError",
    "CompressedHeader",
    "EncodingError",
    "FrameSynchronizer",
    "GridMessageError",
    "MessageFactory",
    "MessageFactoryError",
    "OdometryState",
    "RclpyFactory",
    "RosbagsFactory",
    "StampError",
    "StampedTransform",
    "SyncConfig",
    "SyncConfigError",
    "SyncStats",
    "SyncedSet",
    "TfTree",
    "TransformError",
    "array_to_image_fields",
    "camera_info_fields",
    "camera_info_key",
    "camera_info_to_model",
    "check_grid_info",
    "check_image_size",
    "compressed_image_header",
    "compressed_to_array",
    "compressed_to_labels",
    "compressed_to_rgb",
    "ego_from_camera",
    "format_problem",
    "grid_from_info",
    "header_stamp_ns",
    "image_to_array",
    "image_to_labels",
    "image_to_rgb",
    "make_camera_info",
    "make_compressed_image",
    "make_header",
    "make_image",
    "make_occupancy_grid",
    "make_odometry",
    "make_tf_message",
    "make_time",
    "make_transform_stamped",
    "ns_to_sec_nanosec",
    "occupancy_grid_to_layer",
    "odometry_to_state",
    "stamp_to_ns",
    "tf_message_transforms",
    "transform_stamped_to_matrix",
]
