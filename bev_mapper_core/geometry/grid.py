"""The one BEV grid definition every part of bev_mapper uses.

Conventions (REP 103 ego frame ``base_link``: x forward, y left, z up):

* A layer is a 2-D array indexed ``layer[row, col]`` with shape ``(height, width)``.
* ``col`` runs along +x (forward), ``row`` runs along +y (left).
* Cell ``(0, 0)`` has its corner at ``(x_min, y_min)``; the centre of cell ``(row, col)`` is
  ``(x_min + (col + 0.5) * res, y_min + (row + 0.5) * res)``.

This is exactly the ``nav_msgs/OccupancyGrid`` layout: ``info.origin`` is the corner of cell
(0, 0), ``data`` is row-major, ``info.width`` counts cells along x and ``info.height`` along y.
Nothing else in the package re-derives these relations: build a :class:`BevGrid` once and pass
it around.
"""

from __future__ import annotations

import math
from dataclasses import astuple, dataclass, fields
from functools import cached_property

import numpy as np

from ..errors import GridError

#: Most cells a BEV grid read from untrusted input (a bag's GT, a weights file) may have:
#: 2048 x 2048, ~50 times the default 400 x 200 grid (a replay holds a few float32 layers of
#: this size per class); a larger claim is refused before anything of that size is allocated.
MAX_GRID_CELLS = 2048 * 2048

#: OccupancyGrid value for "unknown".
OCC_UNKNOWN = -1
#: Largest OccupancyGrid value: known cells hold 0..OCC_MAX, the probability in percent.
OCC_MAX = 100

#: Two grids are the same grid when each bound and the resolution agree within this many metres
#: (see :meth:`BevGrid.isclose`). 1 um is far below any cell size, and far above the float64
#: noise of grids that travelled through JSON, YAML or ``OccupancyGrid`` (float32 resolution,
#: undone by ``msg_adapters``).
GRID_TOL_M = 1e-6


@dataclass(frozen=True)
class BevGrid:
    """Axis-aligned metric grid in the ego frame.

    Args:
        x_min, x_max: longitudinal extent in metres (x forward).
        y_min, y_max: lateral extent in metres (y left).
        resolution: cell edge length in metres.

    The default is the Bi-Mapper / HDMapNet grid: 60 m x 30 m at 0.15 m, i.e. 400 columns
    (x) by 200 rows (y).
    """

    # The one place these defaults are written: node parameters and CLI flags read them here.
    x_min: float = -30.0
    x_max: float = 30.0
    y_min: float = -15.0
    y_max: float = 15.0
    resolution: float = 0.15

    def __post_init__(self) -> None:
        values = (self.x_min, self.x_max, self.y_min, self.y_max, self.resolution)
        if not all(math.isfinite(v) for v in values):
            raise GridError(f"grid values must be finite, got {values}")
        if self.resolution <= 0:
            raise GridError(f"grid resolution must be > 0 m, got {self.resolution}")
        if self.x_max <= self.x_min or self.y_max <= self.y_min:
            raise GridError(
                f"grid extent is empty: x [{self.x_min}, {self.x_max}], y [{self.y_min}, {self.y_max}]"
            )
        for name, span in (("x", self.x_max - self.x_min), ("y", self.y_max - self.y_min)):
            cells = span / self.resolution
            if abs(cells - round(cells)) > 1e-6 * max(1.0, cells):
                raise GridError(
                    f"grid {name} extent {span} m is not a whole number of {self.resolution} m cells"
                )

    # ------------------------------------------------------------- identity
    def isclose(self, other: "BevGrid", tol: float = GRID_TOL_M) -> bool:
        """True when ``other`` is the same grid: same cell counts, and every bound and the
        resolution within ``tol`` metres (default :data:`GRID_TOL_M`).

        This is the comparison to use between grids of different origin (weights metadata, a
        bag's GT layers, parameters). ``==`` stays the exact dataclass equality (consistent
        with ``hash``).
        """
        if not isinstance(other, BevGrid):
            return False
        return self.shape == other.shape and all(
            abs(a - b) <= tol for a, b in zip(astuple(self), astuple(other)))

    def to_dict(self) -> dict[str, float]:
        """``{"x_min", "x_max", "y_min", "y_max", "resolution"}`` in field order (for JSON/YAML)."""
        return {f.name: float(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_dict(cls, d) -> "BevGrid":
        """Inverse of :meth:`to_dict`.

        Raises:
            GridError: a key is missing or unknown, a value is not a number, or the grid is invalid.
        """
        names = [f.name for f in fields(cls)]
        try:
            missing, unknown = sorted(set(names) - set(d)), sorted(set(d) - set(names))
        except TypeError:
            raise GridError(f"a grid must be a mapping of {names}, got {d!r}") from None
        if missing or unknown:
            raise GridError(f"grid needs exactly the keys {names}; missing {missing}, unknown {unknown}")
        try:
            values = {n: float(d[n]) for n in names}
        except (TypeError, ValueError):
            raise GridError(f"grid values must be numbers, got {dict(d)}") from None
        return cls(**values)

    # ------------------------------------------------------------------ sizes
    @property
    def width(self) -> int:
        """Number of columns (cells along +x)."""
        return int(round((self.x_max - self.x_min) / self.resolution))

    @property
    def height(self) -> int:
        """Number of rows (cells along +y)."""
        return int(round((self.y_max - self.y_min) / self.resolution))

    @property
    def shape(self) -> tuple[int, int]:
        """Layer shape ``(height, width)`` = ``(rows along y, cols along x)``."""
        return (self.height, self.width)

    # ------------------------------------------------------- cell <-> metric
    def cell_to_metric(self, row, col):
        """Centre ``(x, y)`` in metres of cell(s) ``(row, col)``; accepts scalars or arrays."""
        row = np.asarray(row, dtype=np.float64)
        col = np.asarray(col, dtype=np.float64)
        x = self.x_min + (col + 0.5) * self.resolution
        y = self.y_min + (row + 0.5) * self.resolution
        return x, y

    def metric_to_cell(self, x, y):
        """Cell ``(row, col)`` (integer arrays) containing metric point(s) ``(x, y)``.

        Points outside the grid get indices outside ``[0, height) x [0, width)``; use
        :meth:`contains` to mask them.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        col = np.floor((x - self.x_min) / self.resolution).astype(np.int64)
        row = np.floor((y - self.y_min) / self.resolution).astype(np.int64)
        return row, col

    def contains(self, x, y):
        """Boolean mask: metric point(s) ``(x, y)`` lie inside the grid."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        return (x >= self.x_min) & (x < self.x_max) & (y >= self.y_min) & (y < self.y_max)

    @cached_property
    def centers(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates ``(xs, ys)``, each of shape ``(height, width)``, float64."""
        rows, cols = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        xs, ys = self.cell_to_metric(rows, cols)
        xs.setflags(write=False)
        ys.setflags(write=False)
        return xs, ys

    @cached_property
    def ranges(self) -> np.ndarray:
        """Euclidean distance (m) of each cell centre from the ego origin, shape ``(height, width)``."""
        xs, ys = self.centers
        r = np.hypot(xs, ys)
        r.setflags(write=False)
        return r

    def points(self, z: float = 0.0) -> np.ndarray:
        """Cell centres as ``(height * width, 3)`` ego-frame points at height ``z`` (row-major)."""
        xs, ys = self.centers
        # (H, W) x 2 -> (H*W, 3)
        return np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, float(z))], axis=1)

    # ------------------------------------------------------ OccupancyGrid map
    @property
    def origin_xy(self) -> tuple[float, float]:
        """``info.origin.position`` (x, y) of the OccupancyGrid: the corner of cell (0, 0)."""
        return (float(self.x_min), float(self.y_min))

    def to_occupancy(self, probs: np.ndarray, known: np.ndarray | None = None) -> np.ndarray:
        """Convert a probability layer to OccupancyGrid ``data`` (int8, row-major, flat).

        Args:
            probs: ``(height, width)`` floats in [0, 1] (values are clipped).
            known: optional boolean ``(height, width)``; cells where it is False become -1.

        Returns:
            ``(height * width,)`` int8 array with values 0..100 or -1.
        """
        probs = np.asarray(probs)
        if probs.shape != self.shape:
            raise GridError(f"layer shape {probs.shape} does not match grid shape {self.shape}")
        occ = np.rint(np.clip(probs, 0.0, 1.0) * 100.0).astype(np.int8)
        if known is not None:
            known = np.asarray(known, dtype=bool)
            if known.shape != self.shape:
                raise GridError(f"mask shape {known.shape} does not match grid shape {self.shape}")
            occ[~known] = OCC_UNKNOWN
        return occ.ravel()

    def from_occupancy(self, data, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of :meth:`to_occupancy`: ``(probs float32 (H, W), known bool (H, W))``.

        Args:
            data: ``height * width`` integers (any integer dtype), row-major.
            width, height: the cell counts the data claims.

        Raises:
            GridError: the size differs from the grid's, the data is not integers, or cells hold
                values outside ``OCC_UNKNOWN..OCC_MAX`` (-1..100); the error gives their count.
                Such values are refused rather than clipped: 127 is no probability, and a layer
                that holds it was not written as an OccupancyGrid.
        """
        if (int(width), int(height)) != (self.width, self.height):
            raise GridError(
                f"OccupancyGrid is {width}x{height} cells, grid expects {self.width}x{self.height}"
            )
        arr = np.asarray(data)
        if arr.dtype.kind not in "iu":
            raise GridError(f"OccupancyGrid data must be integers, got dtype {arr.dtype}")
        if arr.size != self.width * self.height:
            raise GridError(f"OccupancyGrid data has {arr.size} cells, grid expects {self.width}x{self.height}")
        arr = arr.reshape(self.shape)  # (H*W,) -> (H, W)
        bad = (arr < OCC_UNKNOWN) | (arr > OCC_MAX)
        n_bad = int(np.count_nonzero(bad))
        if n_bad:
            first = int(np.flatnonzero(bad)[0])
            raise GridError(
                f"{n_bad} OccupancyGrid cells hold values outside {OCC_UNKNOWN}..{OCC_MAX} "
                f"(first: {int(arr.flat[first])} at cell {first})"
            )
        known = arr >= 0
        probs = np.where(known, arr.astype(np.float32) / 100.0, 0.0).astype(np.float32)
        return probs, known

    # ---------------------------------------------------------------- display
    def to_display(self, layer: np.ndarray) -> np.ndarray:
        """Re-orient a layer (or ``(H, W, C)`` image) for viewing: forward up, left on the left.

        Rows of the result run from +x (top) to -x, columns from +y (left) to -y.
        """
        layer = np.asarray(layer)
        if layer.shape[:2] != self.shape:
            raise GridError(f"layer shape {layer.shape[:2]} does not match grid shape {self.shape}")
        # (H=y, W=x, ...) -> (x, y, ...) -> reversed in both
        return np.swapaxes(layer, 0, 1)[::-1, ::-1]

    def describe(self) -> str:
        """Human-readable one-liner, for logs."""
        return (
            f"{self.width}x{self.height} cells at {self.resolution} m, "
            f"x [{self.x_min}, {self.x_max}] m, y [{self.y_min}, {self.y_max}] m"
        )


#: Named grids (``bev-train --grid``, ``bev-train eval --grid``, ``bev-bag replay --grid``):
#:
#: * ``surround``: the default :class:`BevGrid` (60 m x 30 m around the car at 0.15 m), the
#:   Bi-Mapper / HDMapNet grid of every surround rig.
#: * ``ahead``: 32 m x 32 m ahead of ``base_link`` at 0.25 m (128 x 128 cells), the monocular
#:   grid of S2G2 on ``front1``. The paper predicts 64 x 64 cells ahead of one front camera;
#:   this keeps its field at twice its resolution, so that lane dividers and curbs (0.15-0.3 m
#:   wide) still fill cells.
GRID_PRESETS: dict[str, BevGrid] = {
    "surround": BevGrid(),
    "ahead": BevGrid(x_min=0.0, x_max=32.0, y_min=-16.0, y_max=16.0, resolution=0.25),
}


def grid_preset(name: str) -> BevGrid:
    """The named grid of :data:`GRID_PRESETS`.

    Raises:
        GridError: an unknown name.
    """
    try:
        return GRID_PRESETS[name]
    except KeyError:
        raise GridError(f"unknown grid {name!r}; named grids: {sorted(GRID_PRESETS)}") from None

