"""Label images as other segmenters publish them, for the label-map tests: Cityscapes ids and
Cam2BEV colours of native labels, and bags whose label topics are rewritten that way."""

from __future__ import annotations

import pathlib
from collections.abc import Callable

import numpy as np

from bev_mapper_core.labels.classes import NUM_LABELS, Label

L = Label

#: Cityscapes class -> (labelId, trainId, Cam2BEV colour, expected Label), written out here
#: independently of the module's tables (cityscapesScripts labels.py; Cam2BEV convert_30.xml).
CITYSCAPES = {
    "unlabeled": (0, 255, None, L.UNLABELED),
    "ego vehicle": (1, 255, None, L.UNLABELED),
    "static": (4, 255, (0, 0, 0), L.OBSTACLE),
    "ground": (6, 255, (81, 0, 81), L.TERRAIN),
    "road": (7, 0, (128, 64, 128), L.ROAD),
    "sidewalk": (8, 1, (244, 35, 232), L.SIDEWALK),
    "parking": (9, 255, (250, 170, 160), L.ROAD),
    "building": (11, 2, (70, 70, 70), L.BUILDING),
    "wall": (12, 3, (102, 102, 156), L.BUILDING),
    "fence": (13, 4, (190, 153, 153), L.OBSTACLE),
    "bridge": (15, 255, (150, 100, 100), L.UNLABELED),
    "pole": (17, 5, (153, 153, 153), L.OBSTACLE),
    "traffic light": (19, 6, (250, 170, 30), L.OBSTACLE),
    "traffic sign": (20, 7, (220, 220, 0), L.OBSTACLE),
    "vegetation": (21, 8, (107, 142, 35), L.TERRAIN),
    "terrain": (22, 9, (152, 251, 152), L.TERRAIN),
    "sky": (23, 10, (70, 130, 180), L.UNLABELED),
    "person": (24, 11, (255, 0, 0), L.PEDESTRIAN),
    "rider": (25, 12, (220, 20, 60), L.PEDESTRIAN),
    "car": (26, 13, (0, 0, 142), L.VEHICLE),
    "truck": (27, 14, (0, 0, 70), L.VEHICLE),
    "bus": (28, 15, (0, 60, 100), L.VEHICLE),
    "train": (31, 16, (0, 80, 100), L.VEHICLE),
    "motorcycle": (32, 17, (0, 0, 230), L.VEHICLE),
    "bicycle": (33, 18, (119, 11, 32), L.VEHICLE),
}
#: How a native label is written by a Cityscapes-style segmenter (it has no lane divider,
#: crossing or curb class), and what comes back: the "equivalent native" labels.
AS_CITYSCAPES = {L.UNLABELED: "sky", L.ROAD: "road", L.LANE_DIVIDER: "road", L.PED_CROSSING: "road",
                 L.ROAD_BOUNDARY: "sidewalk", L.SIDEWALK: "sidewalk", L.VEHICLE: "car", L.PEDESTRIAN: "person",
                 L.OBSTACLE: "pole", L.BUILDING: "building", L.TERRAIN: "vegetation"}
EQUIVALENT_NATIVE = {L.LANE_DIVIDER: L.ROAD, L.PED_CROSSING: L.ROAD, L.ROAD_BOUNDARY: L.SIDEWALK}


def to_upstream(native: np.ndarray, scheme: str) -> np.ndarray:
    """A native label image as ``scheme``'s segmenter would publish it (ids, or rgb8 colours)."""
    col = {"cityscapes_ids": 0, "cityscapes_train_ids": 1, "cam2bev": 2}[scheme]
    table = np.zeros((NUM_LABELS, 3) if col == 2 else NUM_LABELS, np.uint8)
    for lab, name in AS_CITYSCAPES.items():
        table[lab] = CITYSCAPES[name][col]
    return table[native]


def equivalent_native(native: np.ndarray) -> np.ndarray:
    """What a Cityscapes-style segmenter can say of ``native``: markings as road, curbs as sidewalk."""
    table = np.arange(NUM_LABELS, dtype=np.uint8)
    for a, b in EQUIVALENT_NATIVE.items():
        table[a] = b
    return table[native]


def all_native() -> np.ndarray:
    """Every native label, a few times: ``(3, 2 * NUM_LABELS)`` uint8."""
    return np.tile(np.arange(NUM_LABELS, dtype=np.uint8), (3, 2))


def relabel_bag(src: pathlib.Path, dst: pathlib.Path, convert: Callable[[np.ndarray], tuple[np.ndarray, str]]) -> pathlib.Path:
    """A copy of bag ``src`` at ``dst`` whose label images are ``convert(native) -> (array, encoding)``."""
    from bags.io import topics as T  # noqa: PLC0415 - the bag libraries only where bags are written
    from bags.io.reader import BagReader  # noqa: PLC0415
    from bags.io.writer import BagWriter  # noqa: PLC0415
    from msg_adapters import header_stamp_ns, image_to_array, make_image  # noqa: PLC0415

    with BagReader(src) as r, BagWriter(dst) as w:
        for key, value in r.custom_data.items():
            w.set_custom_data(key, value)
        for topic in r._src.topic_order:  # the bag's topic order is its camera order
            w.add_topic(topic, r.topics[topic].msgtype, latched=topic in r.latched_topics)
        for m in r.messages():
            msg = m.msg
            parsed = T.parse_camera_topic(m.topic)
            if parsed is not None and parsed[1] == "labels":
                arr, enc = convert(image_to_array(msg))
                msg = make_image(w.factory, arr, enc, header_stamp_ns(msg), msg.header.frame_id)
            w.write(m.topic, msg, m.log_ns)
    return dst
