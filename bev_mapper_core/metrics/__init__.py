"""Evaluation metrics of BEV semantic maps: IoU / mIoU, Chamfer distance, precision / "mAP".

Framework-free (numpy + OpenCV). All layers follow :mod:`bev_mapper_core.geometry.grid`: a class stack is
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


from .accumulator import RANGE_BAND_M, SCOPES, MetricAccumulator, default_range_bands, scope_masks
from .functional import DEFAULT_CLIP_M, chamfer, iou, mean_iou
from .table import format_table, format_whole_grid_table
from .whole_grid import ECE_BINS, WholeGridAccumulator, expected_calibration_error

__all__ = [
    "DEFAULT_CLIP_M",
    "ECE_BINS",
    "RANGE_BAND_M",
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
