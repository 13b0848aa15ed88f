"""A mapped frame's messages in the output bag: ``/bev/<class>`` OccupancyGrids and the
``/bev/image`` picture, serialized once per frame.

The grids of one frame share their header and info and differ only in their cells, the last
field of an OccupancyGrid: the first class's message is serialized by rosbags, the others are
its bytes up to the cells followed by their own cells (the bytes rosbags would write for them).
The whole-percent values behind the cells (:func:`published_percent`) are computed once for
all classes and shared with the scorer, which scores the probabilities as published.
"""

from __future__ import annotations

import numpy as np

from bev_mapper_core.geometry.grid import OCC_UNKNOWN, BevGrid
from bev_mapper_core.labels.classes import bev_picture
from bev_mapper_core.mapper import BevPrediction
from msg_adapters import make_image, make_occupancy_grid

from ..io.writer import BagWriter
from .options import IMAGE_TOPIC, OUT_PREFIX


def published_percent(probs: np.ndarray) -> np.ndarray:
    """``(C, H, W)`` whole percent of ``probs`` ``(C, H, W)`` as the OccupancyGrids publish it
    (``rint(clip(p, 0, 1) * 100)``, :meth:`BevGrid.to_occupancy`'s arithmetic), in ``probs``' dtype.
    """
    out = np.clip(probs, 0.0, 1.0)
    np.multiply(out, 100.0, out=out)  # in place: the same products as clip(...) * 100.0
    return np.rint(out, out=out)


def occupancy_cells(percent: np.ndarray, known: np.ndarray | None) -> np.ndarray:
    """``(C, H*W)`` int8 OccupancyGrid data of every class (unknown cells -1), as
    :meth:`BevGrid.to_occupancy` gives each.
    """
    with np.errstate(invalid="ignore"):  # NaN only in unknown cells, overwritten below
        cells = percent.astype(np.int8)
    if known is not None:
        k = np.asarray(known, dtype=bool).view(np.uint8)  # (H, W) 1 known, 0 not
        np.multiply(cells, k, out=cells, casting="unsafe")  # unknown cells 0 (faster than a masked write)
        cells += k.astype(np.int8) + np.int8(OCC_UNKNOWN)  # unknown cells -1, the others as they are
    return cells.reshape(len(cells), -1)  # (C, H, W) -> (C, H*W)


def write_frame_messages(bw: BagWriter, grid: BevGrid, mapper, pred: BevPrediction, stamp: int, ego: str,
                         percent: np.ndarray | None = None) -> None:
    """``/bev/<class>`` grids and the ``/bev/image`` picture of one frame (``percent``: the
    frame's :func:`published_percent`, computed here when not given).
    """
    names = mapper.class_names
    if percent is None:
        percent = published_percent(pred.probs)
    cells = occupancy_cells(percent, pred.known)
    first = bw.serialize(OUT_PREFIX + names[0], make_occupancy_grid(
        bw.factory, grid, pred.probs[0], pred.known, stamp, ego))
    n = cells.shape[1]
    if first.endswith(cells[0].tobytes()):
        head = first[:len(first) - n]  # everything before the cells (their count included)
        for ci, c in enumerate(names):
            bw.write_raw(OUT_PREFIX + c, first if ci == 0 else head + cells[ci].tobytes(), stamp)
    else:  # not laid out as expected: every grid through rosbags
        for ci, c in enumerate(names):
            bw.write(OUT_PREFIX + c, make_occupancy_grid(bw.factory, grid, pred.probs[ci], pred.known,
                                                         stamp, ego), stamp)
    picture = bev_picture(grid, pred.probs, mapper.classes, pred.known)
    bw.write(IMAGE_TOPIC, make_image(bw.factory, picture, "rgb8", stamp, ego), stamp)
