"""S2G2 with a frozen encoder trains on cached features (issue #26): the cached path computes the
same losses as running the frozen encoder every step, and trains only what follows it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from model_helpers import step_losses

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.methods.s2g2.model import S2G2Config, input_size
from bev_mapper_core.methods.s2g2.train import S2G2Training
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import FrameSet
from bev_mapper_core.training.method import method_class
from bev_mapper_core.training.sources import TrainData

torch.set_num_threads(1)
RIG = preset_rig("front1")
GRID = BevGrid(0.0, 16.0, -8.0, 8.0, 0.5)
CLASSES = ("drivable", "vehicle")
RUN = dict(method="s2g2", rig="front1", input="rgb", classes=",".join(CLASSES), batch=2, lr=3e-3, seed=3,
           input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3, bev_downsample=4,
           decoder_channels=8, consistency_ramp_steps=4, grid=[0.0, 16.0, -8.0, 8.0, 0.5], encoder_init="none",
           optimizer="adam", progress=False, augment=False, frozen_encoder=True)


def _data(seed: int = 0) -> TrainData:
    h, w = input_size(S2G2Config(input_width=32), RIG)
    rng = np.random.default_rng(seed)

    def frames(n):
        return FrameSet(np.zeros((n, 1, h, w), np.uint8), rng.random((n, len(CLASSES), *GRID.shape)) > 0.6,
                        np.ones((n, *GRID.shape), bool), camera_names=RIG.names,
                        rgb=rng.integers(0, 256, (n, 1, h, w, 3), dtype=np.uint8))

    return TrainData(frames(6), frames(2), frames(4))


def _losses(copies: int, steps: int = 6, **over) -> tuple[list[float], object]:
    cfg = TrainConfig.from_dict({**RUN, "feature_copies": copies, **over})
    torch.manual_seed(0)
    m = method_class("s2g2")(cfg, RIG, cfg.grid)
    data = _data()
    m.prepare(data, lambda _: None)
    return step_losses(m, data, cfg, steps, epochs=3), m


def test_cached_features_give_the_uncached_losses_step_for_step():
    uncached, m0 = _losses(0)
    cached, m1 = _losses(1)
    assert len(cached) == len(uncached) == 6
    np.testing.assert_allclose(cached, uncached, rtol=1e-5, atol=1e-6)
    assert m1._cache["train"].shape[:2] == (1, 6) and m1._cache["unlabeled"].shape[:2] == (1, 4)
    # the frozen encoder never moved (weights and BatchNorm statistics); the rest did
    for a, b in zip(m1.model.encoder.state_dict().values(), m0.model.encoder.state_dict().values()):
        torch.testing.assert_close(a, b)
    torch.manual_seed(0)
    fresh = method_class("s2g2")(TrainConfig.from_dict({**RUN}), RIG, GRID)
    for k, v in fresh.model.encoder.state_dict().items():
        torch.testing.assert_close(m1.model.encoder.state_dict()[k], v)
    moved = [k for k, v in fresh.model.to_bev.state_dict().items()
             if v.is_floating_point() and not torch.equal(v, m1.model.to_bev.state_dict()[k])]
    assert moved
    assert all(not p.requires_grad for p in m1.model.encoder.parameters())
    assert not any(p is q for p in m1.trainable_parameters() for q in m1.model.encoder.parameters())


def test_augmented_copies_are_cached_and_drawn():
    _, m = _losses(3, steps=2, augment=True)
    cache = m._cache["train"]
    assert cache.shape[0] == 3 and not torch.allclose(cache[0], cache[1]) and not torch.allclose(cache[1], cache[2])


def test_feature_cache_settings_are_checked():
    with pytest.raises(ConfigError, match="needs frozen_encoder"):
        S2G2Training(feature_copies=1)
    with pytest.raises(ConfigError, match="needs augment"):
        S2G2Training(frozen_encoder=True, feature_copies=2, augment=False)
    with pytest.raises(ConfigError, match="0..16"):
        S2G2Training(frozen_encoder=True, feature_copies=99)
    with pytest.raises(ConfigError, match="frozen encoder trains from no loss"):
        S2G2Training(frozen_encoder=True, cycle_into_encoder=True)
    assert replace(S2G2Training(), frozen_encoder=True, feature_copies=4).feature_copies == 4
