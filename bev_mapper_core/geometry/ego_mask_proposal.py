"""Proposing an ego-body mask from a drive: the pixels that never change.

While the vehicle drives, the world moves through every camera's image; the ego's own body (hood,
trunk, mirrors) stays put. :class:`StaticPixels` watches one camera's frames and keeps the pixels
whose label (and colour, where both are given) never changed; :meth:`StaticPixels.proposal` cleans
them with a morphological open then close and keeps only the regions that touch the image's
bottom or side border and not its top row (a sky of constant colour or ``UNLABELED`` touches the
top). Pixels constantly ``UNLABELED`` are left out: masking them would change nothing.

A proposal is for a person to check: a road of uniform colour right in front of a vehicle that
drove straight can look as constant as a hood. Longer drives with turns give better proposals.
"""

from __future__ import annotations

import cv2
import numpy as np

from .ego_mask import EgoMask

#: colour difference (any channel, 0..255) below which a pixel counts as unchanged (JPEG noise)
COLOUR_TOLERANCE = 12


class StaticPixels:
    """Accumulates which pixels of one camera never changed over the frames seen.

    Args:
        tolerance: largest per-channel colour difference that counts as unchanged.
    """

    def __init__(self, tolerance: int = COLOUR_TOLERANCE) -> None:
        self.tolerance = int(tolerance)
        self.frames = 0
        self._first_labels: np.ndarray | None = None
        self._first_rgb: np.ndarray | None = None
        self._changed: np.ndarray | None = None  # (H, W) bool

    def add(self, labels: np.ndarray | None = None, rgb: np.ndarray | None = None) -> None:
        """One frame: its label image ``(H, W)`` and/or RGB image ``(H, W, 3)`` (same kinds every frame).

        Raises:
            ValueError: no image, or a size that differs from the first frame's.
        """
        if labels is None and rgb is None:
            raise ValueError("a frame needs a label or an RGB image")
        shape = (labels if labels is not None else rgb).shape[:2]
        if self._changed is None:
            self._changed = np.zeros(shape, bool)
            self._first_labels = None if labels is None else labels.copy()
            self._first_rgb = None if rgb is None else rgb.astype(np.int16)
        elif self._changed.shape != shape:
            raise ValueError(f"image size changed from {self._changed.shape[::-1]} to {shape[::-1]}")
        else:
            if labels is not None and self._first_labels is not None:
                self._changed |= labels != self._first_labels
            if rgb is not None and self._first_rgb is not None:
                diff = np.abs(rgb.astype(np.int16) - self._first_rgb).max(axis=2)  # (H, W)
                self._changed |= diff > self.tolerance
        self.frames += 1

    def static(self) -> np.ndarray:
        """``(H, W)`` bool: pixels that never changed (before cleaning)."""
        if self._changed is None:
            raise ValueError("no frame seen")
        out = ~self._changed
        if self._first_labels is not None:
            out &= self._first_labels != 0  # constantly UNLABELED: masking changes nothing
        return out

    def proposal(self, source: str = "proposal") -> EgoMask:
        """The cleaned mask (see the module docstring)."""
        static = self.static().astype(np.uint8)
        h, w = static.shape
        k = max(3, (min(h, w) // 40) | 1)  # odd kernel, ~2.5 % of the image
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        cleaned = cv2.morphologyEx(static, cv2.MORPH_OPEN, kernel)
        cleaned = cv2.morphologyEx(cleaned, cv2.MORPH_CLOSE, kernel)
        n, comp = cv2.connectedComponents(cleaned, connectivity=8)  # comp: (H, W) int32
        border = np.concatenate([comp[-1], comp[:, 0], comp[:, -1]])
        keep = set(np.unique(border[border > 0]).tolist()) - set(np.unique(comp[0]).tolist())
        mask = np.isin(comp, sorted(keep)) if keep else np.zeros((h, w), bool)
        return EgoMask(mask, source)


__all__ = ["COLOUR_TOLERANCE", "StaticPixels"]
