"""A team's own labelled frames: ``images/``, ``labels/`` and a label map.

Layout::

    DIR/images/<name>.png|.jpg     RGB frames
    DIR/labels/<name>.png          label images (mono8 ids, or an rgb8 colour palette)
    DIR/label_map.yaml             upstream id (or colour) -> label name

The YAML file is the :mod:`~bev_mapper_core.label_maps` format (``encoding``, ``labels``) with
one optional extra key, ``ignore``: a list of upstream ids (or colours) that mean "not labelled"
(skipped by the loss and the scores). Instead of the file, ``label_map=`` may name a preset:
``native``, ``cityscapes_ids`` (ids 0..3, unlabelled / ego vehicle / border / out of roi, ignored),
``cityscapes_train_ids`` (255 ignored) or ``cam2bev``. Every id (colour) in a label image must be
named by the map or its ``ignore`` list: anything else is an error, not silently "unlabeled".

Labels come back as fine :class:`~bev_mapper_core.labels.classes.Label` ids; the reader's
:attr:`~.base.LabeledImages.space` says what each covers in training
(:func:`~bev_mapper_core.nn.label_space.space_from_labels`: a Cityscapes ``road`` covers the
markings and crossings the map never produces, ``sidewalk`` the curb).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ..errors import ConfigError
from ..labels.label_maps import PRESET_NAMES, LabelMap, file_kind, label_map, label_map_from_dict, pack_rgb, read_yaml_document
from ..labels.spaces import IGNORE, space_from_labels
from .base import DatasetError, LabeledImages, list_images, pair_by_stem, read_label_png

#: Default label-map file name inside a folder dataset.
LABEL_MAP_FILE = "label_map.yaml"
#: Upstream ids each mono8 preset names (ids outside are errors) and ignores.
_PRESET_IDS: dict[str, tuple[range | tuple[int, ...], tuple[int, ...]]] = {
    "native": (range(0, 11), (IGNORE,)),
    "cityscapes_ids": (range(4, 34), (0, 1, 2, 3)),
    "cityscapes_train_ids": (range(0, 19), (255,)),
}


def _known_from_doc(doc: dict, where: str) -> tuple[dict, np.ndarray, np.ndarray]:
    """``(doc without 'ignore', known keys, ignored keys)`` of a folder's YAML document; keys
    are upstream ids (mono8) or packed colours (rgb8).
    """
    if not isinstance(doc, dict):
        raise ConfigError(f"{where} must be a mapping with 'labels' (and optionally 'encoding', 'ignore')")
    doc = dict(doc)
    ignore = doc.pop("ignore", []) or []
    if not isinstance(ignore, list):
        raise ConfigError(f"{where}: 'ignore' must be a list of upstream ids or colours")
    encoding = doc.get("encoding", "mono8")
    lm = label_map_from_dict(doc, where, where)  # validates labels and encoding
    # re-parse the keys through a throwaway map so ids and colours are read by the one parser
    probe = label_map_from_dict({"encoding": encoding, "labels": {k: "road" for k in ignore}}, where, where) \
        if ignore else None
    if encoding == "mono8":
        known = np.array(sorted(int(k) for k in doc["labels"]), np.int64)
        ign = np.flatnonzero(probe.table == 1) if probe is not None else np.zeros(0, np.int64)
    else:
        known = lm.colors.astype(np.int64)
        ign = probe.colors.astype(np.int64) if probe is not None else np.zeros(0, np.int64)
    if np.isin(ign, known).any():
        raise ConfigError(f"{where}: an id or colour is both labelled and ignored")
    return doc, known, ign


class FolderDataset(LabeledImages):
    """The folder layout (see the module docstring).

    Args:
        root: the dataset folder.
        label_map: a preset name, or a YAML path (default ``root/label_map.yaml``).
        skip_bad: skip (and count in :attr:`skipped`) bad pairs instead of raising.

    Raises:
        DatasetError: missing folders, an image without a label PNG (unless ``skip_bad``).
        ConfigError: no or a bad label map.
    """

    def __init__(self, root: str | os.PathLike, label_map: str | None = None, skip_bad: bool = False) -> None:
        root = Path(root)
        self.map, self.known, self.ignored = _folder_map(root, label_map)
        skipped: list[tuple[str, str]] = []
        pairs = pair_by_stem(list_images(root / "images"), root / "labels", skip_bad, skipped)
        produced = np.unique(self.map.table) if self.map.encoding == "rgb8" else np.unique(self.map.table[self.known])
        super().__init__(pairs, space_from_labels(f"folder:{root}", produced.tolist()), skip_bad, skipped)
        self.root = root

    def _convert(self, label_path: Path) -> np.ndarray:
        raw = read_label_png(label_path, color=self.map.encoding == "rgb8")
        keys = raw.astype(np.int64) if raw.ndim == 2 else pack_rgb(raw).astype(np.int64)
        present = np.unique(keys)
        unknown = present[~np.isin(present, self.known) & ~np.isin(present, self.ignored)]
        if unknown.size:
            k = int(unknown[0])
            what = f"id {k}" if raw.ndim == 2 else f"colour ({k >> 16},{(k >> 8) & 255},{k & 255})"
            raise DatasetError(f"{label_path}: {what} is not in the label map ({unknown.size} unknown in all)")
        out = self.map.apply(raw)
        if self.ignored.size:
            out = np.where(np.isin(keys, self.ignored), IGNORE, out).astype(np.uint8)
        return out


def _folder_map(root: Path, spec: str | None) -> tuple[LabelMap, np.ndarray, np.ndarray]:
    """``(label map, known keys, ignored keys)`` of a folder dataset."""
    if spec in PRESET_NAMES:
        lm = label_map(spec)
        if lm.encoding == "rgb8":
            return lm, lm.colors.astype(np.int64), np.zeros(0, np.int64)
        known, ignored = _PRESET_IDS[spec]
        return lm, np.asarray(list(known), np.int64), np.asarray(ignored, np.int64)
    path = Path(spec).expanduser() if spec else root / LABEL_MAP_FILE
    if file_kind(path) is None:  # a directory, FIFO or device is named as such by the reader
        raise ConfigError(f"{path}: no label map (a YAML file of upstream id -> label name, or one of the presets "
                          f"{list(PRESET_NAMES)})")
    where = f"label map {path}"
    doc, known, ignored = _known_from_doc(read_yaml_document(path, where), where)
    return label_map_from_dict(doc, str(path), where), known, ignored


__all__ = ["LABEL_MAP_FILE", "FolderDataset"]
