"""Scoring scopes, range bands and :class:`MetricAccumulator` (visible-cell IoU, Chamfer,
precision over a drive): the one scorer of replay, ``bev-train eval`` and validation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ..errors import ConfigError, InputError
from ..geometry.grid import BevGrid
from ..labels.classes import resolve_classes
from ._checks import _check_bool, _check_mask, _nan_to_none, _safe_div
from ._packed import CellCounter, pack
from ._state import Mergeable, _from_json_number, _json_number
from .functional import DEFAULT_CLIP_M, _packed_chamfer_terms, mean_iou

# ----------------------------------------------------------------------------- scopes
#: Scoring scopes: ``visible`` scores every class on the cells some camera sees (GT not -1);
#: ``ground`` scores flat classes (road, markings, sidewalk) only where the cell's *ground* point
#: is seen too, object classes keep the visible scope (an object hides its own ground).
SCOPES = ("visible", "ground")
#: Width of the default range bands, metres.
RANGE_BAND_M = 10.0


def scope_masks(class_names: Sequence[str], visible, ground=None, scope: str = "visible") -> np.ndarray:
    """Per-class scoring masks ``(C, H, W)`` bool for :meth:`MetricAccumulator.update`.

    Args:
        class_names: BEV class names in layer order (flatness from :mod:`~.classes`).
        visible: ``(H, W)`` bool, cells whose ground truth is known (seen by a camera).
        ground: ``(H, W)`` bool, cells whose ground point is seen, or None (then ``scope``
            ``ground`` falls back to ``visible``).
        scope: one of :data:`SCOPES`.

    Raises:
        ConfigError: unknown scope or class name.
    """
    if scope not in SCOPES:
        raise ConfigError(f"scope must be one of {list(SCOPES)}, got {scope!r}")
    visible = _check_bool("visible", visible, 2)
    classes = resolve_classes(tuple(class_names))
    out = np.repeat(visible[None], len(classes), axis=0)  # (H, W) -> (C, H, W)
    if scope == "ground" and ground is not None:
        ground = _check_mask("ground", ground, visible.shape)
        for c, cls in enumerate(classes):
            if cls.flat:
                out[c] &= ground
    return out


def default_range_bands(grid: BevGrid) -> tuple[tuple[float, float], ...]:
    """Consecutive :data:`RANGE_BAND_M` bands from 0 m up to the farthest cell centre of ``grid``."""
    top = int(math.floor(float(grid.ranges.max()) / RANGE_BAND_M)) + 1
    return tuple((RANGE_BAND_M * i, RANGE_BAND_M * (i + 1)) for i in range(top))


# ----------------------------------------------------------------------------- accumulator
def _band_label(lo: float, hi: float) -> str:
    return f"{lo:g}-{hi:g}"


class MetricAccumulator(Mergeable):
    """Accumulates BEV segmentation metrics frame by frame over a whole drive.

    Args:
        grid: the :class:`BevGrid` the layers live on (resolution and per-cell ranges).
        class_names: one name per layer, in layer order (e.g. ``BEV_CLASS_NAMES``).
        range_bands: ``((lo, hi), ...)`` in metres; a cell belongs to a band when
            ``lo <= grid.ranges < hi`` (half-open). ``hi`` may be ``math.inf``. Default (None):
            consecutive 10 m bands ``(0, 10), (10, 20), ...`` up to the farthest cell of ``grid``
            (:func:`default_range_bands`). Every scorer of the package (``bev-bag replay``,
            ``bev-train eval``, validation during training) uses this default, so their
            by-range tables line up.
            Bands may overlap; cells outside every band still count in the overall metrics.
        threshold: a cell is predicted positive when ``probs >= threshold``.
        clip: Chamfer clipping distance in metres (see :func:`chamfer`).
        use_visibility: if True (default), score only inside the ``visibility`` mask passed to
            :meth:`update` (when one is passed); if False, the mask is ignored.
        chamfer_reduction: how the Chamfer distance of a class is combined over frames.

            * ``"frame"`` (default): per-frame ``cd_p`` / ``cd_l`` / ``cd`` averaged over the
              frames in which the class is present in the prediction or the ground truth (frames
              where both are empty do not contribute).
            * ``"pixel"``: the clipped point-to-set distances of all frames are pooled and
              averaged per side, as in HDMapNet's reference evaluation code (it sums distances
              and point counts over the dataset). A frame with an empty ground truth then adds
              ``clip`` per predicted cell to the ``cd_p`` side only, and a frame with an empty
              prediction adds ``clip`` per ground-truth cell to the ``cd_l`` side only.
              (HDMapNet's code does not clip distances when both sets are non-empty; here they
              are always clipped.)

    Counts (intersection, union, TP, FP) are summed over frames and divided once in
    :meth:`result`, i.e. dataset-level IoU and precision. Accumulators of several drives merge
    exactly (:meth:`merge`, :meth:`state` / :meth:`from_state`, see :mod:`._state`): the merged
    result is that of all their frames in one accumulator.
    """

    _COUNTS = ("frames", "_inter", "_union", "_tp", "_fp", "_band_inter", "_band_union",
               "_cd_p_sum", "_cd_l_sum", "_cd_p_n", "_cd_l_n")

    def __init__(
        self,
        grid: BevGrid,
        class_names: Sequence[str],
        range_bands: Sequence[tuple[float, float]] | None = None,
        threshold: float = 0.5,
        clip: float = DEFAULT_CLIP_M,
        use_visibility: bool = True,
        chamfer_reduction: str = "frame",
    ) -> None:
        if not isinstance(grid, BevGrid):
            raise ConfigError(f"grid must be a BevGrid, got {type(grid).__name__}")
        names = tuple(str(n) for n in class_names)
        if not names:
            raise ConfigError("class_names must not be empty")
        if len(set(names)) != len(names):
            raise ConfigError(f"class_names must be unique, got {list(names)}")
        if "miou" in names:
            raise ConfigError("'miou' is reserved (it is the mean column of iou_by_range)")
        if not (0.0 <= float(threshold) <= 1.0):
            raise ConfigError(f"threshold must be in [0, 1], got {threshold}")
        if not (float(clip) > 0 and math.isfinite(float(clip))):
            raise ConfigError(f"clip must be a finite positive number of metres, got {clip}")
        if chamfer_reduction not in ("frame", "pixel"):
            raise ConfigError(f"chamfer_reduction must be 'frame' or 'pixel', got {chamfer_reduction!r}")

        ranges = grid.ranges  # (H, W) metres
        if range_bands is None:
            range_bands = default_range_bands(grid)
        bands = []
        for band in range_bands:
            try:
                lo, hi = (float(v) for v in band)
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"range band must be a (lo, hi) pair of numbers, got {band!r}") from exc
            if math.isnan(lo) or math.isnan(hi) or lo < 0 or not hi > lo or math.isinf(lo):
                raise ConfigError(f"range band must satisfy 0 <= lo < hi, got {band!r}")
            bands.append((lo, hi))
        labels = [_band_label(lo, hi) for lo, hi in bands]
        if len(set(labels)) != len(labels):
            raise ConfigError(f"range bands must be distinct, got {bands}")

        self.grid = grid
        self.class_names = names
        self.range_bands = tuple(bands)
        self.band_labels = tuple(labels)
        self.threshold = float(threshold)
        self.clip = float(clip)
        self.use_visibility = bool(use_visibility)
        self.chamfer_reduction = chamfer_reduction
        # (B, H*W) bool band membership: each frame's counts, in total and per band, come from
        # one histogram of the packed layers (._packed)
        band_masks = np.stack(
            [((ranges >= lo) & (ranges < hi)).ravel() for lo, hi in bands]
        ) if bands else np.zeros((0, ranges.size), bool)
        self._counter = CellCounter(len(names), band_masks)
        self.reset()

    # -------------------------------------------------------------------------- state
    def reset(self) -> None:
        """Forget all accumulated frames."""
        C, B = len(self.class_names), len(self.range_bands)
        self.frames = 0
        self._inter = np.zeros(C, np.int64)
        self._union = np.zeros(C, np.int64)
        self._tp = np.zeros(C, np.int64)
        self._fp = np.zeros(C, np.int64)
        self._band_inter = np.zeros((C, B), np.int64)
        self._band_union = np.zeros((C, B), np.int64)
        # Chamfer: "frame" -> sums of per-frame means and frame counts;
        # "pixel" -> sums of clipped distances and point counts (per side).
        self._cd_p_sum = np.zeros(C, np.float64)
        self._cd_l_sum = np.zeros(C, np.float64)
        self._cd_p_n = np.zeros(C, np.int64)
        self._cd_l_n = np.zeros(C, np.int64)

    def _config(self) -> dict:
        return {"grid": self.grid.to_dict(), "class_names": list(self.class_names),
                "range_bands": [[lo, _json_number(hi)] for lo, hi in self.range_bands],
                "threshold": self.threshold, "clip": self.clip,
                "use_visibility": self.use_visibility, "chamfer_reduction": self.chamfer_reduction}

    @classmethod
    def _from_config(cls, config: dict) -> "MetricAccumulator":
        try:
            return cls(BevGrid.from_dict(config["grid"]), config["class_names"],
                       range_bands=[(lo, _from_json_number(hi)) for lo, hi in config["range_bands"]],
                       threshold=config["threshold"], clip=config["clip"],
                       use_visibility=config["use_visibility"],
                       chamfer_reduction=config["chamfer_reduction"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"invalid MetricAccumulator state configuration: {exc!r}") from exc

    # ------------------------------------------------------------------------- update
    def _check_frame(self, probs, gt, visibility, known):
        C = len(self.class_names)
        shape = (C,) + self.grid.shape
        probs = np.asarray(probs)
        if not np.issubdtype(probs.dtype, np.floating):
            raise InputError(f"probs must be a float array of probabilities, got dtype {probs.dtype}")
        if probs.shape != shape:
            raise InputError(f"probs shape {probs.shape} does not match (classes, H, W) = {shape}")
        gt = _check_bool("gt", gt, 3)
        if gt.shape != shape:
            raise InputError(f"gt shape {gt.shape} does not match (classes, H, W) = {shape}")
        if visibility is not None and np.ndim(visibility) == 3:
            visibility = _check_bool("visibility", visibility, 3)
            if visibility.shape != shape:
                raise InputError(f"per-class visibility shape {visibility.shape} does not match "
                                 f"(classes, H, W) = {shape}")
        else:
            visibility = _check_mask("visibility", visibility, self.grid.shape)
        known = _check_mask("known", known, self.grid.shape)
        if not _finite_where(probs, known):
            raise InputError("probs contain NaN or infinite values in known cells")
        return probs, gt, visibility, known

    def update(self, probs, gt, visibility=None, known=None) -> np.ndarray:
        """Add one frame.

        Args:
            probs: ``(C, H, W)`` float class probabilities; positive where ``>= threshold``.
            gt: ``(C, H, W)`` bool ground truth.
            visibility: optional ``(H, W)`` bool, or ``(C, H, W)`` bool per class (see
                :func:`scope_masks`); with ``use_visibility`` only these cells are scored
                (prediction and ground truth outside it are ignored).
            known: optional ``(H, W)`` bool; cells where it is False count as predicted negative
                for every class (the mapper has no opinion there, so ground truth there is missed).

        Returns:
            ``(C,)`` float64 IoU of this frame alone (NaN where its union is empty), for logging.

        Raises:
            InputError: wrong dtypes or shapes, non-finite probabilities in known cells.
        """
        probs, gt, visibility, known = self._check_frame(probs, gt, visibility, known)
        C = len(self.class_names)
        # one bit per class (see ._packed): the counts read H * W bytes per 8 classes
        pred = pack(probs >= self.threshold)  # (G, H*W)
        truth = pack(gt)
        if known is not None:
            pred *= known.reshape(-1).view(np.uint8)  # unknown cells: no class
        mask = visibility if (self.use_visibility and visibility is not None) else None
        if mask is not None:
            if mask.ndim == 3:  # per class
                scope = pack(mask)
                pred &= scope
                truth &= scope
            else:
                pred *= mask.reshape(-1).view(np.uint8)
                truth *= mask.reshape(-1).view(np.uint8)
        n_inter, band_inter = self._counter.counts(pred & truth)
        n_union, band_union = self._counter.counts(pred | truth)
        n_pred = self._counter.totals(pred)
        self._inter += n_inter
        self._union += n_union
        self._tp += n_inter
        self._fp += n_pred - n_inter
        self._band_inter += band_inter
        self._band_union += band_union

        shape = self.grid.shape
        for c in range(C):
            d_p, d_g = _packed_chamfer_terms(pred, truth, c, shape, self.grid.resolution, self.clip)
            if d_p.size == 0 and d_g.size == 0:
                continue  # class absent from both: no contribution
            if self.chamfer_reduction == "pixel":
                self._cd_p_sum[c] += d_p.sum()
                self._cd_p_n[c] += d_p.size
                self._cd_l_sum[c] += d_g.sum()
                self._cd_l_n[c] += d_g.size
            else:
                self._cd_p_sum[c] += d_p.mean() if d_p.size else self.clip
                self._cd_l_sum[c] += d_g.mean() if d_g.size else self.clip
                self._cd_p_n[c] += 1
                self._cd_l_n[c] += 1

        self.frames += 1
        return _safe_div(n_inter, n_union)

    # ------------------------------------------------------------------------- result
    def class_iou(self) -> np.ndarray:
        """``(C,)`` dataset-level IoU so far (NaN where the union is still empty)."""
        return _safe_div(self._inter, self._union)

    def result(self) -> dict:
        """Metrics over all frames so far, as a plain JSON-serialisable dict.

        Layout::

            {"frames": n,
             "classes": {name: {"iou", "cd_p", "cd_l", "cd", "precision"}, ...},
             "miou": x, "map": x,
             "iou_by_range": {"0-10": {name: iou, ..., "miou": x}, ...}}

        IoU and precision are fractions in [0, 1], Chamfer distances are metres. Undefined
        values are ``None``: IoU of a class never present in prediction or ground truth,
        precision of a class never predicted, Chamfer of a class with no contributing frame,
        and the means when nothing is defined. ``miou`` / ``map`` / band ``miou`` average only
        the defined entries.
        """
        ious = self.class_iou()
        precision = _safe_div(self._tp, self._tp + self._fp)
        cd_p = _safe_div(self._cd_p_sum, self._cd_p_n)
        cd_l = _safe_div(self._cd_l_sum, self._cd_l_n)
        cd = 0.5 * (cd_p + cd_l)  # NaN if either side is undefined
        classes = {}
        for c, name in enumerate(self.class_names):
            classes[name] = {
                "iou": _nan_to_none(ious[c]),
                "cd_p": _nan_to_none(cd_p[c]),
                "cd_l": _nan_to_none(cd_l[c]),
                "cd": _nan_to_none(cd[c]),
                "precision": _nan_to_none(precision[c]),
            }
        band_iou = _safe_div(self._band_inter, self._band_union)  # (C, B)
        by_range = {}
        for b, label in enumerate(self.band_labels):
            row = {name: _nan_to_none(band_iou[c, b]) for c, name in enumerate(self.class_names)}
            row["miou"] = _nan_to_none(mean_iou(band_iou[:, b]))
            by_range[label] = row
        return {
            "frames": int(self.frames),
            "classes": classes,
            "miou": _nan_to_none(mean_iou(ious)),
            "map": _nan_to_none(mean_iou(precision)),
            "iou_by_range": by_range,
        }


def _finite_where(probs: np.ndarray, known: np.ndarray | None) -> bool:
    """True when ``probs`` ``(C, H, W)`` is finite in every cell ``known`` ``(H, W)`` marks (all
    cells when ``None``). The classes' sum per cell is finite when all of them are; only when it
    is not somewhere known (a NaN or infinity, or a sum that overflows) are the cells checked
    one by one.
    """
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow or inf - inf: checked below
        total = np.add.reduce(probs, axis=0)  # (H, W)
    finite = np.isfinite(total)
    if known is not None:
        finite |= ~known
    if finite.all():
        return True
    each = np.isfinite(probs).all(axis=0)  # (H, W)
    if known is not None:
        each |= ~known
    return bool(each.all())
