"""Topic names and types of the bags this tool writes and reads (one place for both)."""

from __future__ import annotations

TF_STATIC = "/tf_static"
#: ``tf2_msgs/TFMessage`` of the ego motion, ``odom -> base_link`` at each frame stamp.
TF = "/tf"
ODOM = "/odom"
GT_PREFIX = "/bev/gt/"
#: OccupancyGrid: 100 where the cell's ground point is seen by some camera, 0 elsewhere.
GROUND_VISIBILITY = "/bev/visibility/ground"
#: OccupancyGrid: 100 where some camera sees the cell (its ground point, or inside an object's
#: footprint the object), 0 elsewhere: the cells where ``/bev/gt/<class>`` is not -1.
ANY_VISIBILITY = "/bev/visibility/any"
#: ``/bev/truth/<class>``: what IS in every cell, seen or not (100 present, 0 absent, never -1);
#: equal to ``/bev/gt/<class>`` where that is not -1.
TRUTH_PREFIX = "/bev/truth/"
CAMERA_PREFIX = "/cameras/"

IMAGE_TYPE = "sensor_msgs/msg/Image"
#: image_transport's ``compressed`` transport: JPEG or PNG bytes (:func:`compressed_topic`).
COMPRESSED_IMAGE_TYPE = "sensor_msgs/msg/CompressedImage"
#: The image types a camera's image topic may carry.
IMAGE_TYPES = (IMAGE_TYPE, COMPRESSED_IMAGE_TYPE)
#: image_transport's suffix of the compressed transport: ``<image topic>/compressed``.
COMPRESSED_SUFFIX = "/compressed"
CAMERA_INFO_TYPE = "sensor_msgs/msg/CameraInfo"
TF_TYPE = "tf2_msgs/msg/TFMessage"
ODOM_TYPE = "nav_msgs/msg/Odometry"
GRID_TYPE = "nav_msgs/msg/OccupancyGrid"

#: Image kinds per camera: topic suffix.
IMAGE_KINDS = {"rgb": "image_raw", "labels": "labels"}


def image_topic(camera: str, kind: str = "rgb") -> str:
    """``/cameras/<camera>/image_raw`` (kind ``rgb``) or ``/cameras/<camera>/labels``."""
    return f"{CAMERA_PREFIX}{camera}/{IMAGE_KINDS[kind]}"


def compressed_topic(image_topic_name: str) -> str:
    """``<image topic>/compressed``: where image_transport publishes the topic's JPEG/PNG messages."""
    return image_topic_name + COMPRESSED_SUFFIX


def is_compressed_topic(topic: str) -> bool:
    """Whether ``topic`` is image_transport's compressed transport of an image topic."""
    return topic.endswith(COMPRESSED_SUFFIX)


def camera_info_topic(camera: str) -> str:
    """``/cameras/<camera>/camera_info``."""
    return f"{CAMERA_PREFIX}{camera}/camera_info"


def gt_topic(class_name: str) -> str:
    """``/bev/gt/<class>``."""
    return f"{GT_PREFIX}{class_name}"


def truth_topic(class_name: str) -> str:
    """``/bev/truth/<class>``."""
    return f"{TRUTH_PREFIX}{class_name}"


def parse_camera_topic(topic: str) -> tuple[str, str] | None:
    """``('front', 'rgb' | 'labels' | 'camera_info')`` for a camera topic, else ``None``; an
    image topic's compressed transport (``/cameras/front/image_raw/compressed``) is its camera's
    image topic of that kind too.
    """
    if not topic.startswith(CAMERA_PREFIX):
        return None
    parts = topic[len(CAMERA_PREFIX):].split("/")
    if len(parts) == 3 and "/" + parts[2] == COMPRESSED_SUFFIX and parts[1] != "camera_info":
        parts = parts[:2]
    if len(parts) != 2:
        return None
    camera, leaf = parts
    if leaf == "camera_info":
        return camera, "camera_info"
    for kind, suffix in IMAGE_KINDS.items():
        if leaf == suffix:
            return camera, kind
    return None


def parse_gt_topic(topic: str) -> str | None:
    """The class name of a ``/bev/gt/<class>`` topic, else ``None``."""
    if topic.startswith(GT_PREFIX) and "/" not in topic[len(GT_PREFIX):]:
        return topic[len(GT_PREFIX):] or None
    return None


def parse_truth_topic(topic: str) -> str | None:
    """The class name of a ``/bev/truth/<class>`` topic, else ``None``."""
    if topic.startswith(TRUTH_PREFIX) and "/" not in topic[len(TRUTH_PREFIX):]:
        return topic[len(TRUTH_PREFIX):] or None
    return None
