"""Issue #24: RGB Bi-Mapper's photometric augmentation of its training camera images
(``augment``; label input unaffected): what the model sees, what the loss reads, --no-augment
equal to the run before augmentation, exact resume, the flag. Tiny models, CPU, one thread."""

from __future__ import annotations

import pytest
import torch
from augment_helpers import Spy, flag_check, method_and_batch, no_augment_check, resume_check, same, snapshot

from bev_mapper_core.methods.bimapper import train as bimapper_train
from bev_mapper_core.methods.bimapper.train import BiMapperTraining

torch.set_num_threads(1)


def test_augment_is_a_flag_and_a_yaml_key(tmp_path):
    flag_check("bimapper", BiMapperTraining, tmp_path, ("--input", "rgb"))


@pytest.mark.parametrize("augment", [True, False])
def test_camera_images_are_augmented_each_its_own_and_the_targets_are_not(monkeypatch, tmp_path, augment):
    m, batch = method_and_batch("bimapper", tmp_path, rig="surround6", augment=augment)
    before = snapshot(batch)
    spy = Spy(monkeypatch, bimapper_train, "bimapper_loss", 1, m.model, at="forward")
    m.loss(batch, 0, 2)
    assert same(batch, before)
    assert torch.equal(spy.targets[0], batch["target"])
    raw, seen = batch["rgb"], spy.images[0]  # (B, 6, h, w, 3)
    if augment:
        assert seen.shape == raw.shape and seen.dtype == torch.float32
        gain = seen.mean(dim=(2, 3, 4)) / raw.float().mean(dim=(2, 3, 4))  # (B, 6)
        assert (gain - 1).abs().min() > 1e-3 and gain.std() > 0.01  # every image changed, not all alike
    else:
        assert seen.dtype == torch.uint8 and torch.equal(seen, raw)


def test_label_input_ignores_augment(monkeypatch, tmp_path):
    m, batch = method_and_batch("bimapper", tmp_path, input="labels", augment=True)
    spy = Spy(monkeypatch, bimapper_train, "bimapper_loss", 1, m.model, at="forward")
    m.loss(batch, 0, 2)
    assert torch.equal(spy.images[0], batch["images"])
    assert "images augmented" not in m.schedule() and "images augmented" in method_and_batch(
        "bimapper", tmp_path)[0].schedule()


@pytest.mark.slow
def test_no_augment_is_the_run_before_augmentation(tmp_path):
    no_augment_check("bimapper", tmp_path)


@pytest.mark.slow
def test_resume_with_augmentation_equals_an_uninterrupted_run(tmp_path):
    resume_check("bimapper", tmp_path)


@pytest.mark.parametrize(("mode", "says"), [("none", "no mutual learning"), ("async", "both ways from epoch 3"),
                                            ("lv", "LV teaches GV")])
def test_the_logged_schedule_names_the_mutual_mode(tmp_path, mode, says):
    m, _ = method_and_batch("bimapper", tmp_path, mutual=mode, mutual_start_epoch=2)
    assert says in m.schedule() and ("both ways" in m.schedule()) == (mode == "async")
