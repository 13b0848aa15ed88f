"""Common part of the dataset readers: samples, errors, reading and checking image files."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..labels.label_maps import file_kind
from ..labels.spaces import IGNORE, LabelSpace

#: Image file suffixes the readers list (lower case).
IMAGE_SUFFIXES: tuple[str, ...] = (".png", ".jpg", ".jpeg")


class DatasetError(InputError):
    """A dataset file is missing, unreadable, or disagrees with its partner (the message names it)."""


@dataclass(frozen=True)
class Sample:
    """One labelled frame.

    Attributes:
        image: ``(H, W, 3)`` uint8 RGB.
        labels: ``(H, W)`` uint8 class ids of the dataset's :class:`LabelSpace`, ``IGNORE`` (255)
            where unlabelled.
        name: the image's file name (for messages and outputs).
    """

    image: np.ndarray
    labels: np.ndarray
    name: str


def _need(path: Path, kind: str, missing: str) -> None:
    """Raise :class:`DatasetError` unless ``path`` is a ``kind`` (``file`` or ``directory``): a
    missing path says ``missing``, anything else what it is (a FIFO or device is never opened).
    """
    found = file_kind(path)
    if found is None:
        raise DatasetError(f"{path}: {missing}")
    if found != kind:
        raise DatasetError(f"{path} is a {found}, not a {'folder' if kind == 'directory' else 'file'}")


def read_rgb(path: Path) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB of an image file (PNG or JPEG; grey images are expanded).

    Raises:
        DatasetError: missing or undecodable file.
    """
    import cv2  # noqa: PLC0415 - only the readers need OpenCV

    _need(path, "file", "no such image")
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)  # BGR, 8 bit
    if img is None:
        raise DatasetError(f"{path}: not a readable PNG or JPEG image")
    return np.ascontiguousarray(img[..., ::-1])


def read_label_png(path: Path, color: bool = False) -> np.ndarray:
    """A label PNG as stored: ``(H, W)`` uint8 ids, or ``(H, W, 3)`` uint8 RGB when ``color``.

    Raises:
        DatasetError: missing, undecodable, not 8-bit, or of the wrong channel count.
    """
    import cv2  # noqa: PLC0415

    _need(path, "file", "missing annotation")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise DatasetError(f"{path}: not a readable label image")
    if img.dtype != np.uint8:
        raise DatasetError(f"{path}: label images must be 8 bit, got {img.dtype}")
    if color:
        if img.ndim != 3 or img.shape[2] not in (3, 4):
            raise DatasetError(f"{path}: an rgb8 label map needs colour label images, got shape {img.shape}")
        return np.ascontiguousarray(img[..., 2::-1])  # BGR(A) -> RGB
    if img.ndim == 3:
        raise DatasetError(f"{path}: a mono8 label map needs single-channel label images, got shape {img.shape}")
    return img


@dataclass
class LabeledImages:
    """Base of the readers: a list of ``(image path, label path)`` pairs read on demand.

    Subclasses set :attr:`space` and implement :meth:`_convert` (stored labels -> class ids,
    raising :class:`DatasetError` for ids outside the map). With ``skip_bad`` a bad pair is
    skipped and recorded in :attr:`skipped` (``(file, reason)``) instead of raising.
    """

    pairs: list[tuple[Path, Path]]
    space: LabelSpace
    skip_bad: bool = False
    skipped: list[tuple[str, str]] = field(default_factory=list)

    def __post_init__(self) -> None:
        #: bad pairs found while listing (missing annotations), kept across passes
        self.listing_skipped = list(self.skipped)

    def __len__(self) -> int:
        return len(self.pairs)

    def read(self, i: int) -> Sample:
        """Sample ``i``, checked.

        Raises:
            DatasetError: unreadable file, missing annotation, sizes that differ, ids outside the map.
        """
        img_path, lab_path = self.pairs[i]
        image = read_rgb(img_path)
        labels = self._convert(lab_path)
        if labels.shape != image.shape[:2]:
            raise DatasetError(f"{lab_path}: label image is {labels.shape[1]}x{labels.shape[0]}, "
                               f"its image {img_path.name} is {image.shape[1]}x{image.shape[0]}")
        return Sample(image, labels, img_path.name)

    def __iter__(self) -> Iterator[Sample]:
        """Every sample in order; with ``skip_bad``, bad pairs are left out and counted."""
        for i in range(len(self)):
            try:
                yield self.read(i)
            except DatasetError as e:
                if not self.skip_bad:
                    raise
                self.skipped.append((str(self.pairs[i][1]), str(e)))

    def load_all(self) -> tuple[list[Sample], list[tuple[str, str]]]:
        """All good samples and the skipped ``(file, reason)`` (those found while listing, then
        those of this pass).
        """
        self.skipped = list(self.listing_skipped)
        samples = list(self)
        return samples, list(self.skipped)

    def _convert(self, label_path: Path) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError


def list_images(folder: Path) -> list[Path]:
    """Image files of ``folder`` (sorted by name).

    Raises:
        DatasetError: the folder does not exist.
    """
    _need(folder, "directory", "no such folder")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


def pair_by_stem(images: list[Path], label_dir: Path, skip_bad: bool,
                 skipped: list[tuple[str, str]]) -> list[tuple[Path, Path]]:
    """``(image, label_dir/<stem>.png)`` pairs; a missing label PNG raises (or, with ``skip_bad``,
    is recorded in ``skipped``).

    Raises:
        DatasetError: the label folder is missing, or an image has no label PNG.
    """
    _need(label_dir, "directory", "no such label folder")
    pairs = []
    for img in images:
        lab = label_dir / f"{img.stem}.png"
        kind = file_kind(lab)
        if kind != "file":
            reason = f"missing annotation of {img.name}" if kind is None else f"is a {kind}, not a file"
            if not skip_bad:
                raise DatasetError(f"{lab}: missing annotation of {img}" if kind is None else f"{lab} {reason}")
            skipped.append((str(lab), reason))
            continue
        pairs.append((img, lab))
    return pairs


__all__ = ["IGNORE", "IMAGE_SUFFIXES", "DatasetError", "LabeledImages", "Sample", "list_images", "pair_by_stem",
           "read_label_png", "read_rgb"]
