"""Semantic classes: the per-pixel label ids of camera label images and the BEV layers.

A label image (``sensor_msgs/Image`` mono8) carries one :class:`Label` id per pixel, as an
upstream 2-D segmenter would publish (other segmenters' ids or colour palettes are converted to
these by :mod:`~bev_mapper_core.labels.label_maps`). BEV layers are multi-label: each :class:`BevClass` lists
the label ids that count as that class (a lane divider also lies on drivable surface).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from ..errors import ConfigError


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


def _rgb(hex_code: str) -> tuple[int, int, int]:
    return tuple(int(hex_code[i:i + 2], 16) for i in (1, 3, 5))  # "#RRGGBB"


#: Display colour (RGB) of every BEV class name, the one source of BEV colours.
#:
#: The first nine colours are Paul Tol's *muted* qualitative scheme (https://personal.sron.nl/~pault/,
#: "Colour schemes and templates", 2021), designed to stay distinct for colour-blind viewers.
#: Each class name gets its own colour, so the standard set and Cam2BEV's set (``road``,
#: ``vehicle``, ``static``; vehicle shares the standard vehicle's colour) never repeat a colour,
#: whichever mix ``--classes`` asks for. The assignment keeps touching classes far apart, also
#: under simulated protanopia, deuteranopia and tritanopia (``tests/bags/report/test_pictures.py`` checks
#: CIELAB distances): light cyan road surface, dark wine lane dividers and sand crossings on it,
#: rose curbs, olive sidewalks, green vehicles and indigo pedestrians (pedestrians and curbs
#: were both red before). Neutral greys never mean a class: :data:`EMPTY_COLOR` is a known cell
#: with no class, :data:`UNKNOWN_COLORS` the hatch of unknown cells. No further colour keeps those
#: margins against all nine, so S2G2's two own classes (``terrain`` brown, ``obstacle`` Tol's
#: blue) are distinct within their set (road, sidewalk, terrain, obstacle) and from the greys, and
#: at least dE 24 from every other class colour.
CLASS_COLORS: dict[str, tuple[int, int, int]] = {
    "drivable": _rgb("#88CCEE"),  # cyan
    "lane_divider": _rgb("#882255"),  # wine
    "ped_crossing": _rgb("#DDCC77"),  # sand
    "road_boundary": _rgb("#CC6677"),  # rose
    "sidewalk": _rgb("#999933"),  # olive
    "vehicle": _rgb("#117733"),  # green
    "pedestrian": _rgb("#332288"),  # indigo
    "road": _rgb("#44AA99"),  # teal (Cam2BEV)
    "static": _rgb("#AA4499"),  # purple (Cam2BEV)
    "terrain": _rgb("#996633"),  # brown (S2G2)
    "obstacle": _rgb("#4477AA"),  # blue (S2G2)
}
#: Known cells where no class is present: near-white.
EMPTY_COLOR: tuple[int, int, int] = (240, 240, 240)
#: Unknown cells (the mapper's ``known`` False; in pictures also ground truth no camera sees):
#: dark diagonal hatch, base colour and stripe colour. Greys this dark stay clear of every class
#: colour also under colour-blind simulation (mid greys would not).
UNKNOWN_COLORS: tuple[tuple[int, int, int], tuple[int, int, int]] = ((16, 16, 16), (46, 46, 46))
#: Hatch geometry in display pixels: a stripe ``HATCH_WIDTH`` wide every ``HATCH_PERIOD``.
HATCH_PERIOD, HATCH_WIDTH = 6, 2

_ROAD = (Label.ROAD, Label.LANE_DIVIDER, Label.PED_CROSSING)

#: The BEV classes, in layer order.
BEV_CLASSES: tuple[BevClass, ...] = (
    BevClass("drivable", _ROAD, True, CLASS_COLORS["drivable"]),
    BevClass("lane_divider", (Label.LANE_DIVIDER,), True, CLASS_COLORS["lane_divider"]),
    BevClass("ped_crossing", (Label.PED_CROSSING,), True, CLASS_COLORS["ped_crossing"]),
    BevClass("road_boundary", (Label.ROAD_BOUNDARY,), True, CLASS_COLORS["road_boundary"]),
    BevClass("sidewalk", (Label.SIDEWALK,), True, CLASS_COLORS["sidewalk"]),
    BevClass("vehicle", (Label.VEHICLE,), False, CLASS_COLORS["vehicle"]),
    BevClass("pedestrian", (Label.PEDESTRIAN,), False, CLASS_COLORS["pedestrian"]),
)
BEV_CLASS_NAMES: tuple[str, ...] = tuple(c.name for c in BEV_CLASSES)
#: Cam2BEV's three-class setting (road / dynamic / other static), built from the same labels.
CAM2BEV_CLASSES: tuple[BevClass, ...] = (
    BevClass("road", _ROAD, True, CLASS_COLORS["road"]),
    BevClass("vehicle", (Label.VEHICLE, Label.PEDESTRIAN), False, CLASS_COLORS["vehicle"]),
    BevClass(
        "static",
        (Label.ROAD_BOUNDARY, Label.SIDEWALK, Label.OBSTACLE, Label.BUILDING, Label.TERRAIN),
        False,
        CLASS_COLORS["static"],
    ),
)


#: S2G2's four classes (the MonoOccupancy ground truth of the paper: road, sidewalk, terrain,
#: obstacle), built from the same labels; ``road`` and ``sidewalk`` are the classes of those
#: names above, ``obstacle`` is everything standing on the ground.
S2G2_CLASSES: tuple[BevClass, ...] = (
    CAM2BEV_CLASSES[0],
    BEV_CLASSES[4],
    BevClass("terrain", (Label.TERRAIN,), True, CLASS_COLORS["terrain"]),
    BevClass("obstacle", (Label.VEHICLE, Label.PEDESTRIAN, Label.OBSTACLE, Label.BUILDING), False,
             CLASS_COLORS["obstacle"]),
)
#: Every class set by name (``--classes standard|cam2bev|s2g2``).
CLASS_SETS: dict[str, tuple[BevClass, ...]] = {"standard": BEV_CLASSES, "cam2bev": CAM2BEV_CLASSES,
                                               "s2g2": S2G2_CLASSES}


def bev_class(name: str) -> BevClass:
    """Look up a BEV class by name (the standard set first, then Cam2BEV's, then S2G2's)."""
    for c in BEV_CLASSES + CAM2BEV_CLASSES + S2G2_CLASSES:
        if c.name == name:
            return c
    raise ConfigError(f"unknown BEV class {name!r}; known: {list(BEV_CLASS_NAMES)}, "
                      f"Cam2BEV's {[c.name for c in CAM2BEV_CLASSES]} and S2G2's {[c.name for c in S2G2_CLASSES]}")


def known_class_names() -> tuple[str, ...]:
    """Every BEV class name :func:`bev_class` knows: the standard set, then Cam2BEV's and S2G2's others."""
    return tuple(dict.fromkeys(c.name for c in BEV_CLASSES + CAM2BEV_CLASSES + S2G2_CLASSES))


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


#: Weight of the label colour in :func:`overlay_labels` (the image keeps the rest).
OVERLAY_ALPHA = 0.5


def overlay_labels(image: np.ndarray, labels: np.ndarray, alpha: float = OVERLAY_ALPHA) -> np.ndarray:
    """An RGB image ``(H, W, 3)`` uint8 with its label image ``(H, W)`` blended over it: each pixel
    is ``(1 - alpha) * image + alpha * LABEL_COLORS[label]`` (unlabelled pixels darken, their
    colour being black).
    """
    colors = colorize_labels(labels).astype(np.float32)
    out = (1.0 - alpha) * image.astype(np.float32) + alpha * colors
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def colorize_layers(layers: np.ndarray, classes=BEV_CLASSES, known=None, threshold=0.5) -> np.ndarray:
    """RGB picture ``(H, W, 3)`` uint8 of class layers ``(C, H, W)``, in grid orientation.

    Later classes are drawn on top; known empty cells are :data:`EMPTY_COLOR`, unknown cells
    (``known`` False) the :data:`UNKNOWN_COLORS` hatch. No legend or ego: see :func:`bev_picture`.
    """
    from ..display import class_codes, color_table, hatch_mask  # noqa: PLC0415 - display imports us

    classes = tuple(classes)[: layers.shape[0]]
    codes = class_codes(layers, threshold)
    if known is not None:
        unknown = ~np.asarray(known, bool)
        stripes = hatch_mask(*codes.shape)
        codes[unknown] = len(classes) + 1 + stripes[unknown]
    return color_table(classes)[codes]


def bev_picture(grid, layers: np.ndarray, classes=BEV_CLASSES, known=None) -> np.ndarray:
    """Display picture of class layers ``(C, H, W)`` on ``grid`` (the node's ``bev/image``).

    The map is in display orientation (:meth:`BevGrid.to_display`: forward up, left on the left),
    one pixel per cell, unknown cells hatched, the ego footprint at the origin; a legend strip on
    its right names the class colours and shows the axes and a metres scale bar (see
    :class:`~bev_mapper_core.display.BevPainter`). Returns C-contiguous RGB uint8 of shape
    ``(max(W, legend height), H + legend width, 3)``; the map is ``[:W, :H]``. The static parts
    are cached per grid and classes, so a frame costs about what the bare map does.
    """
    from ..display import painter  # noqa: PLC0415 - display imports this module

    return painter(grid, tuple(classes)).picture(layers, known)
