"""Semantic classes: the per-pixel label ids of camera label images and the BEV layers.

A label image (``sensor_msgs/Image`` mono8) carries one :class:`Label` id per pixel, as an
upstream 2-D segmenter would publish. BEV layers are multi-label: each :class:`BevClass` lists
the label ids that count as that class (a lane divider also lies on drivable surface).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from .errors import ConfigError


class Label(IntEnum):
    """Pixel label ids of semantic camera images."""

    UNLABELED = 0  # sky, anything not modelled
    ROAD = 1
    LANE_DIVIDER = 2
    PED_CROSSING = 3
    ROAD_BOUNDARY = 4  # curb
    SIDEWALK = 5
    VEHICLE = 6
    PEDESTRIAN = 7
    OBSTACLE = 8  # static obstacles: poles, cones, bins
    BUILDING = 9
    TERRAIN = 10  # grass, verges


NUM_LABELS = len(Label)

#: Display colour (RGB) of each label, indexed by label id.
LABEL_COLORS = np.array(
    [
        (0, 0, 0),
        (128, 64, 128),
        (255, 255, 255),
        (255, 200, 0),
        (190, 153, 153),
        (244, 35, 232),
        (0, 0, 142),
        (220, 20, 60),
        (250, 170, 30),
        (70, 70, 70),
        (107, 142, 35),
    ],
    dtype=np.uint8,
)


@dataclass(frozen=True)
class BevClass:
    """A BEV layer: its name, the label ids it is made of, whether it is flat, its colour."""

    name: str
    labels: tuple[int, ...]
    flat: bool
    color: tuple[int, int, int]


#: The BEV classes, in layer order.
BEV_CLASSES: tuple[BevClass, ...] = (
    BevClass("drivable", (Label.ROAD, Label.LANE_DIVIDER, Label.PED_CROSSING), True, (128, 64, 128)),
    BevClass("lane_divider", (Label.LANE_DIVIDER,), True, (255, 255, 255)),
    BevClass("ped_crossing", (Label.PED_CROSSING,), True, (255, 200, 0)),
    BevClass("road_boundary", (Label.ROAD_BOUNDARY,), True, (255, 0, 0)),
    BevClass("sidewalk", (Label.SIDEWALK,), True, (244, 35, 232)),
    BevClass("vehicle", (Label.VEHICLE,), False, (0, 0, 255)),
    BevClass("pedestrian", (Label.PEDESTRIAN,), False, (220, 20, 60)),
)
BEV_CLASS_NAMES: tuple[str, ...] = tuple(c.name for c in BEV_CLASSES)
#: Cam2BEV's three-class setting (road / dynamic / other static), built from the same labels.
CAM2BEV_CLASSES: tuple[BevClass, ...] = (
    BevClass("road", (Label.ROAD, Label.LANE_DIVIDER, Label.PED_CROSSING), True, (128, 64, 128)),
    BevClass("vehicle", (Label.VEHICLE, Label.PEDESTRIAN), False, (0, 0, 255)),
    BevClass(
        "static",
        (Label.ROAD_BOUNDARY, Label.SIDEWALK, Label.OBSTACLE, Label.BUILDING, Label.TERRAIN),
        False,
        (70, 70, 70),
    ),
)


def bev_class(name: str) -> BevClass:
    """Look up a BEV class by name (the standard set first, then the Cam2BEV set)."""
    for c in BEV_CLASSES + CAM2BEV_CLASSES:
        if c.name == name:
            return c
    raise ConfigError(f"unknown BEV class {name!r}; known: {list(BEV_CLASS_NAMES)} "
                      f"and Cam2BEV's {[c.name for c in CAM2BEV_CLASSES]}")


def resolve_classes(names) -> tuple[BevClass, ...]:
    """Classes for a list of names (``None`` = all standard classes)."""
    if names is None:
        return BEV_CLASSES
    return tuple(bev_class(n) for n in names)


def class_cover(name: str, available) -> tuple[str, ...] | None:
    """Layers among ``available`` (class names) that together mean exactly the class ``name``.

    Used to score a prediction against ground truth of another class set (Cam2BEV's ``road``
    against the standard ``drivable``, or the other way round): the same name, else the classes
    whose label sets lie inside ``name``'s and together cover it exactly. Their union is then
    the same layer, since a BEV layer is the set of cells carrying one of its labels. ``None``
    when no such cover exists (e.g. Cam2BEV's ``static`` against the standard seven, which have
    no obstacle, building or terrain layer).

    Raises:
        ConfigError: an unknown class name.
    """
    if name in available:
        return (name,)
    want = set(bev_class(name).labels)
    labels = {n: set(bev_class(n).labels) for n in available}
    parts = [n for n, lab in labels.items() if lab <= want]
    # keep the largest parts: a layer inside another part adds nothing to the union
    parts = [n for n in parts if not any(labels[n] < labels[m] for m in parts)]
    if parts and set().union(*(labels[n] for n in parts)) == want:
        return tuple(parts)
    return None


def label_lut(classes) -> np.ndarray:
    """Boolean table ``(NUM_LABELS, C)``: ``lut[label, c]`` is True if label belongs to class c."""
    lut = np.zeros((NUM_LABELS, len(classes)), dtype=bool)
    for ci, c in enumerate(classes):
        lut[list(c.labels), ci] = True
    return lut


def labels_to_layers(labels: np.ndarray, classes=BEV_CLASSES) -> np.ndarray:
    """One-hot a label image ``(H, W)`` into class layers ``(C, H, W)`` bool (multi-label)."""
    lut = label_lut(classes)
    clipped = np.where(labels < NUM_LABELS, labels, Label.UNLABELED)
    return np.moveaxis(lut[clipped], -1, 0)  # (H, W, C) -> (C, H, W)


def colorize_labels(labels: np.ndarray) -> np.ndarray:
    """RGB visualisation ``(H, W, 3)`` uint8 of a label image."""
    clipped = np.where(labels < NUM_LABELS, labels, Label.UNLABELED)
    return LABEL_COLORS[clipped]


def colorize_layers(layers: np.ndarray, classes=BEV_CLASSES, known=None, threshold=0.5) -> np.ndarray:
    """RGB picture ``(H, W, 3)`` of class layers ``(C, H, W)`` (later classes drawn on top).

    Unknown cells (``known`` False) are drawn dark grey, empty known cells light grey.
    """
    C, H, W = layers.shape
    img = np.full((H, W, 3), 40, dtype=np.uint8)
    if known is None:
        known = np.ones((H, W), dtype=bool)
    img[known] = 200
    for ci, c in enumerate(classes[:C]):
        on = (layers[ci] >= threshold) & known
        img[on] = c.color
    return img


def bev_picture(grid, layers: np.ndarray, classes=BEV_CLASSES, known=None) -> np.ndarray:
    """Display picture of class layers ``(C, H, W)`` on ``grid``: ``(W, H, 3)`` uint8 RGB,
    forward up and left on the left (see :meth:`BevGrid.to_display`), C-contiguous."""
    return np.ascontiguousarray(grid.to_display(colorize_layers(layers, tuple(classes), known)))
