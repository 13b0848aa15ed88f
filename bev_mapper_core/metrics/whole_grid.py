"""Whole-grid scores: occluded claims, unknown recall, known precision and calibration (ECE)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from ..errors import ConfigError, InputError
from ..geometry.grid import BevGrid
from ._checks import _check_bool, _check_mask, _nan_to_none, _row_counts, _safe_div
from ._state import Mergeable
from .functional import mean_iou

#: Equal-width probability bins of the expected calibration error (see the package docstring).
ECE_BINS = 10


# ------------------------------------------------------------------------ whole grid
def _calibration_counts(probs: np.ndarray, truth: np.ndarray, mask: np.ndarray, bins: int):
    """Per class and bin: ``(count, sum of p, count present)``, each ``(C, bins)``.

    ``probs`` ``(C, H, W)`` float, ``truth`` ``(C, H, W)`` bool, ``mask`` ``(C, H, W)`` bool.
    """
    C = probs.shape[0]
    # the scored cells only, class-major (boolean indexing keeps C order): (n,) each
    p = np.clip(probs[mask].astype(np.float64), 0.0, 1.0)
    cls = np.repeat(np.arange(C), np.count_nonzero(mask.reshape(C, -1), axis=1))  # class of each scored cell
    flat = np.minimum((p * bins).astype(np.int64), bins - 1) + bins * cls  # class-major bin ids
    size = C * bins
    conf = np.bincount(flat, weights=p, minlength=size).reshape(C, bins)
    # one count of (bin, present) pairs gives both the cells and the present cells per bin
    pairs = np.bincount(2 * flat + truth[mask], minlength=2 * size).reshape(C, bins, 2)
    count = pairs.sum(axis=2)
    pos = pairs[..., 1].astype(np.float64)
    return count, conf, pos


#: :func:`_percent_calibration_counts` sums exactly while a class has at most this many cells
_EXACT_PERCENT_CELLS = 2 ** 22


def _percent_calibration_counts(percent: np.ndarray, values: np.ndarray, truth: np.ndarray,
                                mask: np.ndarray, bins: int):
    """:func:`_calibration_counts` of probabilities given as whole percent, the same numbers.

    ``percent`` ``(C, H, W)`` uint8 in 0..100 and ``values`` ``(101,)``, the probability each
    percent stands for (``probs == values[percent]``); ``truth``, ``mask`` as there. One masked
    histogram of ``2 * percent + truth`` per class replaces the per-cell sums: every value is a
    float32 of at least 0.01, a multiple of 2**-30, so with fewer than 2**22 cells each partial
    sum of the confidences is exact in float64 in any order, and ``count * value`` too.
    """
    C = percent.shape[0]
    p = np.clip(np.asarray(values, np.float64), 0.0, 1.0)  # (101,) as the per-cell path reads them
    bin_of = np.minimum((p * bins).astype(np.int64), bins - 1)  # (101,)
    onehot = np.zeros((101, bins), np.float64)
    onehot[np.arange(101), bin_of] = 1.0
    code = np.add(percent, percent)  # (C, H, W) uint8: 2 * percent + present (numpy adds bytes faster than it shifts them)
    code |= truth.view(np.uint8)
    hist = np.empty((C, 202), np.float64)
    for c in range(C):  # (202,) cells per (percent, present) inside the mask
        hist[c] = cv2.calcHist([code[c]], [0], mask[c].view(np.uint8), [202], [0, 202]).ravel()
    pairs = hist.reshape(C, 101, 2)
    cells = pairs.sum(axis=2)  # (C, 101)
    count = np.rint(cells @ onehot).astype(np.int64)  # (C, bins)
    conf = (cells * p[None]) @ onehot
    pos = pairs[..., 1] @ onehot
    return count, conf, pos


def _ece_from_counts(count, conf_sum, pos_sum) -> np.ndarray:
    """``(C,)`` ECE from per-bin counts (NaN for a class without scored cells)."""
    count = np.asarray(count, np.float64)
    gap = np.abs(np.asarray(pos_sum, np.float64) - np.asarray(conf_sum, np.float64))
    # n_k / N * |pos_k / n_k - conf_k / n_k| = |pos_k - conf_k| / N
    return _safe_div(gap.sum(axis=1), count.sum(axis=1))


def expected_calibration_error(probs, truth, mask=None, bins: int = ECE_BINS) -> np.ndarray:
    """Per-class expected calibration error of probability layers (see the package docstring of `bev_mapper_core.metrics`).

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


class WholeGridAccumulator(Mergeable):
    """What a method publishes over the whole grid, frame by frame (see the package docstring of `bev_mapper_core.metrics`):
    occluded claims, unknown recall, known precision and calibration (ECE).

    Args:
        grid: the :class:`BevGrid` of the layers (cell area for m^2).
        class_names: one name per layer, in layer order.
        threshold: a known cell claims a class when ``p >= threshold``.
        bins: equal-width bins of the ECE (default :data:`ECE_BINS`).

    It never changes :class:`MetricAccumulator`'s scores; the replay runs both on each frame.
    Like it, accumulators of several drives merge exactly (:meth:`merge`, :meth:`state`).
    """

    _COUNTS = ("frames", "frames_with_truth", "_cells", "_hidden", "_known", "_known_visible",
               "_unknown_hidden", "_claims", "_claims_t", "_false", "_count", "_conf", "_pos")

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

    def _config(self) -> dict:
        return {"grid": self.grid.to_dict(), "class_names": list(self.class_names),
                "threshold": self.threshold, "bins": self.bins}

    @classmethod
    def _from_config(cls, config: dict) -> "WholeGridAccumulator":
        try:
            return cls(BevGrid.from_dict(config["grid"]), config["class_names"],
                       threshold=config["threshold"], bins=config["bins"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"invalid WholeGridAccumulator state configuration: {exc!r}") from exc

    def update(self, probs, known, visible, gt, truth=None, calib_mask=None, percent=None) -> None:
        """Add one frame.

        Args:
            probs: ``(C, H, W)`` float, the probabilities as published (in unknown cells
                ignored); may be ``None`` when ``percent`` is given.
            known: ``(H, W)`` bool, cells published as known (not -1).
            visible: ``(H, W)`` bool, cells some camera sees.
            gt: ``(C, H, W)`` bool ground truth, meaningful on visible cells (for the ECE).
            truth: optional ``(C, H, W)`` bool full truth (what is in every cell, seen or not);
                without it the false share of occluded claims is not counted for this frame.
            calib_mask: optional ``(H, W)`` or ``(C, H, W)`` bool, the cells whose calibration
                counts (e.g. the IoU scope masks); default ``visible``. Only known cells count.
            percent: optional ``(C, H, W)`` uint8, ``probs`` as whole percent when they are
                (``probs == np.arange(101, dtype=probs.dtype)[percent] / 100.0``, as published in
                the OccupancyGrids): the calibration counts then come from one histogram per
                class, the same numbers (:func:`_percent_calibration_counts`).

        Raises:
            InputError: wrong dtypes or shapes.
        """
        C = len(self.class_names)
        shape = (C,) + self.grid.shape
        if probs is None and percent is not None:
            percent = np.asarray(percent)
            if percent.dtype != np.uint8 or percent.shape != shape:
                raise InputError(f"percent must be uint8 {shape}, got {percent.dtype} {percent.shape}")
            values = np.arange(101, dtype=np.float32) / 100.0  # what each percent is published as
        else:
            probs = np.asarray(probs)
            if not np.issubdtype(probs.dtype, np.floating) or probs.shape != shape:
                raise InputError(f"probs must be float {shape}, got {probs.dtype} {probs.shape}")
            values = np.arange(101, dtype=probs.dtype) / 100.0
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
        if probs is None:  # p >= threshold from the percent: the values increase with it
            claims = percent >= np.count_nonzero(~(values >= self.threshold))
        else:
            claims = probs >= self.threshold
        claims &= hidden & known  # (C, H, W)
        n_claims = _row_counts(claims.reshape(C, -1))
        self._claims += n_claims
        if truth is not None:
            self._claims_t += n_claims
            self._false += _row_counts((claims & ~truth).reshape(C, -1))
            self.frames_with_truth += 1
        if percent is not None and percent[0].size <= _EXACT_PERCENT_CELLS:
            mask = np.ascontiguousarray(calib & known)
            count, conf, pos = _percent_calibration_counts(np.ascontiguousarray(percent, np.uint8), values,
                                                           np.ascontiguousarray(gt), mask, self.bins)
        else:
            if probs is None:
                probs = values[np.minimum(percent, 100)]  # (C, H, W); unknown cells may hold any byte
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
