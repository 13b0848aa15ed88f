"""Issue #24: S2G2's photometric augmentation of its training images (``augment``): what the
model sees, what the loss reads, --no-augment equal to the run before augmentation, exact resume,
the flag. Tiny models on in-memory frames, CPU, one thread."""

from __future__ import annotations

import pytest
import torch
from augment_helpers import Spy, flag_check, method_and_batch, no_augment_check, resume_check, same, snapshot

from bev_mapper_core.methods.s2g2 import train as s2g2_train
from bev_mapper_core.methods.s2g2.train import S2G2Training

torch.set_num_threads(1)


def test_augment_is_a_flag_and_a_yaml_key(tmp_path):
    flag_check("s2g2", S2G2Training, tmp_path)


@pytest.mark.parametrize("augment", [True, False])
def test_labeled_and_unlabeled_images_are_augmented_and_the_targets_are_not(monkeypatch, tmp_path, augment):
    m, batch = method_and_batch("s2g2", tmp_path, augment=augment)
    before = snapshot(batch)
    spy = Spy(monkeypatch, s2g2_train, "s2g2_loss", 2, m.model)
    m.loss(batch, 0, 5)
    assert same(batch, before)  # the batch itself is left alone
    assert len(spy.images) == 2 and len(spy.targets) == 1  # labeled, then unlabeled frames (their own pass)
    assert torch.equal(spy.targets[0], batch["labeled"]["target"])
    for seen, part in zip(spy.images, ("labeled", "unlabeled")):
        raw = batch[part]["rgb"]  # (B, 1, h, w, 3) uint8
        if augment:
            assert seen.shape == raw.shape and seen.dtype == torch.float32
            assert 0 <= seen.min() and seen.max() <= 255
            assert (seen - raw.float()).abs().mean() > 1.0  # not the raw images
        else:
            assert seen.dtype == torch.uint8 and torch.equal(seen, raw)  # exactly what the model saw before


def test_label_input_ignores_augment(monkeypatch, tmp_path):
    m, batch = method_and_batch("s2g2", tmp_path, input="labels", augment=True)
    spy = Spy(monkeypatch, s2g2_train, "s2g2_loss", 2, m.model)
    m.loss(batch, 0, 5)
    assert torch.equal(spy.images[0], batch["labeled"]["images"])
    assert torch.equal(spy.images[1], batch["unlabeled"]["images"])


@pytest.mark.slow
def test_no_augment_is_the_run_before_augmentation(tmp_path):
    no_augment_check("s2g2", tmp_path)


@pytest.mark.slow
def test_resume_with_augmentation_equals_an_uninterrupted_run(tmp_path):
    resume_check("s2g2", tmp_path)
