"""Issue #24: FocusBEV's photometric augmentation of its training windows (``augment``, one draw
per window): what the model sees, what the loss reads, --no-augment equal to the run before
augmentation, exact resume, the flag. Tiny models on in-memory drives, CPU, one thread."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from augment_helpers import (
    Spy,
    flag_check,
    method_and_batch,
    no_augment_check,
    resume_check,
    same,
    snapshot,
    tiny_data,
)

from bev_mapper_core.methods.focusbev import train as focusbev_train
from bev_mapper_core.methods.focusbev.train import FocusBEVTraining
from bev_mapper_core.nn.augment import AugmentConfig, step_augment

torch.set_num_threads(1)


def test_augment_is_a_flag_and_a_yaml_key(tmp_path):
    flag_check("focusbev", FocusBEVTraining, tmp_path, ("--input", "rgb"))


@pytest.mark.parametrize("augment", [True, False])
def test_window_images_are_augmented_and_the_targets_are_not(monkeypatch, tmp_path, augment):
    m, batch = method_and_batch("focusbev", tmp_path, augment=augment)
    before = snapshot(batch)
    spy = Spy(monkeypatch, focusbev_train, "focusbev_loss", 1, m.model)
    m.loss(batch, 0, 3)
    assert same(batch, before)
    assert torch.equal(spy.targets[0], batch["target"])
    raw = batch["rgb"]  # (B, T, 1, h, w, 3) uint8
    seen = spy.images[0]  # (B*T, 1, h, w, 3): every frame of the windows, history included
    if augment:
        assert seen.dtype == torch.float32 and (seen - raw.flatten(0, 1).float()).abs().mean() > 1.0
    else:
        assert seen.dtype == torch.uint8 and torch.equal(seen, raw.flatten(0, 1))


def test_the_frames_of_a_window_share_one_draw(monkeypatch, tmp_path):
    """Without sensor noise (the one per-frame draw), a window of two equal frames (a drive's first
    frame: its history is the frame itself) stays two equal frames; the windows differ."""
    m, _ = method_and_batch("focusbev", tmp_path)
    train_set = tiny_data(m.cfg)[0]  # drives of 3 frames
    train_set.window = 2
    batch = train_set.batch(np.array([0, 3]))  # the first frames of drives 0 and 1: windows [0, 0] and [3, 3]
    assert torch.equal(batch["rgb"][:, 0], batch["rgb"][:, 1])
    monkeypatch.setattr(focusbev_train, "step_augment",
                        lambda seed, step, dev: step_augment(seed, step, dev, AugmentConfig(p_noise=0.0)))
    spy = Spy(monkeypatch, focusbev_train, "focusbev_loss", 1, m.model)
    m.loss(batch, 0, 3)
    seen = spy.images[0].view(2, 2, *spy.images[0].shape[1:])  # (B*T, ...) -> (B, T, ...)
    assert torch.equal(seen[:, 0], seen[:, 1])
    gain = seen.mean(dim=(1, 2, 3, 4, 5)) / batch["rgb"].float().mean(dim=(1, 2, 3, 4, 5))
    assert abs(gain[0] - gain[1]) > 1e-3  # each window its own draw


def test_label_input_ignores_augment(monkeypatch, tmp_path):
    m, batch = method_and_batch("focusbev", tmp_path, input="labels", augment=True)
    spy = Spy(monkeypatch, focusbev_train, "focusbev_loss", 1, m.model)
    m.loss(batch, 0, 3)
    assert torch.equal(spy.images[0], batch["images"].flatten(0, 1))


@pytest.mark.slow
def test_no_augment_is_the_run_before_augmentation(tmp_path):
    no_augment_check("focusbev", tmp_path)


@pytest.mark.slow
def test_resume_with_augmentation_equals_an_uninterrupted_run(tmp_path):
    resume_check("focusbev", tmp_path)
