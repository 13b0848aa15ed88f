"""Inverse perspective mapping (IPM): the classical, training-free baseline.

Each BEV cell centre is placed on the ground plane (z = 0 in ``base_link``) and projected into
every camera once per calibration; the resulting lookup tables warp each frame with
``cv2.remap`` (nearest for label images, linear for RGB). Cameras overlapping on a cell are
averaged; cells no camera sees are unknown. Objects that stand off the ground are smeared away
from the camera: the known flat-ground limitation of IPM. With ``MapperConfig.ipm_occlusion``
(the default) a camera gives no value to the cells it cannot see behind an object's near edge
(:mod:`~bev_mapper_core.methods.ipm.occlusion`), so the smear becomes unknown instead of object.
:class:`LineOfSight` holds those rays for a rig; the learned methods use it on label input too.
"""

from __future__ import annotations

import sys
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from bev_mapper_core.errors import ConfigError, InputError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.projection import RemapTable, ground_tables, remap_table
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.labels.classes import label_lut
from bev_mapper_core.mapper import BevPrediction, Mapper, MapperConfig

from .. import alternatives
from .columns import ColumnOcclusion, column_raster, rig_columns
from .occlusion import NEAR_EDGE_SLACK_CELLS, OcclusionModel, ray_raster

try:  # the per-cell counting in C (optional: setup.py builds it where a C compiler is)
    from . import _counts as _compiled
except ImportError:  # pragma: no cover - the numpy paths below give the same maps
    _compiled = None

#: per camera name, the calibrations whose tables :meth:`IpmMapper.set_rig` keeps
CAMERA_CACHE = 4

#: no hidden cells (the compiled counting's argument)
_NONE_HIDDEN = np.zeros(0, np.int64)

#: bits per field of IPM's packed per-cell counts (each class's, then the cameras'), the first
#: that fits: 8 (up to 255 cameras, 8 fields per uint64, unpacked as a byte view) or 4 (up to 15
#: cameras, 16 fields)
CODE_BITS = (8, 4)


def code_bits(n_fields: int, n_cameras: int) -> int | None:
    """Bits per field of the packed counts (:data:`CODE_BITS`); ``None``: none fits one uint64
    (the float path then sums class rows).
    """
    for bits in CODE_BITS:
        if n_fields * bits <= 64 and n_cameras < 2 ** bits:
            return bits
    return None


@dataclass(frozen=True)
class GatherTable:
    """A :class:`RemapTable` (nearest) as flat indices: per-frame IPM is then one gather.

    Attributes:
        cells: ``(n,)`` int64 flat indices of the target cells the camera sees (``valid``), in
            increasing order.
        pixels: ``(n,)`` int64 flat index into the camera image of the pixel each of those
            cells takes, exactly the pixel ``cv2.remap(..., INTER_NEAREST, BORDER_REPLICATE)``
            picks (found by remapping an image of pixel indices, so the rounding is cv2's own).
        image_shape: ``(h, w)`` of the camera image the indices are for.
    """

    cells: np.ndarray
    pixels: np.ndarray
    image_shape: tuple[int, int]

    @classmethod
    def from_remap(cls, table: RemapTable, image_shape: tuple[int, int]) -> "GatherTable":
        """The gather form of ``table`` for images of ``image_shape`` = ``(h, w)``."""
        h, w = image_shape
        if h * w >= 2 ** 24:
            raise ValueError(f"images of {w}x{h} have more pixels than float32 indexes exactly")
        index_image = np.arange(h * w, dtype=np.float32).reshape(h, w)
        picked = table.warp(index_image, cv2.INTER_NEAREST)  # (H, W) float32 pixel indices
        cells = np.flatnonzero(table.valid)
        return cls(cells, picked.ravel()[cells].astype(np.int64), (h, w))

    def gather(self, image: np.ndarray) -> np.ndarray:
        """``(n,)`` values of ``image`` (``image_shape``) at the seen cells."""
        return image.reshape(-1)[self.pixels]


class LineOfSight:
    """Which ground cells each camera of a rig sees, from its label image (IPM's rays).

    A camera sees the cells of its ground table (:func:`ground_tables`) that its occlusion
    model does not hide behind the near edge of an object in its labels
    (:class:`~bev_mapper_core.methods.ipm.occlusion.OcclusionModel`). Built once per calibration.

    Args:
        rig, grid: the calibration and the BEV grid.
        occlusion: the occlusion model (its priors); ``None`` = no occlusion reasoning (a camera
            sees its whole ground table, the classical IPM).
        tables: the rig's ground tables when already built (else built here).
        columns: search the near edges per image column
            (:mod:`~bev_mapper_core.methods.ipm.columns`, IPM's default) instead of along the
            polar raster's BEV rays (:func:`~bev_mapper_core.methods.ipm.occlusion.ray_raster`).
        gathers: the rig's gather tables when already built (column search only).
        rasters: per camera, its column raster (column search) or polar ray raster when already
            built (cameras missing from it are built here).
    """

    def __init__(self, rig: Rig, grid: BevGrid, occlusion: OcclusionModel | None,
                 tables: dict[str, RemapTable] | None = None, columns: bool = False,
                 gathers: dict[str, GatherTable] | None = None, rasters: dict | None = None) -> None:
        rasters = rasters or {}
        self.grid = grid
        self.tables = ground_tables(rig, grid) if tables is None else tables
        self.occlusion = occlusion
        self.columns = columns and occlusion is not None
        self.rays, self.column_rasters, self.gathers = {}, {}, {}
        if self.columns:
            self.gathers = gathers if gathers is not None else {
                c.name: GatherTable.from_remap(self.tables[c.name], c.model.image_size[::-1])
                for c in rig.cameras}
            self.column_rasters = {
                c.name: column_raster(c, grid, self.tables[c.name].valid, self.gathers[c.name].cells,
                                      self.gathers[c.name].pixels) if rasters.get(c.name) is None else rasters[c.name]
                for c in rig.cameras}
            self._rig_columns = rig_columns(self.column_rasters)  # all cameras' columns side by side
            self._column_occlusion = ColumnOcclusion(occlusion)
        elif occlusion is not None:
            self.rays = {c.name: ray_raster(c, grid, self.tables[c.name].valid)
                         if rasters.get(c.name) is None else rasters[c.name] for c in rig.cameras}

    def hidden(self, name: str, labels: np.ndarray, ids: np.ndarray) -> np.ndarray | None:
        """Column search: camera ``name``'s gathered cells hidden from it, as ``(k,)``
        increasing indices into its gather (``ids`` = its gather of ``labels``); ``None`` when
        none is.
        """
        return self.hidden_all({name: labels}, {name: ids})[name]

    def hidden_all(self, images: Mapping[str, np.ndarray],
                   ids: Mapping[str, np.ndarray]) -> dict[str, np.ndarray | None]:
        """Column search for all cameras of ``images`` (name -> label image) at once: camera
        name -> its gathered cells hidden from it (as :meth:`hidden`), ``ids`` its gathers.
        """
        slack = self.grid.resolution * NEAR_EDGE_SLACK_CELLS
        return self._column_occlusion.hidden(self._rig_columns, images, ids, slack)

    def camera_valid(self, name: str, warped: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
        """``(H, W)`` bool: the cells camera ``name`` sees, given its warped labels ``(H, W)``
        (the polar raster's input) or its label image ``labels`` (the column search's).
        """
        valid = self.tables[name].valid
        if self.occlusion is None:
            return valid
        if self.columns:
            if labels is None:
                raise ValueError("the column search needs the camera's label image")
            g = self.gathers[name]
            hidden = self.hidden(name, labels, g.gather(labels))
            if hidden is None:
                return valid
            out = valid.copy()
            out.reshape(-1)[g.cells[hidden]] = False
            return out
        slack = self.grid.resolution * NEAR_EDGE_SLACK_CELLS
        return valid & ~self.occlusion.occluded(self.rays[name], warped, valid, slack)

    def known(self, images: Mapping[str, np.ndarray]) -> np.ndarray:
        """``(H, W)`` bool: the cells some camera in ``images`` (name -> label image) sees."""
        known = np.zeros(self.grid.shape, bool)
        if self.columns:  # every camera's search in one pass
            ids = {name: self.gathers[name].gather(labels) for name, labels in images.items()}
            for name, hidden in self.hidden_all(images, ids).items():
                cells = self.gathers[name].cells  # (n,) the cells of its ground table
                known.reshape(-1)[cells if hidden is None else np.delete(cells, hidden)] = True
            return known
        for name, labels in images.items():
            warped = self.tables[name].warp(labels, cv2.INTER_NEAREST)
            known |= self.camera_valid(name, warped)
        return known

    def seen_objects(self, images: Mapping[str, np.ndarray], objects) -> np.ndarray:
        """``(H, W)`` bool: the cells some camera in ``images`` (name -> label image) sees as
        one of the labels ``objects``: its pixel of the cell's ground point shows such an object
        and the cell is not hidden from it, i.e. lies within the object's assumed depth beyond
        its near edge (this line of sight's footprint priors). With IPM's priors: the cells IPM
        maps as that object.
        """
        lut = np.zeros(256, bool)
        lut[[int(x) for x in objects]] = True
        seen = np.zeros(self.grid.shape, bool)
        for name, labels in images.items():
            warped = self.tables[name].warp(labels, cv2.INTER_NEAREST)
            shows = self.tables[name].valid & lut[warped]
            if shows.any():
                seen |= shows & self.camera_valid(name, warped, labels)
        return seen


class IpmMapper(Mapper):
    """IPM of semantic label images onto the ground plane.

    On label input each pixel's class becomes the class of the ground cell it projects to; on
    RGB input there is no class to transfer, so :meth:`map` refuses and :meth:`warp_rgb` gives
    the BEV colour mosaic instead. ``config.ipm_occlusion`` turns the occlusion reasoning on.
    """

    name = "ipm"
    per_set_rig = True  # set_rig rebuilds numpy tables only (time placement, issue #38)
    #: occlusion search per image column (:mod:`.columns`); ``False``: along the polar raster's
    #: BEV rays, the search before issue #28 (kept for comparison: experiments/ipm_occlusion_columns.py)
    occlusion_columns = True

    def __init__(self, rig: Rig, grid: BevGrid, config: MapperConfig) -> None:
        self.preflight(config, rig.name)
        self._occlusion = OcclusionModel()
        super().__init__(rig, grid, config)  # calls set_rig
        self._lut = label_lut(self.classes).astype(np.float32)  # (NUM_LABELS, C)
        ids = np.arange(256)
        known_ids = np.where(ids < len(self._lut), ids, 0)  # label ids unknown to us -> unlabeled
        self._lut_t = np.ascontiguousarray(self._lut[known_ids].T)  # (C, 256): one class row per gather
        self._known_ids = known_ids
        #: label id -> what it adds to a cell's counts (class indicators, then 1 camera, then
        #: zeros to a multiple of 8 bytes), for the compiled counting
        C = len(self.classes)
        self._table = np.zeros((256, 8 * (C // 8 + 1)), np.uint8)  # (256, S), S >= C + 1
        self._table[:, :C] = self._lut[known_ids]
        self._table[:, C] = 1
        self._pack(code_bits(len(self.classes) + 1, len(self.rig.cameras)))

    def _pack(self, bits: int | None) -> None:
        """Pack the per-cell counts ``bits`` per field: one field per class and, last, the count
        of cameras seeing the cell (``None``: the float path, which sums class rows).
        """
        #: label id (0..255) -> its class indicators and a count of 1, packed ``bits`` per field
        self._codes, self._bits = None, bits
        if bits is not None:
            C = len(self.classes)
            self._shifts = np.uint64(bits) * np.arange(C + 1, dtype=np.uint64)  # (C + 1,)
            fields = np.concatenate([self._lut[self._known_ids].astype(np.uint64),
                                     np.ones((256, 1), np.uint64)], axis=1)  # (256, C + 1)
            self._codes = (fields << self._shifts[None]).sum(1, dtype=np.uint64)

    @classmethod
    def preflight(cls, config: MapperConfig, rig_name: str, grid: BevGrid | None = None,
                  cameras: tuple[str, ...] | None = None) -> None:
        """IPM needs label images (a refusal names the methods that run on the input instead)."""
        if config.input_kind != "labels":
            raise ConfigError(
                f"IPM maps semantic label images only (input_kind 'labels'), not {config.input_kind!r}; "
                f"{alternatives('ipm', config.input_kind, rig_name, None if cameras is None else len(cameras))}"
            )

    def set_rig(self, rig: Rig) -> None:
        """Recompute the ground lookup tables (and their gather form) for a new calibration.

        Each camera's tables and rasters are kept for the last :data:`CAMERA_CACHE` cameras per
        camera name (keyed by the camera, mount and intrinsics): a rig placed per set at its
        cameras' times (:mod:`~bev_mapper_core.placement`) rebuilds only the cameras that moved.
        """
        super().set_rig(rig)
        occlusion = self._occlusion if self.config.ipm_occlusion else None
        parts = {c.name: self._camera_parts(c, occlusion) for c in rig.cameras}
        self.tables = {n: p[0] for n, p in parts.items()}
        self.gathers = {n: p[1] for n, p in parts.items()}
        self.sight = LineOfSight(rig, self.grid, occlusion, self.tables, columns=self.occlusion_columns,
                                 gathers=self.gathers, rasters={n: p[2] for n, p in parts.items()})
        for c in rig.cameras:  # the rasters LineOfSight built, for the next time
            raster = self.sight.column_rasters.get(c.name, self.sight.rays.get(c.name))
            entry = self._cache[self._cache_key(c)]
            self._cache[self._cache_key(c)] = (*entry[:2], raster, entry[3])

    def _cache_key(self, cam) -> tuple:
        return (cam.name, cam.ego_from_cam, id(cam.model), id(cam.ego_mask), self.occlusion_columns,
                self.config.ipm_occlusion)

    def _camera_parts(self, cam, occlusion) -> tuple:
        """``(RemapTable, GatherTable, raster or None, cam)`` of one camera, from the cache or built."""
        cache = self.__dict__.setdefault("_cache", {})  # insertion order = use order (LRU)
        key = self._cache_key(cam)
        hit = cache.pop(key, None)
        if hit is None:
            table = remap_table(cam, self._cell_points(), self.grid.shape)
            hit = (table, GatherTable.from_remap(table, cam.model.image_size[::-1]), None, cam)  # cam: ids stay unique
            same_name = [k for k in cache if k[0] == cam.name]
            for k in same_name[:max(0, len(same_name) - CAMERA_CACHE + 1)]:
                del cache[k]
        cache[key] = hit
        return hit

    def _cell_points(self) -> np.ndarray:
        """``(H*W, 3)`` the grid's cell centres on the ground, computed once."""
        pts = self.__dict__.get("_pts")
        if pts is None:
            pts = self._pts = self.grid.points(0.0)
        return pts

    def map(self, images: Mapping[str, np.ndarray], ego_pose=None, stamp_ns=None) -> BevPrediction:
        """Warp each camera's labels to the ground and average the class indicators.

        Per camera one gather of the seen cells' pixels (:class:`GatherTable`) and one lookup of
        their class indicators; the sums run over the cameras in order, so the result is the
        same float32 arithmetic as warping whole images and accumulating them.
        """
        images = self.check_images(images)
        H, W = self.grid.shape
        C = len(self.classes)
        occlusion = self.sight.occlusion is not None
        gathered = {name: self.gathers[name].gather(labels) for name, labels in images.items()}  # (n,) each
        columns = occlusion and self.sight.columns
        hidden_all = self.sight.hidden_all(images, gathered) if columns else {}
        if _compiled is not None and len(self.rig.cameras) < 256 and (columns or not occlusion):
            return self._map_compiled(gathered, hidden_all)
        codes = self._codes
        acc = np.zeros(H * W, np.uint64) if codes is not None else np.zeros((C, H * W), np.float32)
        count = None if codes is not None else np.zeros(H * W, np.float32)
        for name, labels in images.items():
            cells, ids = self.gathers[name].cells, gathered[name]  # ids: (n,) uint8 label ids of the seen cells
            hidden = hidden_all.get(name)  # per image column: indices into the gather
            if occlusion and not columns:  # the polar raster reads the warped image
                warped = np.zeros(H * W, labels.dtype)
                warped[cells] = ids
                keep = self.sight.camera_valid(name, warped.reshape(H, W)).reshape(-1)[cells]
                cells, ids = cells[keep], ids[keep]
            # cells are unique within a camera, so fancy-indexed += adds once per cell
            if codes is not None:
                add = codes[ids]  # every class's count and the camera count in one integer
                if hidden is not None:
                    add[hidden] = 0  # a hidden cell adds nothing, not even to the count
                acc[cells] += add
            else:
                if hidden is not None:
                    keep = np.ones(len(ids), bool)
                    keep[hidden] = False
                    cells, ids = cells[keep], ids[keep]
                acc[:, cells] += self._lut_t[:, ids]
                count[cells] += 1.0
        if codes is not None:  # unpack: field f is bits [f*bits, (f+1)*bits), the count last
            fields = self._unpack(acc)  # (C + 1, H*W)
            acc, count = fields[:C], fields[C]
        known = (count > 0).reshape(H, W)
        # a sum of class indicators (0 / 1) is exact in float32 either way
        probs = (acc / np.maximum(count, 1.0)[None]).reshape(C, H, W)  # (C, H*W) -> (C, H, W)
        return BevPrediction(self.class_names, probs, known)

    def _map_compiled(self, gathered: Mapping[str, np.ndarray],
                      hidden_all: Mapping[str, np.ndarray | None]) -> BevPrediction:
        """:meth:`map`'s counting by the compiled kernel (``_counts.c``): the same maps, bit for bit.

        ``gathered``: camera -> its seen cells' label ids; ``hidden_all``: camera -> the indices
        of those hidden from it (column search). One pass per camera adds each id's class
        indicators and a camera count into ``(H*W, S)`` uint8 counts (``S >= C + 1``, a
        multiple of 8; a field counts at most every camera: fewer than 256), then one division.
        """
        H, W = self.grid.shape
        C = len(self.classes)
        S = self._table.shape[1]
        counts = np.zeros((H * W, S), np.uint8)
        for name, ids in gathered.items():
            hidden = hidden_all.get(name)
            hidden = _NONE_HIDDEN if hidden is None else np.ascontiguousarray(hidden, np.int64)
            cells = np.ascontiguousarray(self.gathers[name].cells, np.int64)  # (no copy where intp is 64 bits)
            _compiled.add(counts, S, cells, ids, self._table, hidden)
        probs = np.empty((C, H, W), np.float32)
        known = np.empty((H, W), bool)
        _compiled.divide(counts, S, C, probs, known.view(np.uint8))
        return BevPrediction(self.class_names, probs, known)

    def _unpack(self, acc: np.ndarray) -> np.ndarray:
        """``(C + 1, H*W)`` float32 fields (class counts, camera count) of the packed ``(H*W,)``
        uint64 counters.
        """
        n = len(self._shifts)
        if self._bits == 8 and sys.byteorder == "little":  # field f is byte f
            fields = cv2.transpose(acc.view(np.uint8).reshape(-1, 8))  # (H*W, 8) -> (8, H*W); ~5x numpy's copy of .T
            return fields[:n].astype(np.float32)  # (n, H*W)
        return ((acc[None] >> self._shifts[:, None]) & np.uint64(2 ** self._bits - 1)).astype(np.float32)

    def warp_rgb(self, images: Mapping[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """BEV colour mosaic ``(H, W, 3)`` uint8 of RGB images (linear), and its known mask."""
        H, W = self.grid.shape
        acc = np.zeros((H, W, 3), np.float32)
        count = np.zeros((H, W), np.float32)
        for name, img in images.items():
            if name not in self.tables:
                raise InputError(f"image from unknown camera {name!r}")
            img = np.asarray(img)
            if img.ndim != 3 or img.shape[2] != 3:
                raise InputError(f"camera {name!r}: RGB image must be (H, W, 3), got {img.shape}")
            table = self.tables[name]
            warped = table.warp(img, cv2.INTER_LINEAR).astype(np.float32)
            acc[table.valid] += warped[table.valid]
            count += table.valid
        known = count > 0
        return (acc / np.maximum(count, 1.0)[..., None]).round().astype(np.uint8), known
