"""The GT, visibility and truth layers of a frame from their OccupancyGrids, each cell through one
lookup table instead of :func:`msg_adapters.occupancy_grid_to_layer`'s arithmetic.

:func:`~msg_adapters.occupancy_grid_to_layer` checks the message's info against the grid, refuses
cells outside -1..100 and converts the int8 cells to ``(probs float32, known bool)``. A frame
holds 16 such layers; :class:`LayerDecoder` gives the same values by indexing tables of the 256
possible bytes (built by the same arithmetic; OpenCV's ``LUT``), checks an info it has checked before by comparing
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
#: per byte: probability >= 0.5 (the visibility and truth layers' test), as bool and float32
HALF = PROBS >= 0.5
HALF_F32 = HALF.astype(np.float32)
# the tables as cv2.LUT takes them: (1, 256), bool as uint8 0/1
_LUT = {"probs": PROBS[None], "known": KNOWN.view(np.uint8)[None], "half": HALF.view(np.uint8)[None],
        "half_f32": HALF_F32[None]}
_UNKNOWN = np.uint8(255)  # -1 read as uint8


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
        if np.count_nonzero(cells > 100) != np.count_nonzero(cells == _UNKNOWN):  # not all in -1..100
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
        _lut(cells, "probs", probs)
        _lut(cells, "known", known.view(np.uint8))

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
        if out is None:
            return cv2.LUT(cells, _LUT["half"]).view(bool)
        _lut(cells, "half_f32" if out.dtype == np.float32 else "half", out if out.dtype == np.float32 else out.view(np.uint8))
        return out


def _lut(cells: np.ndarray, table: str, out: np.ndarray) -> None:
    """``out[...] = table[cells]`` through cv2.LUT, written in place."""
    got = cv2.LUT(cells, _LUT[table], dst=out)
    if got is not out and not np.shares_memory(got, out):  # OpenCV allocated anew: copy over
        out[...] = got
