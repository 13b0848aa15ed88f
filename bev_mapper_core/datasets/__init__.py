"""Labelled real camera images for training and scoring the RGB networks.

Two layouts, both read without any download (a path is given):

* :class:`CamVid`: the SegNet tutorial's CamVid (``train/``, ``trainannot/``, ``val/``,
  ``valannot/``, ``test/``, ``testannot/``; 11 classes + Unlabelled), in its own classes
  (:data:`~bev_mapper_core.labels.spaces.CAMVID`).
* :class:`FolderDataset`: a team's own frames (``images/``, ``labels/`` PNGs and a label-map
  YAML in the :mod:`~bev_mapper_core.labels.label_maps` scheme), in the package's fine labels.

:func:`open_dataset` resolves ``camvid:DIR`` / ``folder:DIR[:PRESET]`` specs (a new layout: a
reader module here and one line in :data:`KINDS`).
"""

from ..errors import ConfigError
from ..labels.label_maps import PRESET_NAMES
from .base import DatasetError, LabeledImages, Sample
from .camvid import CAMVID_IGNORE_ID, CamVid
from .folder import FolderDataset

#: spec kind -> what it reads
KINDS = {"camvid": "camvid:DIR (the SegNet tutorial's CamVid layout)",
         "folder": "folder:DIR[:PRESET] (images/, labels/, a label map)"}


def open_dataset(spec: str, split: str = "train", skip_bad: bool = False) -> LabeledImages:
    """A reader for ``camvid:DIR`` (that split) or ``folder:DIR`` (its own label map;
    ``folder:DIR:PRESET`` names a preset instead; a folder has no splits).

    Raises:
        ConfigError: an unknown kind.
        DatasetError: see the readers.
    """
    kind, _, rest = spec.partition(":")
    if kind == "camvid" and rest:
        return CamVid(rest, split, skip_bad)
    if kind == "folder" and rest:
        path, preset = rest.rsplit(":", 1) if rest.rsplit(":", 1)[-1] in PRESET_NAMES else (rest, None)
        return FolderDataset(path, preset, skip_bad)
    raise ConfigError(f"real data must be one of {list(KINDS.values())}, got {spec!r}")


__all__ = ["CAMVID_IGNORE_ID", "KINDS", "CamVid", "DatasetError", "FolderDataset", "LabeledImages", "Sample",
           "open_dataset"]
