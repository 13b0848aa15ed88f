"""Input checks and small numeric helpers shared by the metrics modules."""

from __future__ import annotations

import math

import numpy as np

from ..errors import InputError


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


def _row_counts(x: np.ndarray) -> np.ndarray:
    """``(N,)`` int64 True cells of each row of ``x`` ``(N, M)`` bool (``count_nonzero(x,
    axis=1)``, the same numbers: row by row, numpy counts a contiguous bool row several times faster).
    """
    return np.fromiter((np.count_nonzero(row) for row in x), np.int64, len(x))
