"""Labelled real camera images for training and scoring the RGB networks.

Two layouts, both read without any download (a path is given):

* :class:`CamVid`: the SegNet tutorial's CamVid (``train/``, ``trainannot/``, ``val/``,
  ``valannot/``, ``test/``, ``testannot/``; 11 classes + Unlabelled), in its own classes
  (:data:`~bev_mapper_core.nn.label_space.CAMVID`).
* :class:`FolderDataset`: a team's own frames (``images/``, ``labels/`` PNGs and a label-map
  YAML in the :mod:`~bev_mapper_core.label_maps` scheme), in the package's fine labels.

:func:`open_dataset` resolves ``camvid:DIR`` / ``folder:DIR`` specs.
"""

from .base import DatasetError, LabeledImages, Sample
from .camvid import CAMVID_IGNORE_ID, CamVid
from .folder import FolderDataset, open_dataset

__all__ = ["CAMVID_IGNORE_ID", "CamVid", "DatasetError", "FolderDataset", "LabeledImages", "Sample", "open_dataset"]
