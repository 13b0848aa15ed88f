"""Learned BEV methods (PyTorch). Importing this package imports torch; the rest of
``bev_mapper_core`` does not.

Bi-Mapper:

* :class:`BiMapperConfig`, :class:`BiMapper` (``bimapper.py``; streams in ``gv.py``, ``lv.py``,
  ``unet.py``; calibration tables in ``geometry.py``; encoder in ``efficientnet.py``),
* :func:`bimapper_loss`, :class:`BiMapperLossConfig`, :func:`mutual_teachers` (``losses.py``),
* :func:`save_weights`, :func:`load_bimapper`, :func:`load_state`, :class:`WeightsFile` (a file's header
  read once), :class:`WeightsError` (``weights.py``),
* the Mapper adapter ``bev_mapper_core.models.bimapper_mapper:BiMapperMapper``.
"""

from .bimapper import BiMapper, BiMapperConfig
from .efficientnet import EfficientNet, EfficientNetConfig, count_parameters
from .losses import BiMapperLossConfig, bimapper_loss, mutual_teachers
from .weights import WeightsError, WeightsFile, load_bimapper, load_state, read_metadata, save_weights

__all__ = [
    "BiMapper",
    "BiMapperConfig",
    "BiMapperLossConfig",
    "EfficientNet",
    "EfficientNetConfig",
    "WeightsError",
    "WeightsFile",
    "bimapper_loss",
    "count_parameters",
    "load_bimapper",
    "load_state",
    "mutual_teachers",
    "read_metadata",
    "save_weights",
]
