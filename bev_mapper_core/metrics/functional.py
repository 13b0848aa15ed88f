"""Per-frame metrics of boolean layers: IoU, mean IoU and HDMapNet's Chamfer distance.

The Chamfer distances run in a small C kernel (``_chamfer.c``, built by ``setup.py`` where a
compiler is; about 5x the numpy path below) when it is built, else in numpy and OpenCV: the
same distances to the bit either way (``tests/bags/replay/test_replay_scoring_unchanged.py``).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from ..errors import InputError
from ._checks import _check_bool, _check_mask, _safe_div
from ._packed import unpack

try:  # the compiled Chamfer kernel (optional: setup.py builds it where a C compiler is)
    from . import _chamfer as _compiled
except ImportError:  # pragma: no cover - the numpy path below gives the same distances
    _compiled = None

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
def _distance_to(cells: np.ndarray, at: np.ndarray, reach: float | None = None) -> np.ndarray:
    """Exact Euclidean distance (in cells) from each cell centre of ``at`` (bool, the same shape)
    to the nearest True cell of ``cells``, as a 1-D float64 array in ``at``'s order.

    ``cells`` must contain at least one True cell. With ``reach`` (cells), distances beyond it
    are only known to be beyond it (at least ``reach``; the caller clips them). The cells of
    ``at`` inside ``cells`` are 0. When the others are many for the box around them widened by
    ``reach`` (:data:`_CELL_COST`), one distance transform of that box finds them all (every
    nearer cell of ``cells`` lies in it, so the distances up to ``reach`` are the same as on the
    whole grid). Otherwise those with a cell of ``cells`` within :data:`_NEAR` cells find it
    among the offsets around them, nearest first, then (when they are few) those within
    :data:`_FARTHER` cells, and the transform runs on the box (or tiles) around the rest,
    widened alike.
    """
    if reach is None:
        # distanceTransform measures the distance to the nearest *zero* pixel.
        return _snap(cv2.distanceTransform(np.where(cells, 0, 1).astype(np.uint8), cv2.DIST_L2,
                                           cv2.DIST_MASK_PRECISE)[at])
    query = at & ~cells
    out = np.zeros(int(np.count_nonzero(at)), np.float64)
    q = np.flatnonzero(query)  # (n,) the cells asked for outside ``cells``, row-major
    if not len(q):
        return out
    H, W = cells.shape
    r = int(math.ceil(reach)) + 1
    rows, cols = q // W, q % W
    around = _box(rows, cols, r, H, W)
    if len(q) * _CELL_COST >= _box_area(around):  # many cells: one transform around them all
        out[~cells[at]] = np.sqrt(_box_d2(cells, around, rows, cols))
        return out
    d2 = np.full(len(q), np.nan)  # squared distance in cells, found so far
    # nearby: every offset up to _NEAR cells around each cell at once, nearest first
    pad = _FARTHER
    padded = np.zeros((H + 2 * pad, W + 2 * pad), bool)  # no cell outside the grid
    padded[pad:pad + H, pad:pad + W] = cells
    wp = W + 2 * pad
    base = (rows + pad) * wp + (cols + pad)  # (n,) flat index into padded
    todo = _nearest(padded.ravel(), base, wp, d2, np.arange(len(q)), _OFFSETS[0])
    if len(todo) and len(todo) * _FARTHER_COST < _box_area(_box(rows[todo], cols[todo], r, H, W)):
        # a few farther: the offsets up to _FARTHER cells (beyond _NEAR), before any transform
        todo = _nearest(padded.ravel(), base, wp, d2, todo, _OFFSETS[1])
    if len(todo):  # farther: the transform around those cells, widened by reach
        rows, cols = rows[todo], cols[todo]
        # one box around them all, or one per tile of _TILE cells holding some when that is less
        tile = (rows // _TILE) * (W // _TILE + 1) + cols // _TILE
        tiles, which = np.unique(tile, return_inverse=True)
        box = _box_area(_box(rows, cols, r, H, W))
        groups = [np.arange(len(todo))] if len(tiles) * (_TILE + 2 * r) ** 2 >= box else \
            [np.flatnonzero(which == i) for i in range(len(tiles))]
        for g in groups:
            d2[todo[g]] = _box_d2(cells, _box(rows[g], cols[g], r, H, W), rows[g], cols[g])
    out[~cells[at]] = np.sqrt(d2)  # at's order: q is row-major, as at's cells
    return out


def _nearest(padded: np.ndarray, base: np.ndarray, wp: int, d2: np.ndarray, todo: np.ndarray,
             offsets: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """For the cells ``todo`` (indices into ``base``, their flat indices in ``padded``, a grid
    ``wp`` wide padded with no cells), the nearest cell among ``offsets`` ``(d2, dy, dx)``
    (nearest first): its squared distance into ``d2``. Returns the cells of ``todo`` with none.
    """
    o_d2, o_dy, o_dx = offsets
    hit = padded[base[todo, None] + (o_dy * wp + o_dx)[None, :]]  # (n, K)
    first = hit.argmax(axis=1)  # (n,) the nearest offset holding a cell (0 when none does)
    found = hit[np.arange(len(todo)), first]
    d2[todo[found]] = o_d2[first[found]]
    return todo[~found]


def _box(rows: np.ndarray, cols: np.ndarray, r: int, H: int, W: int) -> tuple[int, int, int, int]:
    """``(r0, r1, c0, c1)``: the box ``[r0, r1) x [c0, c1)`` around the cells ``(rows, cols)``
    widened by ``r``, inside the ``(H, W)`` grid.
    """
    return (max(int(rows.min()) - r, 0), min(int(rows.max()) + r + 1, H),
            max(int(cols.min()) - r, 0), min(int(cols.max()) + r + 1, W))


def _box_area(box: tuple[int, int, int, int]) -> int:
    """Cells of a :func:`_box`."""
    r0, r1, c0, c1 = box
    return (r1 - r0) * (c1 - c0)


def _box_d2(cells: np.ndarray, box: tuple[int, int, int, int], rows: np.ndarray,
            cols: np.ndarray) -> np.ndarray:
    """Squared distances (cells, float64 integers) from the cells ``(rows, cols)`` to the
    nearest True cell of ``cells`` inside ``box`` (:func:`_box`), by one distance transform of
    the box (snapped as :func:`_snap`).
    """
    r0, r1, c0, c1 = box
    src = (~cells[r0:r1, c0:c1]).view(np.uint8)  # (h, w) 1 = not a cell; the transform finds 0s
    d = cv2.distanceTransform(np.ascontiguousarray(src), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.rint(d[rows - r0, cols - c0].astype(np.float64) ** 2)


#: :func:`_distance_to` looks for the nearest cell among the offsets up to this many cells away
#: before it runs a distance transform
_NEAR = 4
#: ... and runs it per tile of this many cells holding farther cells when that is less work
_TILE = 32


#: ... then, when that is less work than a transform (:data:`_FARTHER_COST`), among the offsets
#: up to this many cells
_FARTHER = 12
#: a distance transform costs about this many cells' farther search per cell of its box
_FARTHER_COST = 60


def _offsets(lo: int, hi: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The offsets ``lo < distance <= hi`` cells one by one, nearest first (all of those at
    each distance, so the first hit is the nearest): ``(K,)`` squared distance (float64), rows
    and columns.
    """
    dy, dx = np.mgrid[-hi:hi + 1, -hi:hi + 1]
    d2 = dy ** 2 + dx ** 2
    keep = (d2 > lo ** 2) & (d2 <= hi ** 2)
    order = np.argsort(d2[keep], kind="stable")  # nearest first; at one distance, row-major
    return d2[keep][order].astype(np.float64), dy[keep][order], dx[keep][order]


#: the offsets of the near search, then of the farther one
_OFFSETS = (_offsets(0, _NEAR), _offsets(_NEAR, _FARTHER))
#: a distance transform costs about this many cells' near search per cell of its box: with more
#: cells asked than its box's area over this, one transform of the box finds them all
_CELL_COST = 60


def _snap(d: np.ndarray) -> np.ndarray:
    """Distances between cell centres from OpenCV's float32 transform, exact: the squared
    distance is an integer, and snapping it removes the last-ulp noise of OpenCV's SIMD path
    (which varies with buffer alignment), so scores are exactly reproducible.
    """
    return np.sqrt(np.rint(d.astype(np.float64) ** 2))


def _chamfer_terms(pred: np.ndarray, gt: np.ndarray, resolution: float, clip: float):
    """Clipped per-cell distances ``(d_pred_to_gt, d_gt_to_pred)`` (1-D float64 arrays, metres,
    each in its set's row-major order) between two ``(H, W)`` bool layers: by the compiled
    kernel where it is built (:func:`_compiled_terms`), else :func:`_numpy_terms`.
    """
    if _compiled is not None and sum(pred.shape) < _COMPILED_MAX:
        return _compiled_terms(np.ascontiguousarray(pred).view(np.uint8), np.ascontiguousarray(gt).view(np.uint8),
                               1, pred.shape, resolution, clip)
    return _numpy_terms(pred, gt, resolution, clip)


def _packed_chamfer_terms(pred: np.ndarray, gt: np.ndarray, c: int, shape: tuple[int, int],
                          resolution: float, clip: float):
    """:func:`_chamfer_terms` of class ``c`` of packed layers (``(G, H*W)`` uint8 of
    :func:`~._packed.pack`, cells of ``shape``), read in place by the compiled kernel.
    """
    if _compiled is not None and sum(shape) < _COMPILED_MAX:
        group, bit = divmod(c, 8)
        return _compiled_terms(pred[group], gt[group], 1 << bit, shape, resolution, clip)
    return _numpy_terms(unpack(pred, c).reshape(shape), unpack(gt, c).reshape(shape), resolution, clip)


#: the compiled kernel counts distances in uint16: grids of ``H + W`` below this
_COMPILED_MAX = 65534


def _compiled_terms(pred: np.ndarray, gt: np.ndarray, bit: int, shape: tuple[int, int],
                    resolution: float, clip: float):
    """:func:`_numpy_terms` by the compiled kernel, of the cells of ``pred`` and ``gt``
    (``(H*W,)`` contiguous uint8, a cell in the set where ``byte & bit``).
    """
    H, W = shape
    out_p, out_g = np.empty(H * W), np.empty(H * W)  # float64; the first n_p / n_g are written
    reach = int(math.ceil(clip / resolution)) + 1  # cells: exact as far as the clip, as _distance_to
    n_p, n_g = _compiled.distances(pred, gt, bit, H, W, reach, resolution, clip, out_p, out_g)
    return out_p[:n_p], out_g[:n_g]


def _numpy_terms(pred: np.ndarray, gt: np.ndarray, resolution: float, clip: float):
    """Clipped per-cell distances ``(d_pred_to_gt, d_gt_to_pred)`` (1-D float64 arrays, metres).

    If the other set is empty every distance is ``clip`` (distance to an empty set is infinite,
    then clipped). Distances are only computed as far as the clip (:func:`_distance_to`), inside
    the box around both sets (the same cells in the same row-major order, and no other cell of
    either set to be near).
    """
    n_p = int(np.count_nonzero(pred))
    n_g = int(np.count_nonzero(gt))
    if n_p and n_g:
        both = pred | gt
        rows = np.flatnonzero(both.any(axis=1))
        cols = np.flatnonzero(both.any(axis=0))
        box = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
        pred, gt = pred[box], gt[box]
    reach = clip / resolution
    if n_g == 0:
        d_p = np.full(n_p, clip)
    else:
        d_p = np.minimum(_distance_to(gt, pred, reach) * resolution, clip)
    if n_p == 0:
        d_g = np.full(n_g, clip)
    else:
        d_g = np.minimum(_distance_to(pred, gt, reach) * resolution, clip)
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
