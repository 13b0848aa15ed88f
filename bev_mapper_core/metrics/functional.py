"""Per-frame metrics of boolean layers: IoU, mean IoU and HDMapNet's Chamfer distance."""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..errors import InputError
from ._checks import _check_bool, _check_mask, _safe_div

#: Default Chamfer clipping distance in metres (HDMapNet's evaluation ``--CD_threshold`` = 5).
DEFAULT_CLIP_M = 5.0


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
def _distance_to(cells: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Exact Euclidean distance (in cells) from each cell centre of ``at`` (bool, the same shape)
    to the nearest True cell of ``cells``, as a 1-D float64 array in ``at``'s order.

    ``cells`` must contain at least one True cell.
    """
    # distanceTransform measures the distance to the nearest *zero* pixel.
    src = np.where(cells, 0, 1).astype(np.uint8)
    d = cv2.distanceTransform(src, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[at]
    # Between cell centres the squared distance is an integer: snapping it removes the last-ulp
    # noise of OpenCV's SIMD path (which varies with buffer alignment), so scores are exactly
    # reproducible. Only the cells asked for are snapped.
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
        d_p = np.minimum(_distance_to(gt, pred) * resolution, clip)
    if n_p == 0:
        d_g = np.full(n_g, clip)
    else:
        d_g = np.minimum(_distance_to(pred, gt) * resolution, clip)
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
