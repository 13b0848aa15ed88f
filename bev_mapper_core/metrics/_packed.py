"""Per-class cell counts of bool layers packed one bit per class, 8 classes a byte.

The scorers count, per class and frame, the cells of a few ``(C, H, W)`` bool layers (the
intersection and union of prediction and ground truth, the prediction), in total and per range
band. Packed, a frame's classes are ``ceil(C / 8)`` bytes per cell, so each step of the counting
reads ``H * W`` bytes instead of ``C * H * W``: one histogram of the 256 byte values per group
of 8 classes (and per range-band pattern of the cells) gives every class's counts at once, the
same integers as counting each class's layer.
"""

from __future__ import annotations

import numpy as np

#: ``(256, 8)`` int64: bit ``b`` of each byte value
_BITS = ((np.arange(256)[:, None] >> np.arange(8)[None, :]) & 1).astype(np.int64)


def pack(layers: np.ndarray) -> np.ndarray:
    """``(G, N)`` uint8, ``G = ceil(C / 8)``: bit ``c % 8`` of group ``c // 8`` is ``layers[c]``
    (``(C, ...)`` bool, flattened to ``N`` cells per class).
    """
    C = layers.shape[0]
    flat = np.ascontiguousarray(layers).reshape(C, -1).view(np.uint8)  # (C, ...) -> (C, N) 0/1
    out = np.empty((-(-C // 8), flat.shape[1]), np.uint8)
    shifted = np.empty(flat.shape[1], np.uint8)
    for c in range(C):
        group, bit = divmod(c, 8)
        if bit == 0:
            out[group] = flat[c]
        else:
            np.multiply(flat[c], np.uint8(1 << bit), out=shifted)  # (numpy multiplies bytes faster than it shifts them)
            out[group] |= shifted
    return out


def unpack(bits: np.ndarray, c: int) -> np.ndarray:
    """``(N,)`` bool layer of class ``c`` from :func:`pack`'s ``(G, N)`` bytes."""
    group, bit = divmod(c, 8)
    return np.bitwise_and(bits[group], np.uint8(1 << bit)).astype(np.bool_)


class CellCounter:
    """Counts the True cells of every class of packed layers (:func:`pack`), in total and per
    range band, from one histogram per group of 8 classes.

    Args:
        n_classes: ``C``.
        band_masks: ``(B, N)`` bool, the cells of each band (bands may overlap; ``B`` may be 0).

    Each cell's membership of the bands is one of ``K`` patterns (found once here); a histogram
    of ``256 * pattern + byte`` over the cells counts, per pattern, the cells of each byte value,
    and the bits of the byte values and the patterns' bands turn it into per-class counts.
    """

    def __init__(self, n_classes: int, band_masks: np.ndarray) -> None:
        self.n_classes = int(n_classes)
        self.n_bands = band_masks.shape[0]
        if not self.n_bands:  # one pattern, in no band
            patterns, which = np.zeros((1, 0), bool), np.zeros(band_masks.shape[1], np.intp)
        elif self.n_bands <= 62:  # each cell's bands as the bits of one integer
            code = (band_masks.astype(np.int64) << np.arange(self.n_bands)[:, None]).sum(axis=0)  # (N,)
            codes, which = np.unique(code, return_inverse=True)  # (K,), (N,)
            patterns = (codes[:, None] >> np.arange(self.n_bands)[None, :]) & 1  # (K, B)
        else:
            patterns, which = np.unique(band_masks.T, axis=0, return_inverse=True)  # (K, B), (N,)
        self._offset = which.reshape(-1).astype(np.intp) * 256  # (N,) 256 * pattern of each cell
        self._members = patterns.astype(np.int64)  # (K, B) 1 where the pattern is in the band
        self._bins = 256 * len(patterns)

    def totals(self, bits: np.ndarray) -> np.ndarray:
        """``(C,)`` int64 True cells of each class in ``bits`` ``(G, N)`` (no bands: one plain histogram)."""
        C = self.n_classes
        totals = np.empty(C, np.int64)
        for group in range(bits.shape[0]):
            n = min(8, C - 8 * group)
            totals[8 * group:8 * group + n] = np.bincount(bits[group], minlength=256) @ _BITS[:, :n]
        return totals

    def counts(self, bits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(totals (C,), per band (C, B))`` int64 True cells of each class in ``bits`` ``(G, N)``."""
        C = self.n_classes
        totals = np.empty(C, np.int64)
        bands = np.empty((C, self.n_bands), np.int64)
        for group in range(bits.shape[0]):
            n = min(8, C - 8 * group)
            hist = np.bincount(self._offset + bits[group], minlength=self._bins)  # (K * 256,)
            per = hist.reshape(-1, 256) @ _BITS[:, :n]  # (K, 256) @ (256, n) -> (K, n) cells per pattern
            totals[8 * group:8 * group + n] = per.sum(axis=0)
            bands[8 * group:8 * group + n] = per.T @ self._members  # (n, K) @ (K, B) -> (n, B)
        return totals, bands

