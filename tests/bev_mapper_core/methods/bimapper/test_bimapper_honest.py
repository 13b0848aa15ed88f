"""Issue #11 for Bi-Mapper: the visibility head, ``unknown_below``, the PON uncertainty loss and
per-class temperature scaling (tiny configs, CPU).
"""

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch
from model_helpers import GRID, RIG, TINY, batch, random_labels
from safetensors.torch import load_file, save_file

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods.bimapper.calibrate import fit_temperature
from bev_mapper_core.methods.bimapper.config import BiMapperConfig
from bev_mapper_core.methods.bimapper.losses import BiMapperLossConfig, bimapper_loss, uncertainty_loss
from bev_mapper_core.methods.bimapper.mapper import BiMapperMapper
from bev_mapper_core.methods.bimapper.model import BiMapper
from bev_mapper_core.methods.bimapper.train import init_from
from bev_mapper_core.methods.bimapper.weights import WeightsFile, save_weights
from bev_mapper_core.nn.weights import META_KEY, WeightsError

torch.set_num_threads(1)
VIS = replace(TINY, ipm_skip=True, visibility_head=True)


def _images(raw: torch.Tensor) -> dict:
    return {c.name: raw[0, n].numpy() for n, c in enumerate(RIG.cameras)}


def test_visibility_head_forward_backward():
    torch.manual_seed(0)
    model = BiMapper(VIS, RIG, GRID)
    b = batch(2)
    b["mask"][:, :, : GRID.shape[1] // 2] = False  # half the grid hidden
    out = model(b["images"])
    assert out["visibility_logits"].shape == (2, 1, *GRID.shape)
    loss, parts = bimapper_loss(out, b, 0, BiMapperLossConfig(visibility_weight=1.0, uncertainty_weight=0.001))
    assert parts["visibility"] > 0 and parts["uncertainty"] > 0
    loss.backward()
    assert model.decoder.vis_head[-1].weight.grad.abs().sum() > 0
    # the visibility loss alone reaches the shared decoder, not the class head
    model.zero_grad()
    torch.nn.functional.binary_cross_entropy_with_logits(
        model(b["images"])["visibility_logits"][:, 0], b["mask"].float()).backward()
    assert model.decoder.stem[0][0].weight.grad.abs().sum() > 0
    assert model.decoder.head[-1].weight.grad is None or not model.decoder.head[-1].weight.grad.any()
    # models without the head give no visibility logit, and refuse its loss
    plain = BiMapper(TINY, RIG, GRID)
    out = plain(b["images"])
    assert out["visibility_logits"] is None
    with pytest.raises(ConfigError, match="visibility head"):
        bimapper_loss(out, b, 0, BiMapperLossConfig(visibility_weight=1.0))


def test_visibility_loss_learns_the_mask():
    """A few steps on a fixed mask: the head's BCE falls well below its start (log 2 at zero init)."""
    torch.manual_seed(0)
    model = BiMapper(VIS, RIG, GRID)
    b = batch(2)
    b["mask"][:, :, : GRID.shape[1] // 3] = False
    opt = torch.optim.Adam(model.parameters(), 1e-2)
    first = None
    for _ in range(15):
        loss, parts = bimapper_loss(model(b["images"]), b, 0, BiMapperLossConfig(visibility_weight=1.0))
        first = first if first is not None else parts["visibility"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert parts["visibility"] < 0.5 * first


def _old_file(model: BiMapper, path) -> None:
    """Save ``model`` as a file written before the head existed: no new config keys."""
    save_weights(model, path)
    tensors = load_file(str(path))
    from safetensors import safe_open
    with safe_open(str(path), framework="pt") as f:
        meta = json.loads(f.metadata()[META_KEY])
    for k in ("visibility_head", "temperature"):
        del meta["config"][k]
    save_file(tensors, str(path), metadata={META_KEY: json.dumps(meta, sort_keys=True)})


def test_old_weights_load_and_behave_as_before(tmp_path):
    torch.manual_seed(3)
    model = BiMapper(replace(TINY, ipm_skip=True), RIG, GRID).eval()
    path = tmp_path / "old.safetensors"
    _old_file(model, path)
    wf = WeightsFile.open(path)
    assert wf.config.visibility_head is False and wf.config.temperature is None
    raw = random_labels(4)
    with torch.no_grad():
        exp = torch.sigmoid(model(raw)["logits"][0]).numpy()
        frustum = model.known()[0].numpy()
    for ub in (0.0, 0.5, 0.99):  # no head: unknown_below changes nothing
        pred = BiMapperMapper(RIG, GRID, MapperConfig(
            backend="torch", weights=str(path), unknown_below=ub, ipm_occlusion=False)).map(_images(raw))
        np.testing.assert_array_equal(pred.probs, exp)
        np.testing.assert_array_equal(pred.known, frustum)


def test_shipped_weights_have_no_head_and_load():
    wf = WeightsFile.open(BiMapperMapper.weights_path(MapperConfig(), "surround6"))
    wf.validate()
    assert isinstance(wf.config.visibility_head, bool)


def test_unknown_below_makes_unobservable_cells_unknown(tmp_path):
    """Forcing the head's bias: very negative -> every cell unknown; very positive -> the frustum;
    0 switches the head off."""
    torch.manual_seed(4)
    model = BiMapper(VIS, RIG, GRID).eval()
    raw = random_labels(5)
    frustum = model.known()[0].numpy()
    assert frustum.any() and not frustum.all()
    results = {}
    for bias in (-50.0, 50.0):
        with torch.no_grad():
            model.decoder.vis_head[-1].weight.zero_()
            model.decoder.vis_head[-1].bias.fill_(bias)
        path = tmp_path / f"b{bias}.safetensors"
        save_weights(model, path)
        for ub in (0.0, 0.5):
            config = MapperConfig(backend="torch", weights=str(path), unknown_below=ub, ipm_occlusion=False)
            results[bias, ub] = BiMapperMapper(RIG, GRID, config).map(_images(raw))
    assert not results[-50.0, 0.5].known.any()
    np.testing.assert_array_equal(results[50.0, 0.5].known, frustum)
    np.testing.assert_array_equal(results[-50.0, 0.0].known, frustum)
    np.testing.assert_array_equal(results[-50.0, 0.5].probs, results[-50.0, 0.0].probs)  # only known changes
    # a head that varies over the grid
    with torch.no_grad():
        model.decoder.vis_head[-1].weight.zero_()
        model.decoder.vis_head[-1].weight[0, 0] = 1.0  # p_visible from the first hidden channel
        model.decoder.vis_head[-1].bias.fill_(-0.5)
    path = tmp_path / "half.safetensors"
    save_weights(model, path)
    mapper = BiMapperMapper(RIG, GRID, MapperConfig(backend="torch", weights=str(path), unknown_below=0.5, ipm_occlusion=False))
    with torch.no_grad():
        p_vis = torch.sigmoid(mapper.model(raw)["visibility_logits"][0, 0]).numpy()
    pred = mapper.map(_images(raw))
    np.testing.assert_array_equal(pred.known, frustum & (p_vis >= 0.5))
    with pytest.raises(ConfigError, match="unknown_below"):
        MapperConfig(unknown_below=1.5)


def test_uncertainty_loss_hand_made():
    hidden = torch.tensor([[[True, False]]])  # (1, 1, 2)
    # p = 0.5 on the hidden cell: no loss, whatever the visible cell says
    z = torch.tensor([[[[0.0, 30.0]]]])  # (1, 1, 1, 2)
    assert uncertainty_loss(z, hidden).item() == pytest.approx(0.0, abs=1e-7)
    # certain on the hidden cell: log 2, the KL of a sure Bernoulli to the uniform one
    z = torch.tensor([[[[30.0, 0.0]]]])
    assert uncertainty_loss(z, hidden).item() == pytest.approx(math.log(2), abs=1e-6)
    # p = sigmoid(1): log 2 - H(p)
    p = 1 / (1 + math.exp(-1))
    h = -p * math.log(p) - (1 - p) * math.log(1 - p)
    z = torch.tensor([[[[1.0, 5.0]]]])
    assert uncertainty_loss(z, hidden).item() == pytest.approx(math.log(2) - h, abs=1e-6)
    # gradient pushes the hidden logit towards 0
    z = torch.tensor([[[[2.0, 5.0]]]], requires_grad=True)
    uncertainty_loss(z, hidden).backward()
    assert z.grad[0, 0, 0, 0] > 0 and z.grad[0, 0, 0, 1] == 0
    assert uncertainty_loss(z, torch.zeros(1, 1, 2, dtype=torch.bool)).item() == 0.0


def _ece(p: np.ndarray, y: np.ndarray, bins: int = 10) -> float:
    idx = np.minimum((p * bins).astype(int), bins - 1)
    return sum(abs(p[idx == b].mean() - y[idx == b].mean()) * (idx == b).mean() for b in range(bins) if (idx == b).any())


def test_temperature_scaling_lowers_nll_and_ece():
    """Overconfident logits (true logit x 4) on class 0 and underconfident (x 0.25) on class 1:
    the fit recovers T ~ 4 and ~ 0.25, and lowers NLL and ECE of both."""
    g = torch.Generator().manual_seed(0)
    true = torch.randn(20000, 2, generator=g) * 2.0
    y = (torch.rand(20000, 2, generator=g) < torch.sigmoid(true)).float()
    z = true * torch.tensor([4.0, 0.25])
    t = fit_temperature(z, y)
    assert t[0] == pytest.approx(4.0, rel=0.1) and t[1] == pytest.approx(0.25, rel=0.1)
    bce = torch.nn.functional.binary_cross_entropy_with_logits
    for k in range(2):
        assert bce(z[:, k] / t[k], y[:, k]) < bce(z[:, k], y[:, k]) - 0.01
        before = _ece(torch.sigmoid(z[:, k]).numpy(), y[:, k].numpy())
        after = _ece(torch.sigmoid(z[:, k] / t[k]).numpy(), y[:, k].numpy())
        assert after < 0.5 * before


def test_temperature_is_stored_and_applied(tmp_path):
    torch.manual_seed(5)
    model = BiMapper(replace(TINY, ipm_skip=True), RIG, GRID).eval()
    raw = random_labels(6)
    with torch.no_grad():
        logits = model(raw)["logits"][0]
    model.config = replace(model.config, temperature=(2.0, 1.0, 0.5))
    path = tmp_path / "t.safetensors"
    save_weights(model, path)
    assert WeightsFile.open(path).config.temperature == (2.0, 1.0, 0.5)
    pred = BiMapperMapper(RIG, GRID, MapperConfig(backend="torch", weights=str(path))).map(_images(raw))
    exp = torch.sigmoid(logits / torch.tensor([2.0, 1.0, 0.5]).view(-1, 1, 1)).numpy()
    np.testing.assert_allclose(pred.probs, exp, atol=1e-6)
    with pytest.raises(ConfigError, match="temperature"):
        BiMapperConfig(classes=TINY.classes, temperature=(1.0, 2.0))


def test_init_from_old_file_fine_tunes_with_a_fresh_head(tmp_path):
    torch.manual_seed(6)
    old = BiMapper(replace(TINY, ipm_skip=True), RIG, GRID).eval()
    path = tmp_path / "old.safetensors"
    _old_file(old, path)
    new = BiMapper(VIS, RIG, GRID).eval()
    fresh = init_from(new, str(path))
    assert fresh and all(k.startswith("decoder.vis_head.") for k in fresh)
    raw = random_labels(7)
    with torch.no_grad():
        assert torch.equal(new(raw)["logits"], old(raw)["logits"])
    other = BiMapper(replace(VIS, decoder_channels=8), RIG, GRID)
    with pytest.raises(WeightsError):
        init_from(other, str(path))


@pytest.mark.slow
def test_the_unknown_cells_do_not_depend_on_the_layers_asked_for():
    """The line of sight and the seen-object rule (issue #39) follow the classes the model maps,
    not the subset of layers published: a node publishing three layers and a replay of all seven
    mark the same cells unknown (a subset without pedestrians once gave 19 other cells)."""
    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.mapper import create_mapper
    from bev_mapper_core.synth import generate_drive
    from bev_mapper_core.synth.config import SynthConfig

    rig, grid = preset_rig("surround6"), BevGrid()
    (frame,) = generate_drive(rig, grid, SynthConfig(frames=1, seed=12))
    images = {n: c.labels for n, c in frame.cameras.items()}
    known = [create_mapper(rig, grid, MapperConfig(threads=1, backend="torch", classes=classes)).map(images).known
             for classes in (None, ("drivable", "ped_crossing", "vehicle"), ("drivable",))]
    assert not known[0].all() and known[0].any()
    assert np.array_equal(known[0], known[1]) and np.array_equal(known[0], known[2])
