"""Learned BEV methods (PyTorch). Importing this package imports torch; the rest of
``bev_mapper_core`` does not.

Bi-Mapper:

* :class:`BiMapperConfig`, :class:`BiMapper` (``bimapper.py``; streams in ``gv.py``, ``lv.py``,
  ``unet.py``; calibration tables in ``geometry.py``; encoder in ``efficientnet.py``),
* :func:`bimapper_loss`, :class:`BiMapperLossConfig`, :func:`mutual_teachers` (``losses.py``),
* :func:`save_weights`, :func:`load_bimapper`, :func:`load_state`, :class:`WeightsFile` (a file's header
  read once), :class:`WeightsError` (``weights.py``),
* the Mapper adapter ``bev_mapper_core.models.bimapper_mapper:BiMapperMapper``.

S2G2 (issue #13; import the modules themselves): ``s2g2.py`` (:class:`~.s2g2.S2G2Config`,
:class:`~.s2g2.S2G2`), ``s2g2_blocks.py`` (view transform, cross-view and inter-view attention),
``s2g2_losses.py`` (Eq. 1-6, ``ema_update``, ``sigmoid_rampup``), ``s2g2_weights.py``
(safetensors ``bev_mapper.s2g2``), the Mapper adapter ``s2g2_mapper:S2G2Mapper``. Inputs of
both: ``inputs.py`` (:func:`~.inputs.preprocess_images`).
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
