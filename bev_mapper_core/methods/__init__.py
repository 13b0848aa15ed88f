"""The methods: one package each, registered in one table, :data:`METHODS`.

A method package (``methods/<name>/``) holds everything of one method: its network and blocks
(``model.py``, ``blocks.py``), losses, weights file format (``weights.py``), the
:class:`~bev_mapper_core.mapper.Mapper` behind ``create_mapper`` (``mapper.py``) and the
training plug-in behind ``bev-train`` (``train.py``). What several methods share lives in
:mod:`bev_mapper_core.nn`. This table is the only place a method is registered: the mapper
registry (:func:`bev_mapper_core.mapper.available_methods`) and the training registry
(:func:`bev_mapper_core.training.method.train_methods`) read it. Entries are ``"module:Class"``
strings, imported on first use, so that listing the methods (or running IPM) imports no torch.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

#: The shipped weights files (``package_data``), named ``<method>_<rig>_<input>.safetensors``
#: (the default of that method, rig and input); a further ``_<variant>`` names a file that is
#: shipped but only used when passed as ``weights``.
WEIGHTS_DIR = Path(__file__).resolve().parent.parent / "weights"


@dataclass(frozen=True)
class MethodSpec:
    """One method's entry in :data:`METHODS`.

    Args:
        mapper: ``"module:Class"`` of its :class:`~bev_mapper_core.mapper.Mapper`; None for a
            method that makes no BEV map itself (the 2-D segmenter).
        trainer: ``"module:Class"`` of its ``TrainMethod`` plug-in; None for a training-free method.
        presets: node parameter files ``config/<name>.yaml`` made for this method, name ->
            changes to the rig preset's parameters (``rig``, ``grid``, ``input_kind``).
        weights: the shipped weights files (in :data:`WEIGHTS_DIR`) this method reads.
        summary: one line for listings.
    """

    mapper: str | None
    trainer: str | None
    presets: dict[str, dict[str, str]] = field(default_factory=dict)
    weights: tuple[str, ...] = ()
    summary: str = ""


_PKG = "bev_mapper_core.methods"

#: name -> :class:`MethodSpec`, the one registry of methods.
METHODS: MappingProxyType[str, MethodSpec] = MappingProxyType({
    "ipm": MethodSpec(
        mapper=f"{_PKG}.ipm.mapper:IpmMapper", trainer=None,
        summary="inverse perspective mapping of label images, with occlusion reasoning (training-free)",
    ),
    "segmenter": MethodSpec(
        mapper=None, trainer=f"{_PKG}.segmenter.train:SegmenterMethod",
        weights=("segmenter.safetensors", "segmenter_open.safetensors", "segmenter_w320.safetensors"),
        summary="per-camera 2-D segmenter: RGB image -> pixel labels (input of segipm and chained label models)",
    ),
    "segipm": MethodSpec(
        mapper=f"{_PKG}.segipm.mapper:SegIpmMapper", trainer=None,
        weights=("segmenter.safetensors", "segmenter_open.safetensors"),
        summary="two-stage RGB baseline: the 2-D segmenter, then IPM",
    ),
    "bimapper": MethodSpec(
        mapper=f"{_PKG}.bimapper.mapper:BiMapperMapper", trainer=f"{_PKG}.bimapper.train:BiMapperMethod",
        weights=("bimapper_surround6_labels.safetensors", "bimapper_cam2bev4_labels.safetensors",
                 "bimapper_front1_labels.safetensors", "bimapper_surround6_rgb_e2e.safetensors"),
        summary="Bi-Mapper (RA-L 2023): global-cross and local-self view streams, any rig",
    ),
    "s2g2": MethodSpec(
        mapper=f"{_PKG}.s2g2.mapper:S2G2Mapper", trainer=f"{_PKG}.s2g2.train:S2G2Method",
        presets={"front1_s2g2": {"rig": "front1", "input_kind": "rgb", "grid": "ahead"}},
        weights=("s2g2_front1_rgb.safetensors", "s2g2_front1_rgb_semi.safetensors"),
        summary="S2G2 (RA-L 2022): semi-supervised monocular BEV from one front camera",
    ),
    "focusbev": MethodSpec(
        mapper=f"{_PKG}.focusbev.mapper:FocusBEVMapper", trainer=f"{_PKG}.focusbev.train:FocusBEVMethod",
        presets={"front1_focusbev": {"rig": "front1", "input_kind": "rgb", "grid": "ahead"}},
        weights=("focusbev_front1_rgb.safetensors",),
        summary="FocusBEV: polar column-wise view transform, cycle self-calibration, ego-motion fusion",
    ),
})


def shipped_weights(method: str, rig_name: str, input_kind: str) -> Path:
    """Where the shipped weights of a method, rig and input kind live (the file may not exist)."""
    return WEIGHTS_DIR / f"{method}_{rig_name}_{input_kind}.safetensors"


def mapper_targets() -> dict[str, str]:
    """Name -> ``"module:Class"`` of every method that makes BEV maps."""
    return {name: spec.mapper for name, spec in METHODS.items() if spec.mapper}


def trainer_targets() -> dict[str, str]:
    """Name -> ``"module:Class"`` of every method with a training plug-in."""
    return {name: spec.trainer for name, spec in METHODS.items() if spec.trainer}


def method_presets() -> dict[str, dict[str, str]]:
    """``config/<name>.yaml`` name -> its changes to the rig's parameters, with ``method`` set."""
    return {name: {**over, "method": method} for method, spec in METHODS.items() for name, over in spec.presets.items()}


__all__ = ["METHODS", "WEIGHTS_DIR", "MethodSpec", "mapper_targets", "method_presets", "shipped_weights", "trainer_targets"]
