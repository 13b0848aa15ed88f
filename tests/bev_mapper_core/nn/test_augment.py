"""The photometric augmentation alone on raw camera images (``Augment.camera_images``, issue #24):
layouts, shared draws per run of images, the step generator."""

from __future__ import annotations

import pytest
import torch

from bev_mapper_core.nn.augment import Augment, AugmentConfig, step_augment, step_generator

torch.set_num_threads(1)
NEUTRAL = AugmentConfig(brightness=(1, 1), contrast=(1, 1), saturation=(1, 1), white_balance=(1, 1), gamma=(1, 1),
                        p_blur=0.0, p_noise=0.0)


def _images(*lead: int) -> torch.Tensor:
    return torch.randint(0, 256, (*lead, 12, 20, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))


@pytest.mark.parametrize("lead", [(2, 6), (3, 2, 1)])  # (B, N) cameras, (B, T, N) windows
def test_neutral_strengths_give_back_the_images_in_their_layout(lead):
    x = _images(*lead)
    y = Augment(NEUTRAL, step_generator(0, 0)).camera_images(x)
    assert y.shape == x.shape and y.dtype == torch.float32
    torch.testing.assert_close(y, x.float(), atol=1e-3, rtol=0)


def test_camera_images_is_the_photometric_part_per_image():
    x = _images(2, 3)
    y = Augment(AugmentConfig(), step_generator(4, 7)).camera_images(x)
    ref = Augment(AugmentConfig(), step_generator(4, 7)).photometric(x.flatten(0, 1).permute(0, 3, 1, 2).float() / 255)
    torch.testing.assert_close(y, (ref * 255).permute(0, 2, 3, 1).view(x.shape))
    assert 0 <= y.min() and y.max() <= 255
    assert (y - x.float()).abs().mean() > 1.0


def test_runs_of_images_share_their_draws_but_not_the_noise():
    frame = _images(1, 1)
    x = frame.repeat(3, 2, 1, 1, 1, 1)  # (3 windows, 2 equal frames, 1 camera, h, w, 3)
    y = Augment(AugmentConfig(p_noise=0.0), step_generator(0, 1)).camera_images(x, share=2)
    assert torch.equal(y[:, 0], y[:, 1])  # a window's frames: one draw
    assert not torch.equal(y[0], y[1]) and not torch.equal(y[1], y[2])  # windows: their own
    noisy = Augment(AugmentConfig(p_noise=1.0), step_generator(0, 1)).camera_images(x, share=2)
    assert not torch.equal(noisy[:, 0], noisy[:, 1])  # sensor noise per frame
    apart = Augment(AugmentConfig(p_noise=0.0), step_generator(0, 1)).camera_images(x)  # share 1: per image
    assert not torch.equal(apart[:, 0], apart[:, 1])
    with pytest.raises(ValueError, match="runs of 4"):
        Augment(AugmentConfig(), step_generator(0, 1)).camera_images(x, share=4)
    with pytest.raises(ValueError, match="camera images"):
        Augment(AugmentConfig(), step_generator(0, 1)).camera_images(x[..., :2])


def test_a_step_draws_the_same_whatever_came_before():
    x = _images(2, 1)
    a = step_augment(3, 10, "cpu").camera_images(x)
    torch.rand(5)  # the global stream plays no part
    assert torch.equal(step_augment(3, 10, "cpu").camera_images(x), a)
    assert not torch.equal(step_augment(3, 11, "cpu").camera_images(x), a)
    assert not torch.equal(step_augment(4, 10, "cpu").camera_images(x), a)
