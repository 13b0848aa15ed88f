"""Label images -> ``(H, W)`` uint8 :class:`~bev_mapper_core.labels.classes.Label` ids.

A label image comes from an upstream 2-D segmenter. Which ids (or colours) it holds is the
``label_map`` setting (:mod:`bev_mapper_core.labels.label_maps`): this package's own ids (``native``,
the default), another segmenter's ids (mono8) or a colour palette (rgb8). The functions here
decode the message with the size checks and limits of :mod:`msg_adapters.image`, check that its
encoding is the one the label map expects, and apply the map once, so that what they return is
what every mapper takes.

===========================  ==============================  =========================
label map encoding           ``sensor_msgs/Image`` encoding  ``CompressedImage``
===========================  ==============================  =========================
mono8 (native, Cityscapes)   ``mono8``, ``8UC1``             8-bit single-channel PNG
rgb8 (Cam2BEV, palettes)     ``rgb8``, ``bgr8``              8-bit RGB PNG
===========================  ==============================  =========================

Palette colours must match exactly, so colour-coded label images must travel losslessly (raw
or PNG; JPEG changes colours, and those pixels become unlabeled). Anything else is an
:class:`~msg_adapters.errors.EncodingError` that names the label map and what it expects.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bev_mapper_core.errors import InputError
from bev_mapper_core.labels.label_maps import NATIVE, LabelMap, label_map

from ._fields import as_str, byte_buffer, field
from .errors import EncodingError
from .image import compressed_to_array, image_to_array
from .limits import DEFAULT_LIMITS, AdapterLimits

#: ``sensor_msgs/Image`` encodings accepted per label-map encoding.
LABEL_IMAGE_ENCODINGS: dict[str, tuple[str, ...]] = {"mono8": ("mono8", "8UC1"), "rgb8": ("rgb8", "bgr8")}
_HINT = {
    "mono8": "colour-coded label images need an rgb8 label_map (cam2bev, or a YAML palette with encoding: rgb8)",
    "rgb8": "label ids need a mono8 label_map (native, cityscapes_ids, cityscapes_train_ids, or a YAML file)",
}


def _map(lm: LabelMap | None) -> LabelMap:
    return label_map(NATIVE) if lm is None else lm


def _apply(lm: LabelMap, arr: np.ndarray) -> np.ndarray:
    try:
        return lm.apply(arr)
    except InputError as exc:
        raise EncodingError(str(exc)) from None


def image_to_labels(msg: Any, expected_size: Any = None, *, limits: AdapterLimits = DEFAULT_LIMITS,
                    label_map: LabelMap | None = None) -> np.ndarray:
    """Decode a label image and map it to ``(H, W)`` uint8 Label ids.

    Args:
        msg: the ``sensor_msgs/Image``.
        expected_size, limits: as in :func:`~msg_adapters.image.image_to_array` (checked before
            anything is decoded).
        label_map: what the image holds (:func:`bev_mapper_core.labels.label_maps.label_map`); None =
            ``native`` (mono8 Label ids, returned as they are).

    Raises:
        EncodingError: an encoding the label map does not take (see the module table), or any
            defect :func:`~msg_adapters.image.image_to_array` refuses.
    """
    lm = _map(label_map)
    encoding = as_str(field(msg, "encoding", EncodingError, "label image"), "encoding", EncodingError,
                      "label image")
    accepted = LABEL_IMAGE_ENCODINGS[lm.encoding]
    if encoding not in accepted:
        raise EncodingError(f"label images must be {' or '.join(accepted)} for label_map {lm.name!r}, "
                            f"got {encoding!r}; {_HINT[lm.encoding]}")
    return _apply(lm, image_to_array(msg, expected_size=expected_size, limits=limits))


def _is_jpeg(msg: Any) -> bool:
    """Whether ``msg.data`` starts with JPEG's start-of-image marker (other defects: not here)."""
    try:
        head = byte_buffer(field(msg, "data", EncodingError, "compressed image"), "data", EncodingError,
                           "compressed image")[:2]
    except EncodingError:
        return False  # compressed_to_array says why
    return bytes(head) == b"\xff\xd8"


def compressed_to_labels(msg: Any, expected_size: Any = None, *, limits: AdapterLimits = DEFAULT_LIMITS,
                         label_map: LabelMap | None = None, check_format: bool = False) -> np.ndarray:
    """Decode a compressed label image (PNG) and map it to ``(H, W)`` uint8 Label ids.

    ``expected_size``, ``limits`` and ``label_map`` as in :func:`image_to_labels`; the size in
    the PNG/JPEG header (and with ``check_format`` the ``format`` string) is checked before
    decoding (:func:`~msg_adapters.image.compressed_to_array`).

    Raises:
        EncodingError: a JPEG (lossy: it changes label ids), the decoded image is not what the label map takes (8-bit single-channel
            for mono8 maps, 8-bit RGB for rgb8 maps), or any defect ``compressed_to_array``
            refuses.
    """
    lm = _map(label_map)
    if _is_jpeg(msg):  # before decoding; the bag reader and the node refuse it alike
        raise EncodingError("compressed label images must be PNG: JPEG changes label ids")
    img = compressed_to_array(msg, expected_size, limits=limits, check_format=check_format)
    channels = 1 if img.ndim == 2 else img.shape[2]
    want = 1 if lm.encoding == "mono8" else 3
    if channels != want or img.dtype != np.uint8:
        what = "single-channel" if want == 1 else "RGB"
        raise EncodingError(f"compressed label images must be 8-bit {what} for label_map {lm.name!r}, got "
                            f"{channels} channel(s) of {img.dtype}; {_HINT[lm.encoding]}")
    return _apply(lm, img)


__all__ = ["LABEL_IMAGE_ENCODINGS", "compressed_to_labels", "image_to_labels"]
