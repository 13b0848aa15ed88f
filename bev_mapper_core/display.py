"""Readable pictures of BEV layers: class colours, unknown hatch, ego footprint, legend, scale.

:class:`BevPainter` draws class layers on a :class:`~bev_mapper_core.geometry.grid.BevGrid` in display
orientation (:meth:`BevGrid.to_display`: forward up, left on the left), ``scale`` display pixels
per cell:

* every cell gets the colour of the last class present in it (layer order, so objects lie on
  top of the road), :data:`~.classes.EMPTY_COLOR` when known and empty, and the dark diagonal
  hatch of :data:`~.classes.UNKNOWN_COLORS` when unknown (the mapper's ``known`` False, or cells
  the caller marks ``hidden``, e.g. where the ground truth is not visible);
* the ego footprint is drawn at the origin: a white box of :data:`EGO_LENGTH_M` x
  :data:`EGO_WIDTH_M` with a black outline and a black triangle at its front, its centre
  :data:`EGO_CENTER_X_M` ahead of ``base_link`` (the rear axle);
* :meth:`BevPainter.legend` is a side strip: a swatch and the name of each class (optionally the
  frame's IoU of each), the empty and unknown swatches, the ego, an axes glyph (x forward up,
  y left) and a metres scale bar at the picture's scale.

Everything that does not depend on the frame (colour table, hatch, ego overlay, legend) is built
once per painter; :func:`painter` caches painters per grid, classes and scale, so the per-frame
cost is one class-code pass, a table lookup and a masked copy.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from functools import lru_cache

import cv2
import numpy as np

from .geometry.grid import BevGrid
from .labels.classes import EMPTY_COLOR, HATCH_PERIOD, HATCH_WIDTH, UNKNOWN_COLORS, BevClass

#: Ego vehicle footprint drawn in pictures (and used by the synthetic world): a mid-size car,
#: 4.6 m long and 1.9 m wide, its centre 1.3 m ahead of ``base_link`` (the rear axle), so it
#: spans x in [-1.0, 3.6] m and y in [-0.95, 0.95] m.
EGO_LENGTH_M, EGO_WIDTH_M, EGO_CENTER_X_M = 4.6, 1.9, 1.3

#: Background of the legend strip and of picture bands, and their text colour.
STRIP_BG = (24, 24, 24)
STRIP_FG = (235, 235, 235)
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_FONT_SCALE = 0.4
_ROW = 16  # legend row height (px)
_PAD = 6  # legend margins (px)
_SWATCH = 11  # legend swatch edge (px)
_SCALE_BARS_M = (1, 2, 5, 10, 20, 50, 100)


def hatch_mask(height: int, width: int) -> np.ndarray:
    """``(height, width)`` bool: the stripes of the unknown hatch (diagonal, top-right to
    bottom-left), :data:`~.classes.HATCH_WIDTH` pixels every :data:`~.classes.HATCH_PERIOD`.
    """
    r = np.arange(height)[:, None]
    c = np.arange(width)[None, :]
    return (r + c) % HATCH_PERIOD < HATCH_WIDTH


def class_codes(layers: np.ndarray, threshold: float = 0.5) -> np.ndarray:
    """``(H, W)`` uint8 code of the topmost class present per cell: 0 none, ``c + 1`` class c."""
    layers = np.asarray(layers)
    if layers.shape[0] == 0:
        return np.zeros(layers.shape[1:], np.uint8)
    weights = np.arange(1, layers.shape[0] + 1, dtype=np.uint8)[:, None, None]
    return ((layers >= threshold) * weights).max(axis=0)  # the last class present wins


def color_table(classes: Sequence[BevClass]) -> np.ndarray:
    """``(C + 3, 3)`` uint8 colours of the codes: empty, the C classes, unknown base, stripe."""
    return np.array([EMPTY_COLOR, *(c.color for c in classes), *UNKNOWN_COLORS], np.uint8)


def text_size(text: str) -> tuple[int, int]:
    """Width and height in pixels of ``text`` in the legend font."""
    (w, h), _ = cv2.getTextSize(text, _FONT, _FONT_SCALE, 1)
    return w, h


def put_text(img: np.ndarray, text: str, x: int, y: int, color=STRIP_FG) -> None:
    """Draw ``text`` with its baseline at ``(x, y)`` in the legend font."""
    cv2.putText(img, text, (int(x), int(y)), _FONT, _FONT_SCALE, color, 1, cv2.LINE_AA)


def _arrow(img, p0, p1, color) -> None:
    cv2.arrowedLine(img, p0, p1, color, 1, cv2.LINE_AA, tipLength=0.3)


class BevPainter:
    """Draws class layers of ``grid`` as display pictures with ``scale`` pixels per cell.

    Args:
        grid: the grid of the layers.
        classes: the classes of the layers, in layer order.
        scale: display pixels per cell (nearest-neighbour upscaling).
        threshold: a class is drawn where its layer is ``>= threshold``.
    """

    def __init__(self, grid: BevGrid, classes: Sequence[BevClass], scale: int = 1,
                 threshold: float = 0.5) -> None:
        self.grid = grid
        self.classes = tuple(classes)
        self.scale = int(scale)
        self.threshold = float(threshold)
        if self.scale < 1:
            raise ValueError(f"scale must be >= 1, got {scale}")
        self.lut = color_table(self.classes)
        # the same colours as a 256-entry 3-channel table for cv2.LUT (about twice np.take's speed)
        self._lut3 = np.zeros((256, 1, 3), np.uint8)
        self._lut3[:len(self.lut), 0] = self.lut
        self.unknown_code = len(self.classes) + 1
        self.height, self.width = grid.width * self.scale, grid.height * self.scale  # display
        stripes = hatch_mask(self.height, self.width)
        self._unknown = (self.unknown_code + stripes).astype(np.uint8)  # display orientation
        # the same codes in grid orientation (undoing to_display), to fill unknown cells before
        # re-orienting when no upscaling follows
        self._unknown_grid = np.ascontiguousarray(np.swapaxes(self._unknown[::-1, ::-1], 0, 1))
        self.ego_mask, self.ego_rgb = self._ego_overlay()
        self._ego_idx = np.flatnonzero(self.ego_mask)
        self._ego_vals = self.ego_rgb.reshape(-1, 3)[self._ego_idx]
        self._templates: dict[tuple[int, str], np.ndarray] = {}

    # ------------------------------------------------------------------ geometry
    @property
    def px_per_m(self) -> float:
        """Display pixels per metre."""
        return self.scale / self.grid.resolution

    def to_px(self, x: float, y: float) -> tuple[float, float]:
        """Display pixel ``(col, row)`` (sub-pixel) of the ego-frame point ``(x, y)`` metres."""
        g = self.grid
        return (g.y_max - y) * self.px_per_m, (g.x_max - x) * self.px_per_m

    def ego_box_px(self) -> tuple[int, int, int, int]:
        """Pixel box ``(col0, row0, col1, row1)`` (inclusive) of the ego footprint."""
        x0, x1 = EGO_CENTER_X_M - EGO_LENGTH_M / 2, EGO_CENTER_X_M + EGO_LENGTH_M / 2
        c0, r0 = self.to_px(x1, EGO_WIDTH_M / 2)  # front left = top left
        c1, r1 = self.to_px(x0, -EGO_WIDTH_M / 2)
        return round(c0), round(r0), round(c1) - 1, round(r1) - 1

    def _ego_overlay(self) -> tuple[np.ndarray, np.ndarray]:
        rgb = np.zeros((self.height, self.width, 3), np.uint8)
        mask = np.zeros((self.height, self.width), np.uint8)
        c0, r0, c1, r1 = self.ego_box_px()
        for img, fill, line in ((rgb, (255, 255, 255), (0, 0, 0)), (mask, 1, 1)):
            cv2.rectangle(img, (c0, r0), (c1, r1), fill, -1)
            cv2.rectangle(img, (c0, r0), (c1, r1), line, max(1, self.scale // 2))
            w, h = c1 - c0, r1 - r0  # forward triangle in the front third
            tri = np.array([[c0 + w // 2, r0 + max(2, h // 12)], [c0 + w // 5, r0 + h // 3],
                            [c1 - w // 5, r0 + h // 3]], np.int32)
            cv2.fillPoly(img, [tri], line)
        return mask.astype(bool), rgb

    # ------------------------------------------------------------------ drawing
    def codes(self, layers: np.ndarray, known=None, hidden=None) -> np.ndarray:
        """Display-oriented ``(height, width)`` uint8 codes (see :func:`color_table`)."""
        codes = class_codes(layers, self.threshold)
        seen = None if known is None else np.asarray(known, bool)
        if hidden is not None:
            seen = ~np.asarray(hidden, bool) if seen is None else seen & ~np.asarray(hidden, bool)
        if self.scale == 1:
            if seen is not None:
                codes = np.where(seen, codes, self._unknown_grid)
            return self.grid.to_display(codes)
        if seen is not None:
            codes = np.where(seen, codes, np.uint8(self.unknown_code))
        codes = self.grid.to_display(codes)
        codes = np.repeat(np.repeat(codes, self.scale, axis=0), self.scale, axis=1)
        return np.where(codes == self.unknown_code, self._unknown, codes)

    def paint(self, layers: np.ndarray, known=None, hidden=None, *, ego: bool = True) -> np.ndarray:
        """RGB ``(height, width, 3)`` uint8 map of ``layers`` ``(C, H, W)``.

        Args:
            layers: class probabilities or booleans, layer order of ``classes``.
            known: ``(H, W)`` bool, False = unknown (hatched); None = all known.
            hidden: ``(H, W)`` bool, cells to hatch as unknown as well (None = none).
            ego: draw the ego footprint.
        """
        codes = self.codes(layers, known, hidden)  # (height, width) uint8, below len(self.lut)
        rgb = cv2.LUT(cv2.merge([codes, codes, codes]), self._lut3)  # (height, width, 3): self.lut[codes]
        if ego:
            rgb.reshape(-1, 3)[self._ego_idx] = self._ego_vals
        return rgb

    def unknown(self, *, ego: bool = True) -> np.ndarray:
        """A map with every cell unknown (e.g. a frame without ground truth)."""
        layers = np.zeros((0,) + self.grid.shape, np.float32)
        return self.paint(layers, np.zeros(self.grid.shape, bool), ego=ego)

    # ------------------------------------------------------------------ legend
    def scale_bar_m(self, max_px: int) -> float:
        """The longest of 1, 2, 5, 10, 20, 50, 100 m whose bar fits in ``max_px`` pixels."""
        fits = [m for m in _SCALE_BARS_M if m * self.px_per_m <= max_px]
        return float(fits[-1]) if fits else float(_SCALE_BARS_M[0])

    def legend_width(self, ious: bool = False, unknown_label: str = "unknown") -> int:
        """Width (px) of :meth:`legend`'s strip."""
        names = [c.name for c in self.classes] + ["known, empty", unknown_label,
                                                   self._ego_label()]
        text_w = max(text_size(n)[0] for n in names)
        iou_w = text_size("100%")[0] + _PAD if ious else 0
        return max(2 * _PAD + _SWATCH + 5 + text_w + iou_w, 110)

    @staticmethod
    def _ego_label() -> str:
        return f"ego {EGO_LENGTH_M:g} x {EGO_WIDTH_M:g} m"

    def legend(self, height: int, ious: Mapping[str, float | None] | None = None,
               unknown_label: str = "unknown", header: str = "") -> np.ndarray:
        """The legend strip ``(max(height, needed), width, 3)`` uint8 (see the module docstring).

        Args:
            height: wanted height (px); the strip is taller when its content needs it.
            ious: optional class name -> IoU in [0, 1] written right of each class name
                (None / NaN, i.e. undefined, as ``-``; classes not in it, i.e. not scored, blank).
            unknown_label: the name of the hatch swatch.
            header: optional first line (e.g. ``"frame IoU"``).
        """
        width = self.legend_width(ious is not None, unknown_label)
        needed = self.legend_height(header)
        img = np.empty((max(height, needed), width, 3), np.uint8)
        img[:] = STRIP_BG
        y = _PAD
        if header:
            put_text(img, header, _PAD, y + 11)
            y += _ROW
        sx = _PAD
        tx = _PAD + _SWATCH + 5
        for ci, c in enumerate(self.classes):
            self._swatch(img, sx, y + 2, self.lut[ci + 1])
            put_text(img, c.name, tx, y + 11)
            if ious is not None and c.name in ious:  # blank: not scored
                v = ious[c.name]
                text = "-" if v is None or not math.isfinite(v) else f"{100 * v:.0f}%"
                put_text(img, text, width - _PAD - text_size(text)[0], y + 11)
            y += _ROW
        self._swatch(img, sx, y + 2, EMPTY_COLOR)
        put_text(img, "known, empty", tx, y + 11)
        y += _ROW
        hatch = self.lut[self.unknown_code + hatch_mask(_SWATCH, _SWATCH)]
        self._swatch(img, sx, y + 2, None, hatch)
        put_text(img, unknown_label, tx, y + 11)
        y += _ROW
        self._ego_icon(img, sx, y + 1)
        put_text(img, self._ego_label(), tx, y + 11)
        y += _ROW + 4
        # axes glyph: x forward (up), y left
        ox, oy = _PAD + 40, y + 32
        _arrow(img, (ox, oy), (ox, oy - 30), STRIP_FG)
        _arrow(img, (ox, oy), (ox - 30, oy), STRIP_FG)
        put_text(img, "x fwd", ox + 6, oy - 20)
        put_text(img, "y left", _PAD, oy + 16)
        y = oy + 26
        # scale bar
        bar_m = self.scale_bar_m(width - 2 * _PAD)
        length = int(round(bar_m * self.px_per_m))  # pixels [_PAD, _PAD + length)
        img[y + 5:y + 7, _PAD:_PAD + length] = STRIP_FG
        for x in (_PAD, _PAD + length - 1):
            img[y + 1:y + 11, x] = STRIP_FG
        put_text(img, f"{bar_m:g} m", _PAD, y + 24)
        return img

    def legend_height(self, header: str = "") -> int:
        """Height (px) the legend's content needs."""
        rows = len(self.classes) + 3 + (1 if header else 0)
        return _PAD + rows * _ROW + 4 + 58 + 30 + _PAD

    @staticmethod
    def _swatch(img, x, y, color, pattern=None) -> None:
        if pattern is not None:
            img[y:y + _SWATCH, x:x + _SWATCH] = pattern
        else:
            img[y:y + _SWATCH, x:x + _SWATCH] = color
        cv2.rectangle(img, (x - 1, y - 1), (x + _SWATCH, y + _SWATCH), (150, 150, 150), 1)

    @staticmethod
    def _ego_icon(img, x, y) -> None:
        w, h = 7, 13
        x0 = x + (_SWATCH - w) // 2
        cv2.rectangle(img, (x0, y), (x0 + w, y + h), (255, 255, 255), -1)
        cv2.rectangle(img, (x0, y), (x0 + w, y + h), (0, 0, 0), 1)
        tri = np.array([[x0 + w // 2, y + 2], [x0 + 2, y + 5], [x0 + w - 2, y + 5]], np.int32)
        cv2.fillPoly(img, [tri], (0, 0, 0))

    # ------------------------------------------------------------------ picture
    def picture(self, layers: np.ndarray, known=None, unknown_label: str = "unknown") -> np.ndarray:
        """Map with the legend strip on its right, C-contiguous RGB uint8 (``bev/image``).

        The legend, the background and the ego overlay are built once (per ``unknown_label``);
        a frame costs :meth:`paint` and one copy.
        """
        key = (0, unknown_label)
        template = self._templates.get(key)
        if template is None:
            legend = self.legend(self.height, unknown_label=unknown_label)
            template = np.empty((legend.shape[0], self.width + legend.shape[1], 3), np.uint8)
            template[:] = STRIP_BG
            template[:, self.width:] = legend
            self._templates[key] = template
        out = template.copy()
        out[:self.height, :self.width] = self.paint(layers, known)
        return out


@lru_cache(maxsize=16)
def painter(grid: BevGrid, classes: tuple[BevClass, ...], scale: int = 1) -> BevPainter:
    """The cached :class:`BevPainter` of ``grid``, ``classes`` and ``scale``."""
    return BevPainter(grid, classes, scale)
