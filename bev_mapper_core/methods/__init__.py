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
        inputs: the input kinds (``labels``, ``rgb``) it maps; a learned method, those it can be
            trained for.
        chains: a learned method that maps RGB input through the shipped 2-D segmenter in front
            of its label weights (when it has no RGB weights).
        monocular: it maps one camera only.
        train_flags: what ``bev-train --method NAME`` needs beyond ``--rig`` and ``--input``.
        any_rig_flags: the ``bev-train`` flags that train this method's weights for any rig
            (``--rig random`` and a rig-free architecture); empty: it trains for one rig only.
    """

    mapper: str | None
    trainer: str | None
    presets: dict[str, dict[str, str]] = field(default_factory=dict)
    weights: tuple[str, ...] = ()
    summary: str = ""
    inputs: tuple[str, ...] = ("labels", "rgb")
    chains: bool = False
    monocular: bool = False
    train_flags: str = ""
    any_rig_flags: str = ""


#: The rig name of weights that map any rig (``<method>_any_<input>.safetensors``).
ANY_RIG = "any"

_PKG = "bev_mapper_core.methods"

#: name -> :class:`MethodSpec`, the one registry of methods.
METHODS: MappingProxyType[str, MethodSpec] = MappingProxyType({
    "ipm": MethodSpec(
        mapper=f"{_PKG}.ipm.mapper:IpmMapper", trainer=None, inputs=("labels",),
        summary="inverse perspective mapping of label images, with occlusion reasoning (training-free)",
    ),
    "segmenter": MethodSpec(
        mapper=None, trainer=f"{_PKG}.segmenter.train:SegmenterMethod",
        weights=("segmenter.safetensors", "segmenter_open.safetensors", "segmenter_w320.safetensors"),
        summary="per-camera 2-D segmenter: RGB image -> pixel labels (input of segipm and chained label models)",
    ),
    "segipm": MethodSpec(
        mapper=f"{_PKG}.segipm.mapper:SegIpmMapper", trainer=None, inputs=("rgb",),
        weights=("segmenter.safetensors", "segmenter_open.safetensors"),
        summary="two-stage RGB baseline: the 2-D segmenter, then IPM",
    ),
    "bimapper": MethodSpec(
        mapper=f"{_PKG}.bimapper.mapper:BiMapperMapper", trainer=f"{_PKG}.bimapper.train:BiMapperMethod",
        weights=("bimapper_surround6_labels.safetensors", "bimapper_cam2bev4_labels.safetensors",
                 "bimapper_front1_labels.safetensors", "bimapper_surround6_rgb_e2e.safetensors",
                 "bimapper_any_labels.safetensors"),
        summary="Bi-Mapper (RA-L 2023): global-cross and local-self view streams, any rig",
        chains=True, any_rig_flags="--rig random --streams lv --ipm-skip",
    ),
    "s2g2": MethodSpec(
        mapper=f"{_PKG}.s2g2.mapper:S2G2Mapper", trainer=f"{_PKG}.s2g2.train:S2G2Method",
        presets={"front1_s2g2": {"rig": "front1", "input_kind": "rgb", "grid": "ahead"}},
        weights=("s2g2_front1_rgb.safetensors", "s2g2_front1_rgb_semi.safetensors"),
        summary="S2G2 (RA-L 2022): semi-supervised monocular BEV from one front camera",
        monocular=True, train_flags="--grid ahead --unlabeled-drives N",
    ),
    "focusbev": MethodSpec(
        mapper=f"{_PKG}.focusbev.mapper:FocusBEVMapper", trainer=f"{_PKG}.focusbev.train:FocusBEVMethod",
        presets={"front1_focusbev": {"rig": "front1", "input_kind": "rgb", "grid": "ahead"}},
        weights=("focusbev_front1_rgb.safetensors",),
        summary="FocusBEV: polar column-wise view transform, cycle self-calibration, ego-motion fusion",
        monocular=True, train_flags="--grid ahead",
    ),
})


def shipped_weights(method: str, rig_name: str, input_kind: str) -> Path:
    """Where the shipped weights of a method, rig and input kind live (the file may not exist)."""
    return WEIGHTS_DIR / f"{method}_{rig_name}_{input_kind}.safetensors"


#: How the messages name each input kind.
INPUT_WORDS = {"labels": "label images", "rgb": "RGB images"}


def _shipped(spec: MethodSpec) -> bool:
    """Whether every file a training-free method reads is shipped (segipm: the segmenter)."""
    return all((WEIGHTS_DIR / w).is_file() for w in spec.weights)


def runnable_methods(input_kind: str, rig_name: str, cameras: int | None = None,
                     exclude: tuple[str, ...] = ()) -> tuple[str, ...]:
    """The methods of :data:`METHODS` that map ``input_kind`` images of rig ``rig_name`` with what
    is shipped, each as ``'name (why)'``: the training-free ones that take that input (any
    calibrated rig), the learned ones whose shipped weights are for that rig and input, and for
    RGB a chaining method whose label weights for the rig are shipped (the segmenter in front).
    ``cameras``: the rig's number of cameras, when known (a monocular method needs one);
    ``exclude``: methods not to name (the one refusing).
    """
    words = INPUT_WORDS[input_kind]
    out = []
    for name, spec in METHODS.items():
        if spec.mapper is None or name in exclude or input_kind not in spec.inputs:
            continue
        if spec.monocular and cameras not in (None, 1):
            continue
        if spec.trainer is None:
            if _shipped(spec):
                out.append(f"{name} ({words}, any calibrated rig)")
        elif shipped_weights(name, rig_name, input_kind).is_file():
            out.append(f"{name} (its shipped weights for rig {rig_name!r}, {words})")
        elif (spec.chains and input_kind == "rgb" and shipped_weights(name, rig_name, "labels").is_file()
              and _shipped(METHODS["segmenter"])):
            out.append(f"{name} (RGB through the shipped segmenter, then its shipped label weights "
                       f"for rig {rig_name!r})")
        elif shipped_weights(name, ANY_RIG, input_kind).is_file() and not spec.monocular:
            out.append(f"{name} (its shipped weights for any rig, {words})")
        elif (spec.chains and input_kind == "rgb" and shipped_weights(name, ANY_RIG, "labels").is_file()
              and _shipped(METHODS["segmenter"])):
            out.append(f"{name} (RGB through the shipped segmenter, then its shipped label weights for any rig)")
    return tuple(out)


def train_command(method: str, rig_name: str, input_kind: str) -> str:
    """The ``bev-train`` command that trains ``method``'s weights for a rig and input, with what
    it says when ``rig_name`` is no preset (``bev-train`` trains the preset rigs).
    """
    from ..geometry.rig import PRESETS  # noqa: PLC0415 - only the messages need it

    spec = METHODS[method]
    flags = spec.train_flags
    if rig_name not in PRESETS and spec.any_rig_flags:  # weights for every rig, this one included
        return (f"bev-train --method {method} {spec.any_rig_flags} --input {input_kind}"
                f"{' ' + flags if flags else ''} --out runs/NAME (weights for any rig; rig {rig_name!r} is no preset)")
    rig = rig_name if rig_name in PRESETS else "PRESET"
    cmd = f"bev-train --method {method} --rig {rig} --input {input_kind}{' ' + flags if flags else ''} --out runs/NAME"
    if rig_name not in PRESETS:
        cmd += f" (bev-train trains the preset rigs {', '.join(PRESETS)}; rig {rig_name!r} is none of them)"
    return cmd


def alternatives(method: str, input_kind: str, rig_name: str, cameras: int | None = None) -> str:
    """What a refusal of ``method`` on ``input_kind`` images of rig ``rig_name`` adds: the methods
    that run there as shipped (:func:`runnable_methods`), and for a learned method how to get
    its weights (:func:`train_command`; not for a monocular method on a rig of several cameras).
    """
    runs = runnable_methods(input_kind, rig_name, cameras, exclude=(method,))
    words = INPUT_WORDS[input_kind]
    text = (f"methods that run on {words} of rig {rig_name!r} as shipped: {', '.join(runs)}" if runs
            else f"no other method runs on {words} of rig {rig_name!r} as shipped")
    spec = METHODS[method]
    if spec.trainer is not None and input_kind in spec.inputs and not (spec.monocular and cameras not in (None, 1)):
        text += f"; to train {method} weights: {train_command(method, rig_name, input_kind)}, then pass weights=<file>"
    return text


def mapper_targets() -> dict[str, str]:
    """Name -> ``"module:Class"`` of every method that makes BEV maps."""
    return {name: spec.mapper for name, spec in METHODS.items() if spec.mapper}


def trainer_targets() -> dict[str, str]:
    """Name -> ``"module:Class"`` of every method with a training plug-in."""
    return {name: spec.trainer for name, spec in METHODS.items() if spec.trainer}


def method_presets() -> dict[str, dict[str, str]]:
    """``config/<name>.yaml`` name -> its changes to the rig's parameters, with ``method`` set."""
    return {name: {**over, "method": method} for method, spec in METHODS.items() for name, over in spec.presets.items()}


__all__ = ["ANY_RIG", "INPUT_WORDS", "METHODS", "WEIGHTS_DIR", "MethodSpec", "alternatives", "mapper_targets", "method_presets",
           "runnable_methods", "shipped_weights", "train_command", "trainer_targets"]
