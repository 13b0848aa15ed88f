"""Evaluation metrics of BEV semantic maps: IoU / mIoU, Chamfer distance, precision / "mAP".

Framework-free (numpy + OpenCV). All layers follow :mod:`bev_mapper_core.grid`: a class stack is
``(C, H, W)`` (classes, rows along +y, cols along +x), masks are ``(H, W)``.

What is computed, and how it relates to the papers:

* **IoU** per class, **dataset-level**: intersections and unions are summed over every frame of
  a drive and divided once at the end (as HDMapNet, Bi-Mapper, LSS ... report it), *not* the
  mean of per-frame IoUs. mIoU is the mean over classes whose union is non-empty.
* **IoU by range band**: the same counts restricted to cells whose centre range
  (:attr:`BevGrid.ranges`, metres from the ego origin) lies in ``[lo, hi)``.
* **Chamfer distance** (HDMapNet's semantic-map CD), in metres, on the sets of positive cells of
  prediction ``P`` and ground truth ``G`` of one class in one frame:
  ``CD_p = mean_{p in P} min(d(p, G), clip)`` (precision side, false positives far from any
  ground truth raise it), ``CD_L = mean_{g in G} min(d(g, P), clip)`` (recall side, missed
  ground truth raises it), ``CD = (CD_p + CD_L) / 2``. Distances are exact Euclidean distances
  between cell centres (``cv2.distanceTransform`` with ``DIST_L2`` / ``DIST_MASK_PRECISE``) times
  the grid resolution. See :func:`chamfer` for the empty-set and clipping rules and
  :class:`MetricAccumulator` for how frames are combined.
* **Precision** per class ``TP / (TP + FP)`` summed over the drive, and **"mAP"** = mean of the
  per-class precisions. This is the quantity S2G2 reports as mAP (mean over classes of the
  precision at the fixed decision threshold), *not* a ranked-retrieval average precision (no
  sweep over thresholds, no precision/recall curve).

The scores above only look at cells some camera sees. :class:`WholeGridAccumulator` scores what
a method publishes over the *whole* grid, beside them (it never changes them):

* **Occluded claims** per class: over the cells no camera sees, the share published as known
  with ``p >= threshold`` for the class, the share of those claims that are false against the
  full truth (what is in the cell, seen or not), and both as area in m^2 per frame.
* **Unknown recall**: the share of the cells no camera sees that are published as unknown;
  **known precision**: the share of the published-known cells that some camera sees.
* **Calibration**: the expected calibration error (ECE) of the published probabilities of each
  class on the visible, known cells: the cells are put in :data:`ECE_BINS` equal-width bins of
  ``p`` over [0, 1] (bin ``k`` holds ``k/B <= p < (k+1)/B``, the last one also ``p = 1``), and
  ``ECE = sum_k n_k / N * |frequency_k - confidence_k|`` where ``confidence_k`` is the mean ``p``
  of bin ``k`` and ``frequency_k`` the share of its cells where the class is present. Each class
  is a binary event, so the many cells a method rightly gives ``p = 0`` count too.

Undefined values (a class never present in prediction or ground truth, ...) are NaN in the
array-level functions and ``None`` in :meth:`MetricAccumulator.result`, so that the result is
strict JSON (``json.dumps(result, allow_nan=False)`` works).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from .classes import resolve_classes
from .errors import ConfigError, InputError
from .grid import BevGrid

__all__ = [
    "DEFAULT_CLIP_M",
    "ECE_BINS",
    "SCOPES",
    "MetricAccumulator",
    "WholeGridAccumulator",
    "chamfer",
    "default_range_bands",
    "expected_calibration_error",
    "format_table",
    "format_whole_grid_table",
    "iou",
    "mean_iou",
    "scope_masks",
]

#: Default Chamfer clipping distance in metres (HDMapNet's evaluation ``--CD_threshold`` = 5).
DEFAULT_CLIP_M = 5.0
#: Equal-width probability bins of the expected calibration error (see the module docstring).
ECE_BINS = 10


# ----------------------------------------------------------------------------- input checks
def _check_bool(name: str, arr, ndim: int) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.dtype != np.bool_:
        raise InputError(f"{name} must be a bool array, got dtype {arr.dtype}")
    if arr.ndim != ndim:
        raise InputError(f"{name} must have {ndim} dimensions, got shape {arr.shape}")
    return arr


def _check_mask(name: str, mask, shape: tuple[int, int]) -> np.ndarray | None:
    if mask is None:
        return None
    mask = _check_bool(name, mask, 2)
    if mask.shape != tuple(shape):
        raise InputError(f"{name} shape {mask.shape} does not match layer shape {tuple(shape)}")
    return mask


def _nan_to_none(x: float) -> float | None:
    x = float(x)
    return None if math.isnan(x) else x


def _safe_div(num, den) -> np.ndarray:
    """Elementwise ``num / den`` as float64 with NaN where ``den == 0``."""
    num = np.asarray(num, dtype=np.float64)
    den = np.asarray(den, dtype=np.float64)
    out = np.full(np.broadcast(num, den).shape, np.nan)
    np.divide(num, den, out=out, where=den != 0)
    return out


# ------------------------------------------------------------------------------------- IoU
def iou(pred, gt, mask=None) -> np.ndarray:
    """Per-class intersection over union of boolean layers.

    Args:
        pred: ``(C, H, W)`` bool predicted layers.
        gt: ``(C, H, W)`` bool ground-truth layers.
        mask: optional ``(H, W)`` bool; only cells where it is True are scored.

    Returns:
        ``(C,)`` float64 IoU per class. A class whose union is empty (absent from both prediction
        and ground truth inside the mask) gets **NaN**: it is undefined, not perfect; use
        :func:`mean_iou` to average while ignoring it.

    Raises:
        InputError: non-bool inputs, wrong number of dimensions or mismatched shapes.
    """
    pred = _check_bool("pred", pred, 3)
    gt = _check_bool("gt", gt, 3)
    if pred.shape != gt.shape:
        raise InputError(f"pred shape {pred.shape} does not match gt shape {gt.shape}")
    mask = _check_mask("mask", mask, pred.shape[1:])
    inter = pred & gt
    union = pred | gt
    if mask is not None:
        inter &= mask
        union &= mask
    C = pred.shape[0]
    return _safe_div(
        np.count_nonzero(inter.reshape(C, -1), axis=1), np.count_nonzero(union.reshape(C, -1), axis=1)
    )


def mean_iou(ious) -> float:
    """Mean of per-class IoUs ignoring NaN (undefined) entries; NaN if all are undefined."""
    ious = np.asarray(ious, dtype=np.float64)
    valid = ~np.isnan(ious)
    if not valid.any():
        return float("nan")
    return float(ious[valid].mean())


# --------------------------------------------------------------------------------- Chamfer
def _distance_to(cells: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance (in cells) of every cell centre to the nearest True cell.

    ``cells`` must contain at least one True cell.
    """
    # distanceTransform measures the distance to the nearest *zero* pixel.
    src = np.where(cells, 0, 1).astype(np.uint8)
    d = cv2.distanceTransform(src, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    # Between cell centres the squared distance is an integer: snapping it removes the last-ulp
    # noise of OpenCV's SIMD path (which varies with buffer alignment), so scores are exactly
    # reproducible.
    return np.sqrt(np.rint(d.astype(np.float64) ** 2))


def _chamfer_terms(pred: np.ndarray, gt: np.ndarray, resolution: float, clip: float):
    """Clipped per-cell distances ``(d_pred_to_gt, d_gt_to_pred)`` (1-D float64 arrays, metres).

    If the other set is empty every distance is ``clip`` (distance to an empty set is infinite,
    then clipped).
    """
    n_p = int(np.count_nonzero(pred))
    n_g = int(np.count_nonzero(gt))
    if n_g == 0:
        d_p = np.full(n_p, clip)
    else:
        d_p = np.minimum(_distance_to(gt)[pred].astype(np.float64) * resolution, clip)
    if n_p == 0:
        d_g = np.full(n_g, clip)
    else:
        d_g = np.minimum(_distance_to(pred)[gt].astype(np.float64) * resolution, clip)
    return d_p, d_g


def chamfer(pred, gt, resolution: float, clip: float = DEFAULT_CLIP_M, mask=None):
    """HDMapNet-style Chamfer distance between the positive cells of two ``(H, W)`` bool layers.

    Args:
        pred: ``(H, W)`` bool prediction ``P``.
        gt: ``(H, W)`` bool ground truth ``G``.
        resolution: cell size in metres (``grid.resolution``).
        clip: every point-to-set distance is clipped at this many metres (default 5 m, the
            threshold of HDMapNet's evaluation), so one stray blob cannot dominate.
        mask: optional ``(H, W)`` bool; cells outside it are removed from both ``P`` and ``G``.

    Returns:
        ``(cd_p, cd_l, cd)`` in metres, where ``cd_p`` is the mean over ``p`` in ``P`` of the
        distance to ``G`` (precision side), ``cd_l`` the mean over ``g`` in ``G`` of the distance
        to ``P`` (recall side) and ``cd = (cd_p + cd_l) / 2``.

        * If exactly one set is empty, every term is charged ``clip``: the distance to an empty
          set is clipped to ``clip``, and the mean over an empty set is defined as ``clip``, so
          ``cd_p = cd_l = cd = clip``.
        * If both sets are empty the distance is undefined and ``(nan, nan, nan)`` is returned;
          :class:`MetricAccumulator` then does not count the frame for that class.
    """
    pred = _check_bool("pred", pred, 2)
    gt = _check_bool("gt", gt, 2)
    if pred.shape != gt.shape:
        raise InputError(f"pred shape {pred.shape} does not match gt shape {gt.shape}")
    if not (resolution > 0 and math.isfinite(resolution)):
        raise InputError(f"resolution must be a finite positive number of metres, got {resolution}")
    if not (clip > 0 and math.isfinite(clip)):
        raise InputError(f"clip must be a finite positive number of metres, got {clip}")
    mask = _check_mask("mask", mask, pred.shape)
    if mask is not None:
        pred = pred & mask
        gt = gt & mask
    d_p, d_g = _chamfer_terms(pred, gt, float(resolution), float(clip))
    if d_p.size == 0 and d_g.size == 0:
        return (float("nan"),) * 3
    cd_p = float(d_p.mean()) if d_p.size else float(clip)
    cd_l = float(d_g.mean()) if d_g.size else float(clip)
    return cd_p, cd_l, 0.5 * (cd_p + cd_l)


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


class MetricAccumulator:
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
    :meth:`result`, i.e. dataset-level IoU and precision.
    """

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
        # (B, H*W) float32 band membership; used as a matrix so that per-band counts of all
        # classes come out of one product (exact: counts per frame are far below 2**24).
        self._band_matrix = np.stack(
            [((ranges >= lo) & (ranges < hi)).ravel() for lo, hi in bands]
        ).astype(np.float32) if bands else np.zeros((0, ranges.size), np.float32)
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
        finite = np.isfinite(probs)
        if known is not None:
            finite |= ~known  # values in unknown cells are never looked at
        if not finite.all():
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
        pred = probs >= self.threshold  # (C, H, W)
        if known is not None:
            pred &= known
        mask = visibility if (self.use_visibility and visibility is not None) else None
        if mask is not None:
            pred &= mask  # (H, W) broadcasts over classes; (C, H, W) is per class
            gt = gt & mask

        inter = (pred & gt).reshape(C, -1)  # (C, H*W)
        union = (pred | gt).reshape(C, -1)
        n_inter = np.count_nonzero(inter, axis=1)
        n_union = np.count_nonzero(union, axis=1)
        n_pred = np.count_nonzero(pred.reshape(C, -1), axis=1)
        self._inter += n_inter
        self._union += n_union
        self._tp += n_inter
        self._fp += n_pred - n_inter
        if self.range_bands:
            # (C, H*W) @ (H*W, B) -> (C, B) counts per band
            self._band_inter += np.rint(inter.astype(np.float32) @ self._band_matrix.T).astype(np.int64)
            self._band_union += np.rint(union.astype(np.float32) @ self._band_matrix.T).astype(np.int64)

        for c in range(C):
            d_p, d_g = _chamfer_terms(pred[c], gt[c], self.grid.resolution, self.clip)
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


# ------------------------------------------------------------------------ whole grid
def _calibration_counts(probs: np.ndarray, truth: np.ndarray, mask: np.ndarray, bins: int):
    """Per class and bin: ``(count, sum of p, count present)``, each ``(C, bins)``.

    ``probs`` ``(C, H, W)`` float, ``truth`` ``(C, H, W)`` bool, ``mask`` ``(C, H, W)`` bool.
    """
    C = probs.shape[0]
    p = np.clip(probs.astype(np.float64), 0.0, 1.0)
    b = np.minimum((p * bins).astype(np.int64), bins - 1)  # (C, H, W) bin of each cell
    flat = (b + bins * np.arange(C)[:, None, None])[mask]  # class-major bin ids of scored cells
    size = C * bins
    count = np.bincount(flat, minlength=size).reshape(C, bins)
    conf = np.bincount(flat, weights=p[mask], minlength=size).reshape(C, bins)
    pos = np.bincount(flat, weights=truth[mask].astype(np.float64), minlength=size).reshape(C, bins)
    return count, conf, pos


def _ece_from_counts(count, conf_sum, pos_sum) -> np.ndarray:
    """``(C,)`` ECE from per-bin counts (NaN for a class without scored cells)."""
    count = np.asarray(count, np.float64)
    gap = np.abs(np.asarray(pos_sum, np.float64) - np.asarray(conf_sum, np.float64))
    # n_k / N * |pos_k / n_k - conf_k / n_k| = |pos_k - conf_k| / N
    return _safe_div(gap.sum(axis=1), count.sum(axis=1))


def expected_calibration_error(probs, truth, mask=None, bins: int = ECE_BINS) -> np.ndarray:
    """Per-class expected calibration error of probability layers (see the module docstring).

    Args:
        probs: ``(C, H, W)`` float probabilities.
        truth: ``(C, H, W)`` bool, the class is present.
        mask: optional ``(H, W)`` or ``(C, H, W)`` bool, the cells that count.
        bins: number of equal-width bins over [0, 1].

    Returns:
        ``(C,)`` float64 ECE in [0, 1]; NaN for a class with no cell in the mask.
    """
    probs = np.asarray(probs)
    truth = _check_bool("truth", truth, 3)
    if probs.shape != truth.shape:
        raise InputError(f"probs shape {probs.shape} does not match truth shape {truth.shape}")
    if mask is None:
        mask = np.ones(truth.shape, bool)
    mask = np.broadcast_to(_check_bool("mask", mask, np.ndim(mask)), truth.shape)
    return _ece_from_counts(*_calibration_counts(probs, truth, mask, int(bins)))


class WholeGridAccumulator:
    """What a method publishes over the whole grid, frame by frame (see the module docstring):
    occluded claims, unknown recall, known precision and calibration (ECE).

    Args:
        grid: the :class:`BevGrid` of the layers (cell area for m^2).
        class_names: one name per layer, in layer order.
        threshold: a known cell claims a class when ``p >= threshold``.
        bins: equal-width bins of the ECE (default :data:`ECE_BINS`).

    It never changes :class:`MetricAccumulator`'s scores; the replay runs both on each frame.
    """

    def __init__(self, grid: BevGrid, class_names: Sequence[str], threshold: float = 0.5,
                 bins: int = ECE_BINS) -> None:
        if not isinstance(grid, BevGrid):
            raise ConfigError(f"grid must be a BevGrid, got {type(grid).__name__}")
        names = tuple(str(n) for n in class_names)
        if not names or len(set(names)) != len(names):
            raise ConfigError(f"class_names must be unique and not empty, got {list(names)}")
        if not (0.0 <= float(threshold) <= 1.0):
            raise ConfigError(f"threshold must be in [0, 1], got {threshold}")
        if not (isinstance(bins, int) and bins >= 1):
            raise ConfigError(f"bins must be an integer >= 1, got {bins!r}")
        self.grid = grid
        self.class_names = names
        self.threshold = float(threshold)
        self.bins = bins
        self.reset()

    def reset(self) -> None:
        """Forget all accumulated frames."""
        C, B = len(self.class_names), self.bins
        self.frames = 0
        self.frames_with_truth = 0
        self._cells = self._hidden = self._known = 0
        self._known_visible = self._unknown_hidden = 0
        self._claims = np.zeros(C, np.int64)  # hidden, known, p >= threshold
        self._claims_t = np.zeros(C, np.int64)  # the same, in frames with full truth
        self._false = np.zeros(C, np.int64)  # ... of which the class is absent
        self._count = np.zeros((C, B), np.int64)
        self._conf = np.zeros((C, B), np.float64)
        self._pos = np.zeros((C, B), np.float64)

    def update(self, probs, known, visible, gt, truth=None, calib_mask=None) -> None:
        """Add one frame.

        Args:
            probs: ``(C, H, W)`` float, the probabilities as published (in unknown cells ignored).
            known: ``(H, W)`` bool, cells published as known (not -1).
            visible: ``(H, W)`` bool, cells some camera sees.
            gt: ``(C, H, W)`` bool ground truth, meaningful on visible cells (for the ECE).
            truth: optional ``(C, H, W)`` bool full truth (what is in every cell, seen or not);
                without it the false share of occluded claims is not counted for this frame.
            calib_mask: optional ``(H, W)`` or ``(C, H, W)`` bool, the cells whose calibration
                counts (e.g. the IoU scope masks); default ``visible``. Only known cells count.

        Raises:
            InputError: wrong dtypes or shapes.
        """
        C = len(self.class_names)
        shape = (C,) + self.grid.shape
        probs = np.asarray(probs)
        if not np.issubdtype(probs.dtype, np.floating) or probs.shape != shape:
            raise InputError(f"probs must be float {shape}, got {probs.dtype} {probs.shape}")
        known = _check_mask("known", known, self.grid.shape)
        visible = _check_mask("visible", visible, self.grid.shape)
        gt = _check_bool("gt", gt, 3)
        if gt.shape != shape:
            raise InputError(f"gt shape {gt.shape} does not match (classes, H, W) = {shape}")
        if truth is not None:
            truth = _check_bool("truth", truth, 3)
            if truth.shape != shape:
                raise InputError(f"truth shape {truth.shape} does not match (classes, H, W) = {shape}")
        if calib_mask is None:
            calib_mask = visible
        calib = np.broadcast_to(_check_bool("calib_mask", calib_mask, np.ndim(calib_mask)), shape)

        hidden = ~visible
        self._cells += visible.size
        self._hidden += int(np.count_nonzero(hidden))
        self._known += int(np.count_nonzero(known))
        self._known_visible += int(np.count_nonzero(known & visible))
        self._unknown_hidden += int(np.count_nonzero(hidden & ~known))
        claims = (probs >= self.threshold) & (hidden & known)  # (C, H, W)
        n_claims = np.count_nonzero(claims.reshape(C, -1), axis=1)
        self._claims += n_claims
        if truth is not None:
            self._claims_t += n_claims
            self._false += np.count_nonzero((claims & ~truth).reshape(C, -1), axis=1)
            self.frames_with_truth += 1
        count, conf, pos = _calibration_counts(probs, gt, calib & known, self.bins)
        self._count += count
        self._conf += conf
        self._pos += pos
        self.frames += 1

    def class_ece(self) -> np.ndarray:
        """``(C,)`` ECE so far (NaN for a class with no scored cell)."""
        return _ece_from_counts(self._count, self._conf, self._pos)

    def result(self) -> dict:
        """The whole-grid scores as a plain JSON-serialisable dict.

        Layout::

            {"frames": n, "frames_with_truth": k,
             "occlusion": {"hidden_share", "unknown_recall", "known_precision",
                           "classes": {name: {"claim_share", "false_share",
                                              "claim_m2_per_frame", "false_m2_per_frame"}}},
             "calibration": {"bins": B, "mean_ece": x,
                             "classes": {name: {"ece", "cells",
                                                "reliability": {"count": [B], "confidence": [B],
                                                                "frequency": [B]}}}}}

        Shares are fractions in [0, 1] (``claim_share``: claims over the hidden cells;
        ``false_share``: false claims over the claims of the frames with full truth), areas are
        m^2 per frame (false area per frame with full truth). ``None`` where undefined: no
        hidden cell, no claim, no frame with full truth, an empty bin.
        """
        area = self.grid.resolution ** 2
        n, nt = self.frames, self.frames_with_truth
        classes = {}
        for c, name in enumerate(self.class_names):
            classes[name] = {
                "claim_share": _nan_to_none(_safe_div(self._claims[c], self._hidden)),
                "false_share": _nan_to_none(_safe_div(self._false[c], self._claims_t[c])) if nt else None,
                "claim_m2_per_frame": _nan_to_none(_safe_div(self._claims[c] * area, n)),
                "false_m2_per_frame": _nan_to_none(_safe_div(self._false[c] * area, nt)) if nt else None,
            }
        ece = self.class_ece()
        calib = {}
        for c, name in enumerate(self.class_names):
            calib[name] = {
                "ece": _nan_to_none(ece[c]),
                "cells": int(self._count[c].sum()),
                "reliability": {
                    "count": [int(v) for v in self._count[c]],
                    "confidence": [_nan_to_none(v) for v in _safe_div(self._conf[c], self._count[c])],
                    "frequency": [_nan_to_none(v) for v in _safe_div(self._pos[c], self._count[c])],
                },
            }
        return {
            "frames": int(n),
            "frames_with_truth": int(nt),
            "occlusion": {
                "hidden_share": _nan_to_none(_safe_div(self._hidden, self._cells)),
                "unknown_recall": _nan_to_none(_safe_div(self._unknown_hidden, self._hidden)),
                "known_precision": _nan_to_none(_safe_div(self._known_visible, self._known)),
                "classes": classes,
            },
            "calibration": {
                "bins": self.bins,
                "mean_ece": _nan_to_none(mean_iou(ece)),
                "classes": calib,
            },
        }


# ------------------------------------------------------------------------------ formatting
def _fmt(value, scale: float = 1.0, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value * scale:.{digits}f}"


def format_table(result: dict) -> str:
    """Readable text table of a :meth:`MetricAccumulator.result` dict.

    IoU and precision are shown in percent, Chamfer distances in metres; ``-`` marks undefined
    values.
    """
    classes = result.get("classes", {})
    names = list(classes)
    width = max([len("class"), len("mIoU / mAP")] + [len(n) for n in names])
    lines = [f"BEV metrics over {result.get('frames', 0)} frame(s)"]
    header = f"{'class':<{width}}  {'IoU%':>6}  {'CD_p m':>7}  {'CD_L m':>7}  {'CD m':>7}  {'Prec%':>6}"
    lines += [header, "-" * len(header)]
    for name in names:
        m = classes[name]
        lines.append(
            f"{name:<{width}}  {_fmt(m.get('iou'), 100):>6}  {_fmt(m.get('cd_p'), 1, 3):>7}  "
            f"{_fmt(m.get('cd_l'), 1, 3):>7}  {_fmt(m.get('cd'), 1, 3):>7}  "
            f"{_fmt(m.get('precision'), 100):>6}"
        )
    lines.append("-" * len(header))
    lines.append(f"{'mIoU / mAP':<{width}}  {_fmt(result.get('miou'), 100):>6}  "
                 f"{'':>7}  {'':>7}  {'':>7}  {_fmt(result.get('map'), 100):>6}")

    by_range = result.get("iou_by_range") or {}
    if by_range:
        cols = names + ["miou"]
        colw = [max(6, len(c)) for c in cols]
        bandw = max([len("range m")] + [len(b) for b in by_range])
        lines.append("")
        lines.append("IoU% by range band")
        head = f"{'range m':<{bandw}}  " + "  ".join(f"{c:>{w}}" for c, w in zip(cols, colw))
        lines += [head, "-" * len(head)]
        for band, row in by_range.items():
            lines.append(
                f"{band:<{bandw}}  "
                + "  ".join(f"{_fmt(row.get(c), 100):>{w}}" for c, w in zip(cols, colw))
            )
    return "\n".join(lines)



def format_whole_grid_table(result: dict) -> str:
    """Readable text table of :meth:`WholeGridAccumulator.result` (or of a ``metrics.json``
    holding its ``occlusion`` / ``calibration`` keys).

    Shares and ECE are in percent, areas in m^2 per frame; ``-`` marks undefined values.
    """
    occ = result.get("occlusion") or {}
    cal = result.get("calibration") or {}
    names = list((occ.get("classes") or {}) or (cal.get("classes") or {}))
    width = max([len("class"), len("mean")] + [len(n) for n in names])
    lines = [f"Whole grid: {_fmt(occ.get('hidden_share'), 100)}% of the cells hidden from every "
             f"camera; unknown recall {_fmt(occ.get('unknown_recall'), 100)}% (hidden cells "
             f"published as unknown), known precision {_fmt(occ.get('known_precision'), 100)}% "
             "(published-known cells some camera sees)"]
    header = (f"{'class':<{width}}  {'hidden claim%':>13}  {'false%':>6}  {'claim m2/fr':>11}  "
              f"{'false m2/fr':>11}  {'ECE%':>6}")
    lines += [header, "-" * len(header)]
    for name in names:
        o = (occ.get("classes") or {}).get(name, {})
        c = (cal.get("classes") or {}).get(name, {})
        lines.append(
            f"{name:<{width}}  {_fmt(o.get('claim_share'), 100, 2):>13}  "
            f"{_fmt(o.get('false_share'), 100):>6}  {_fmt(o.get('claim_m2_per_frame')):>11}  "
            f"{_fmt(o.get('false_m2_per_frame')):>11}  {_fmt(c.get('ece'), 100, 2):>6}")
    lines.append("-" * len(header))
    lines.append(f"{'mean':<{width}}  {'':>13}  {'':>6}  {'':>11}  {'':>11}  "
                 f"{_fmt(cal.get('mean_ece'), 100, 2):>6}")
    lines.append(f"hidden claim: cells no camera sees, published known with p >= 0.5; false: of "
                 f"those, where the class is absent (full truth); ECE: {cal.get('bins', ECE_BINS)} "
                 "equal-width bins, visible known cells")
    return "\n".join(lines)
