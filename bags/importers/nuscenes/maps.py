"""nuScenes' map expansion (``<DATAROOT>/maps/expansion/<location>.json``, v1.3 or later) read
without the devkit, and its layers rasterised on the package's grid.

Which map layer makes which class (:data:`MAP_SOURCES`):

* ``drivable``: the ``drivable_area`` polygons, filled (the devkit's ``get_map_mask``);
* ``ped_crossing``: the ``ped_crossing`` polygons, filled (the package's class is the crossing's
  area; HDMapNet's evaluation draws the crossing's two long edges as lines instead);
* ``sidewalk``: the ``walkway`` polygons, filled;
* ``lane_divider``: the ``road_divider`` and ``lane_divider`` lines, drawn 5 cells wide
  (HDMapNet's divider class and thickness);
* ``road_boundary``: the outline of the union of ``road_segment`` and ``lane`` polygons, 5 cells
  wide (HDMapNet's ``contours`` class).

Conventions (patch, yaw, rounding) are those of :mod:`bags.importers.raster`.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetLayoutError, DatasetVersionError
from ..raster import HDMAPNET_THICKNESS, MapPolygon, Patch, draw_boundaries, draw_lines, fill_polygons, overlapping

#: class -> (kind, map layers): how each map class is made (see the module docstring)
MAP_SOURCES: dict[str, tuple[str, tuple[str, ...]]] = {
    "drivable": ("fill", ("drivable_area",)),
    "lane_divider": ("lines", ("road_divider", "lane_divider")),
    "ped_crossing": ("fill", ("ped_crossing",)),
    "road_boundary": ("outline", ("road_segment", "lane")),
    "sidewalk": ("fill", ("walkway",)),
}
POLYGON_LAYERS = ("drivable_area", "ped_crossing", "walkway", "road_segment", "lane")
LINE_LAYERS = ("road_divider", "lane_divider")
MIN_VERSION = (1, 3)


def map_path(dataroot: Path, location: str) -> Path:
    """``<dataroot>/maps/expansion/<location>.json``."""
    return Path(dataroot) / "maps" / "expansion" / f"{location}.json"


def _bbox(points: np.ndarray) -> tuple[float, float, float, float]:
    return (float(points[:, 0].min()), float(points[:, 1].min()), float(points[:, 0].max()), float(points[:, 1].max()))


@dataclass(frozen=True)
class _Layer:
    items: tuple  # MapPolygon or (N, 2) line arrays
    boxes: np.ndarray  # (M, 4) x_min, y_min, x_max, y_max

    def near(self, patch: Patch) -> list:
        return [self.items[i] for i in overlapping(self.boxes, patch.bounds())]


class NuScenesMap:
    """One location's map expansion (see the module docstring).

    Raises:
        DatasetLayoutError: the file is not a map expansion (invalid JSON, layers or references).
        DatasetVersionError: a map expansion older than v1.3.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            with open(self.path, "rb") as f:
                obj = json.load(f)
        except json.JSONDecodeError as exc:
            raise DatasetLayoutError(f"{self.path}: not valid JSON ({exc})") from None
        if not isinstance(obj, dict):
            raise DatasetLayoutError(f"{self.path}: not a map expansion (a JSON object of layers)")
        self.version = str(obj.get("version", "1.0"))
        try:
            parsed = tuple(int(p) for p in self.version.split(".")[:2])
        except ValueError:
            parsed = (0,)
        if parsed < MIN_VERSION:
            raise DatasetVersionError(f"{self.path}: map expansion version {self.version}; the importer reads "
                                      "v1.3 or later (nuScenes-map-expansion-v1.3)")
        try:
            nodes = {n["token"]: (float(n["x"]), float(n["y"])) for n in obj["node"]}
            self.layers: dict[str, _Layer] = {}
            polygons = {p["token"]: p for p in obj["polygon"]}
            lines = {ln["token"]: ln for ln in obj["line"]}
            for name in POLYGON_LAYERS:
                items = []
                for rec in obj.get(name, []):
                    tokens = rec["polygon_tokens"] if name == "drivable_area" else [rec["polygon_token"]]
                    for t in tokens:
                        items.append(self._polygon(polygons[t], nodes))
                items = [p for p in items if len(p.exterior) >= 3]
                self.layers[name] = _Layer(tuple(items), np.array([_bbox(p.exterior) for p in items]).reshape(-1, 4))
            for name in LINE_LAYERS:
                items = [np.array([nodes[t] for t in lines[rec["line_token"]]["node_tokens"]]).reshape(-1, 2)
                         for rec in obj.get(name, [])]
                items = [ln for ln in items if len(ln) >= 2]
                self.layers[name] = _Layer(tuple(items), np.array([_bbox(ln) for ln in items]).reshape(-1, 4))
        except (KeyError, TypeError, ValueError) as exc:
            raise DatasetLayoutError(f"{self.path}: not a readable map expansion ({type(exc).__name__}: {exc})") from None

    @staticmethod
    def _polygon(rec: dict, nodes: dict) -> MapPolygon:
        ext = np.array([nodes[t] for t in rec["exterior_node_tokens"]], dtype=np.float64).reshape(-1, 2)
        holes = tuple(np.array([nodes[t] for t in h["node_tokens"]], dtype=np.float64).reshape(-1, 2)
                      for h in rec.get("holes", []) if h.get("node_tokens"))
        return MapPolygon(ext, holes)

    def layer_masks(self, patch: Patch, classes: tuple[str, ...] = tuple(MAP_SOURCES),
                    thickness: int = HDMAPNET_THICKNESS) -> dict[str, np.ndarray]:
        """``class -> (H, W) bool`` of the map classes on the patch (see the module docstring)."""
        out = {}
        for c in classes:
            kind, names = MAP_SOURCES[c]
            items = [it for n in names for it in self.layers[n].near(patch)]
            if kind == "fill":
                mask = fill_polygons(patch, items)
            elif kind == "lines":
                mask = draw_lines(patch, items, thickness)
            else:
                mask = draw_boundaries(patch, items, thickness)
            out[c] = mask.astype(bool)
        return out


__all__ = ["MAP_SOURCES", "NuScenesMap", "map_path"]
