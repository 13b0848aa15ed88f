"""The GT, visibility and truth layers of a frame from their OccupancyGrids, each cell through one
lookup table instead of :func:`msg_adapters.occupancy_grid_to_layer`'s arithmetic.

:func:`~msg_adapters.occupancy_grid_to_layer` checks the message's info against the grid, refuses
cells outside -1..100 and converts the int8 cells to ``(probs float32, known bool)``. A frame
holds 16 such layers; :class:`LayerDecoder` gives the same values by indexing tables of the 256
possible bytes (built by the same arithmetic; OpenCV's ``LUT``; the known and ``>= 0.5`` cells by
comparisons giving the tables' values), checks an info it has checked before by comparing
its fields, and writes straight into the frame's ``(C, H, W)`` arrays. Any layer it is not sure of
(a message not decoded by :mod:`bags.io.raw.cdr`, cells outside -1..100, a size that differs)
goes through :func:`~msg_adapters.occupancy_grid_to_layer` itself, so errors read as before.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from bev_mapper_core.geometry.grid import BevGrid
from msg_adapters import check_grid_info, occupancy_grid_to_layer

from ..raw.cdr import OccupancyGrid

_VALUES = np.arange(-1, 101).astype(np.int8)  # every valid cell value
_KNOWN = _VALUES >= 0
#: per byte of a cell (int8 read as uint8): its probability, as from_occupancy computes it
PROBS = np.zeros(256, np.float32)
PROBS[_VALUES.view(np.uint8)] = np.where(_KNOWN, _VALUES.astype(np.float32) / 100.0, 0.0).astype(np.float32)
KNOWN = np.zeros(256, bool)
KNOWN[_VALUES.view(np.uint8)] = _KNOWN
#: per byte: probability >= 0.5 (the visibility and truth layers' test)
HALF = PROBS >= 0.5
# the probability table as cv2.LUT takes it: (1, 256)
_PROBS_LUT = PROBS[None]
_UNKNOWN = 255  # -1 read as uint8
#: the cells >= 0.5 are those from this byte to 100: the same as HALF, by comparisons (faster)
HALF_FROM = int(np.argmax(HALF))
_BYTES = np.arange(256)
if not (np.array_equal(HALF, (_BYTES >= HALF_FROM) & (_BYTES <= 100))
        and np.array_equal(KNOWN[:101], _KNOWN[1:]) and not KNOWN[255]):
    raise AssertionError("the comparisons of LayerDecoder no longer give the tables' values")


def _info_key(info: Any) -> tuple:
    """The fields :func:`msg_adapters.check_grid_info` reads, with their types."""
    p, q = info.origin.position, info.origin.orientation
    values = (info.resolution, info.width, info.height, p.x, p.y, q.x, q.y, q.z, q.w)
    return tuple((type(v), v) for v in values)


class LayerDecoder:
    """Decodes OccupancyGrid layers of ``grid`` (see module docstring)."""

    def __init__(self, grid: BevGrid) -> None:
        self.grid = grid
        self._checked: set[tuple] = set()

    def cells(self, msg: Any) -> np.ndarray | None:
        """The ``(H, W)`` uint8 bytes of a layer that fits the grid, or ``None`` when
        :func:`~msg_adapters.occupancy_grid_to_layer` must decode it (it raises then, or not).
        """
        if not isinstance(msg, OccupancyGrid):
            return None
        data = msg.data
        if data.dtype != np.int8 or data.size != self.grid.width * self.grid.height:
            return None
        key = _info_key(msg.info)
        if key not in self._checked:
            try:
                check_grid_info(msg.info, self.grid)
            except Exception:  # noqa: BLE001 - occupancy_grid_to_layer says why
                return None
            self._checked.add(key)
        cells = data.view(np.uint8)
        if np.add(cells, 1, dtype=np.uint8).max() > 101:  # some cell outside -1..100 (-1 + 1 wraps to 0)
            return None
        return cells.reshape(self.grid.shape)  # (H*W,) -> (H, W)

    def into(self, msg: Any, probs: np.ndarray, known: np.ndarray) -> None:
        """Decode ``msg`` into ``probs`` ``(H, W)`` float32 and ``known`` ``(H, W)`` bool.

        Raises:
            what :func:`~msg_adapters.occupancy_grid_to_layer` raises for it.
        """
        cells = self.cells(msg)
        if cells is None:
            probs[...], known[...] = occupancy_grid_to_layer(msg, self.grid)
            return
        _lut(cells, probs)
        np.not_equal(cells, _UNKNOWN, out=known)  # KNOWN's values

    def half(self, msg: Any, out: np.ndarray | None = None) -> np.ndarray:
        """``probs >= 0.5`` of ``msg`` ``(H, W)``: bool, or into ``out`` (bool or float32 0/1).

        Raises:
            what :func:`~msg_adapters.occupancy_grid_to_layer` raises for it.
        """
        cells = self.cells(msg)
        if cells is None:
            half = occupancy_grid_to_layer(msg, self.grid)[0] >= 0.5
            if out is None:
                return half
            out[...] = half
            return out
        if out is not None and out.dtype == np.bool_:  # straight into it
            return np.less_equal(np.subtract(cells, HALF_FROM, dtype=np.uint8), 100 - HALF_FROM, out=out)
        half = np.subtract(cells, HALF_FROM, dtype=np.uint8) <= 100 - HALF_FROM  # HALF's values
        if out is None:
            return half
        out[...] = half
        return out

    def half_into(self, msg: Any, half: np.ndarray, known: np.ndarray) -> None:
        """Decode ``msg`` into ``half`` ``(H, W)`` bool (``probs >= 0.5``) and ``known``
        ``(H, W)`` bool: :meth:`into`'s layers as the scorers read them, with no float decoding.

        Raises:
            what :func:`~msg_adapters.occupancy_grid_to_layer` raises for it.
        """
        cells = self.cells(msg)
        if cells is None:
            probs, known[...] = occupancy_grid_to_layer(msg, self.grid)
            np.greater_equal(probs, 0.5, out=half)
            return
        np.less_equal(np.subtract(cells, HALF_FROM, dtype=np.uint8), 100 - HALF_FROM, out=half)  # HALF's values
        np.not_equal(cells, _UNKNOWN, out=known)  # KNOWN's values


def _lut(cells: np.ndarray, out: np.ndarray) -> None:
    """``out[...] = PROBS[cells]`` through cv2.LUT, written in place."""
    got = cv2.LUT(cells, _PROBS_LUT, dst=out)
    if got is not out and not np.shares_memory(got, out):  # OpenCV allocated anew: copy over
        out[...] = got
