"""BEV layers <-> ``nav_msgs/OccupancyGrid``.

The cell layout is :class:`bev_mapper_core.geometry.grid.BevGrid`'s (identical to OccupancyGrid's):
``info.origin`` is the corner of cell (0, 0) at ``grid.origin_xy``, ``info.width`` counts cells
along x, ``info.height`` along y, data is row-major; values 0..100, -1 unknown.

``info.resolution`` is a float32 on the wire, so comparisons against a grid and the
reconstruction of a grid from a message go through float32 (0.15 stays 0.15).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bev_mapper_core.errors import GridError
from bev_mapper_core.geometry.grid import GRID_TOL_M, BevGrid

from ._fields import as_float, as_int, byte_buffer, field
from .errors import GridMessageError
from .factory import MessageFactory, make_header, make_point, make_quaternion


def _f32(value: float) -> float:
    """The float64 that prints like float32 ``value`` (undoes float32 storage of 0.15 etc.);
    beyond float32's range, inf (refused by the grid checks).
    """
    with np.errstate(over="ignore"):
        return float(str(np.float32(value)))


def occupancy_data(grid: BevGrid, probs: np.ndarray, known: np.ndarray | None = None) -> np.ndarray:
    """Flat int8 OccupancyGrid data of a probability layer (``grid.to_occupancy``)."""
    try:
        return grid.to_occupancy(probs, known)
    except GridError as exc:
        raise GridMessageError(str(exc)) from None


def make_occupancy_grid(
    factory: MessageFactory,
    grid: BevGrid,
    probs: np.ndarray,
    known: np.ndarray | None,
    stamp_ns: int,
    frame_id: str,
) -> Any:
    """Build a ``nav_msgs/OccupancyGrid`` of one layer ``(H, W)`` in [0, 1]; unknown -> -1."""
    data = occupancy_data(grid, probs, known)
    ox, oy = grid.origin_xy
    origin = factory.msg(
        "geometry_msgs/msg/Pose",
        position=make_point(factory, (ox, oy, 0.0)),
        orientation=make_quaternion(factory, (0.0, 0.0, 0.0, 1.0)),
    )
    header = make_header(factory, stamp_ns, frame_id)
    info = factory.msg(
        "nav_msgs/msg/MapMetaData",
        map_load_time=header.stamp,
        resolution=float(grid.resolution),
        width=int(grid.width),
        height=int(grid.height),
        origin=origin,
    )
    return factory.msg(
        "nav_msgs/msg/OccupancyGrid", header=header, info=info, data=factory.int8_seq(data)
    )


def _info_float(info: Any, path: str) -> float:
    return as_float(field(info, path, GridMessageError, "OccupancyGrid info"), f"info.{path}",
                    GridMessageError, "OccupancyGrid")


def _info_size(info: Any) -> tuple[int, int]:
    return tuple(as_int(field(info, k, GridMessageError, "OccupancyGrid info"), f"info.{k}",
                        GridMessageError, "OccupancyGrid") for k in ("width", "height"))


def _check_orientation(q: Any) -> None:
    xyzw = np.array([_info_float(q, k) for k in "xyzw"], dtype=np.float64)
    if not (np.allclose(xyzw[:3], 0.0, atol=1e-6) and abs(abs(xyzw[3]) - 1.0) < 1e-6):
        raise GridMessageError(
            f"OccupancyGrid origin is rotated (quaternion {xyzw.tolist()}); only axis-aligned "
            "grids are supported"
        )


def grid_from_info(info: Any) -> BevGrid:
    """Reconstruct the :class:`BevGrid` of an OccupancyGrid's ``info`` (``MapMetaData``)."""
    _check_orientation(field(info, "origin.orientation", GridMessageError, "OccupancyGrid info"))
    res = _f32(_info_float(info, "resolution"))
    w, h = _info_size(info)
    ox, oy = _info_float(info, "origin.position.x"), _info_float(info, "origin.position.y")
    if w <= 0 or h <= 0:
        raise GridMessageError(f"OccupancyGrid has empty size {w}x{h}")
    try:
        return BevGrid(
            x_min=ox, x_max=round(ox + w * res, 9), y_min=oy, y_max=round(oy + h * res, 9),
            resolution=res,
        )
    except GridError as exc:
        raise GridMessageError(f"OccupancyGrid info does not describe a valid grid: {exc}") from None


def check_grid_info(info: Any, grid: BevGrid) -> None:
    """Raise :class:`GridMessageError` unless ``info`` describes ``grid``: same cell counts,
    resolution and origin within the grid tolerance :data:`~bev_mapper_core.geometry.grid.GRID_TOL_M`
    (as :meth:`BevGrid.isclose`).
    """
    res = _f32(_info_float(info, "resolution"))
    if abs(res - grid.resolution) > GRID_TOL_M:
        raise GridMessageError(
            f"OccupancyGrid resolution {res} m differs from the grid's {grid.resolution} m"
        )
    w, h = _info_size(info)
    if (w, h) != (grid.width, grid.height):
        raise GridMessageError(
            f"OccupancyGrid is {w}x{h} cells, grid expects {grid.width}x{grid.height}"
        )
    ox, oy = _info_float(info, "origin.position.x"), _info_float(info, "origin.position.y")
    gx, gy = grid.origin_xy
    if abs(ox - gx) > GRID_TOL_M or abs(oy - gy) > GRID_TOL_M:
        raise GridMessageError(f"OccupancyGrid origin ({ox}, {oy}) differs from the grid's ({gx}, {gy})")
    _check_orientation(field(info, "origin.orientation", GridMessageError, "OccupancyGrid info"))


def occupancy_grid_to_layer(msg: Any, grid: BevGrid | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Decode an OccupancyGrid into ``(probs float32 (H, W), known bool (H, W))``.

    Args:
        msg: the OccupancyGrid (rclpy or rosbags).
        grid: expected grid; ``None`` reconstructs it from ``msg.info``.

    Values must be -1 (unknown) or 0..100: cells outside that range are refused, not clipped
    (see :meth:`BevGrid.from_occupancy`); the error says how many there are.

    Raises:
        GridMessageError: a field is missing or of the wrong type, info does not match ``grid``,
            the data length is wrong, or cells hold values outside -1..100 (with their count).
    """
    info = field(msg, "info", GridMessageError, "OccupancyGrid")
    if grid is None:
        grid = grid_from_info(info)
    else:
        check_grid_info(info, grid)
    arr = _cells(field(msg, "data", GridMessageError, "OccupancyGrid"))
    if arr.size != grid.width * grid.height:
        raise GridMessageError(
            f"OccupancyGrid data has {arr.size} cells, expected {grid.width}x{grid.height}"
        )
    try:
        return grid.from_occupancy(arr, grid.width, grid.height)
    except GridError as exc:
        raise GridMessageError(str(exc)) from None


def _cells(data: Any) -> np.ndarray:
    """The ``int8[]`` data of an OccupancyGrid as a flat integer array (no wrap-around casts).

    One-byte buffers (int8 or uint8 arrays, ``array.array('b')``, bytes) are read as int8, as
    on the wire; wider integer arrays and lists keep their values, so 200 stays 200 (and is
    refused) instead of wrapping to -56.
    """
    if isinstance(data, np.ndarray) and data.dtype.kind in "iu" and data.dtype.itemsize > 1:
        return data.reshape(-1)
    if isinstance(data, (list, tuple)):
        try:
            arr = np.asarray(data)
        except (TypeError, ValueError) as exc:
            raise GridMessageError(f"OccupancyGrid data is not a sequence of integers: {exc}") from None
        if arr.size and arr.dtype.kind not in "iu":
            raise GridMessageError(f"OccupancyGrid data must hold integers, got dtype {arr.dtype}")
        return arr.astype(np.int64, copy=False).reshape(-1)
    if isinstance(data, np.ndarray) and data.dtype.kind not in "iu":
        raise GridMessageError(f"OccupancyGrid data must hold integers, got dtype {data.dtype}")
    if hasattr(data, "typecode") and data.itemsize != 1:
        raise GridMessageError(f"OccupancyGrid data must be int8, got array of {data.typecode!r}")
    return byte_buffer(data, "data", GridMessageError, "OccupancyGrid").view(np.int8)
