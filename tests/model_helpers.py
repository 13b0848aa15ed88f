"""A tiny two-camera rig, a flat labelled world rendered through it and a tiny Bi-Mapper config,
shared by the model tests of several methods."""

from __future__ import annotations

import math

import numpy as np
import torch

from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig, RigCamera
from bev_mapper_core.geometry.transforms import ego_from_optical
from bev_mapper_core.labels.classes import NUM_LABELS, Label, labels_to_layers, resolve_classes
from bev_mapper_core.methods.bimapper.config import BiMapperConfig

CLASSES = ("drivable", "lane_divider", "sidewalk")


GRID = BevGrid(x_min=-12, x_max=12, y_min=-6, y_max=6, resolution=0.5)  # 24 x 48 cells


CAM_MODEL = CameraModel(K=((40.0, 0, 31.5), (0, 40.0, 19.5), (0, 0, 1)), width=64, height=40)


RIG = Rig("tiny2", (
    RigCamera("front", CAM_MODEL, ego_from_optical((1.0, 0.0, 1.5))),
    RigCamera("back", CAM_MODEL, ego_from_optical((-1.0, 0.2, 1.5), yaw=math.pi)),
))


TINY = BiMapperConfig(
    classes=CLASSES, input_width=48, width_mult=0.25, depth_mult=0.25, encoder_stages=3,
    neck_channels=16, bev_channels=8, bev_downsample=4, unet_channels=8, decoder_channels=16,
    plane_shape=(26, 10),
)


def flat_label(x, y):
    """Road for |y| < 3 with a divider at y in [0, 0.5); sidewalk beyond."""
    lab = np.where(np.abs(y) < 3.0, Label.ROAD, Label.SIDEWALK).astype(np.uint8)
    lab[(y >= 0.0) & (y < 0.5)] = Label.LANE_DIVIDER
    return lab


def render(cam: RigCamera) -> np.ndarray:
    """Label image of the flat world (ray cast onto z = 0)."""
    rays = cam.model.pixel_rays().reshape(-1, 3)  # (H*W, 3)
    R, o = cam.ego_from_cam_array[:3, :3], cam.ego_from_cam_array[:3, 3]
    d = rays @ R.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = -o[2] / d[:, 2]
    hit = (d[:, 2] < -1e-9) & (t > 0)
    x, y = np.where(hit, o[0] + t * d[:, 0], 0), np.where(hit, o[1] + t * d[:, 1], 0)
    w, h = cam.model.image_size
    return np.where(hit, flat_label(x, y), Label.UNLABELED).reshape(h, w).astype(np.uint8)


def batch(n=2, kind="labels"):
    imgs = np.stack([render(c) for c in RIG.cameras])  # (N, H, W)
    if kind == "rgb":
        imgs = np.stack([np.stack([imgs * 20, imgs * 7, 255 - imgs * 11], -1)]).astype(np.uint8)[0]  # (N, H, W, 3)
    xs, ys = GRID.centers
    tgt = labels_to_layers(flat_label(xs, ys), resolve_classes(CLASSES)).astype(np.float32)  # (C, H, W)
    images = torch.from_numpy(imgs)[None].repeat(n, *([1] * imgs.ndim))
    return {"images": images, "target": torch.from_numpy(tgt)[None].repeat(n, 1, 1, 1),
            "mask": torch.ones(n, *GRID.shape, dtype=torch.bool)}


def random_labels(seed: int) -> torch.Tensor:
    """(1, N, H, W) uint8 label images of random ids, some beyond the label set (-> unlabeled)."""
    rng = np.random.default_rng(seed)
    w, h = CAM_MODEL.image_size
    return torch.from_numpy(rng.integers(0, NUM_LABELS + 3, size=(1, len(RIG.cameras), h, w), dtype=np.uint8))


def step_losses(method, data, cfg, steps: int, epochs: int) -> list[float]:
    """A training method's loss at each of its first ``steps`` optimizer steps over ``data``
    (:meth:`prepare` already run), at most ``epochs`` epochs: the loop of the trainer, bare."""
    opt = method.configure_optimizer(cfg.lr)
    method.model.train()
    out, step = [], 0
    for epoch in range(epochs):
        for batch in data.batches(cfg.batch, cfg.seed, epoch):
            loss, _ = method.loss(batch, epoch, step)
            opt.zero_grad()
            loss.backward()
            opt.step()
            method.after_step(step)
            out.append(float(loss.detach()))
            step += 1
            if step == steps:
                return out
    return out


def random_rgb_data(rgb: np.ndarray, classes, grid: BevGrid, camera_names, unlabeled: bool = True):
    """A :class:`~bev_mapper_core.training.sources.TrainData` of 4 training, 2 held-out (and 2
    unlabeled) frames with random targets, each frame's RGB image one of ``rgb`` ``(F, 1, H, W, 3)``
    (same draws on every call)."""
    from bev_mapper_core.training.data import FrameSet
    from bev_mapper_core.training.sources import TrainData

    rng = np.random.default_rng(0)

    def frames(n):
        idx = rng.integers(0, len(rgb), n)
        return FrameSet(np.zeros((n, 1, 4, 4), np.uint8), rng.random((n, len(classes), *grid.shape)) > 0.6,
                        np.ones((n, *grid.shape), bool), camera_names=camera_names, rgb=rgb[idx])

    return TrainData(frames(4), frames(2), frames(2) if unlabeled else None)


def tiny_run(cfg_dict: dict, data, out, logs=None) -> tuple[list[float], dict]:
    """A run through the trainer (``TrainConfig.from_dict(cfg_dict)``, ``out`` its folder) on
    ``data``: ``(loss_total per epoch, last weights)``; ``logs`` collects the trainer's messages."""
    from safetensors.torch import load_file

    from bev_mapper_core.training.config import TrainConfig
    from bev_mapper_core.training.sources import InMemorySource
    from bev_mapper_core.training.trainer import train

    cfg = TrainConfig.from_dict({**cfg_dict, "out": str(out)})
    doc = train(cfg, log=(logs.append if logs is not None else lambda m: None),
                data=InMemorySource(data.train, data.val, data.unlabeled))
    return [r["loss_total"] for r in doc["history"]], load_file(str(out / "last.safetensors"))


def memory_focusbev(path) -> str:
    """A small untrained FocusBEV file with a memory bank (window 2, 0.3 s apart) for ``front1`` on
    the ``ahead`` grid, for the tests of how the node and the replay run FocusBEV's memory (the
    shipped file, issue #39, maps each frame alone), mapping every class nearly everywhere: its path."""
    from bev_mapper_core.geometry.grid import grid_preset
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.methods.focusbev.model import FocusBEV, FocusBEVConfig
    from bev_mapper_core.methods.focusbev.weights import save_focusbev

    torch.manual_seed(0)
    cfg = FocusBEVConfig(input_width=64, backbone_width=8, fpn_levels=2, channels=16, decoder_layers=1, heads=2,
                         window=2, decoder_channels=8)
    model = FocusBEV(cfg, preset_rig("front1"), grid_preset("ahead"))
    last = [m for m in model.head.modules() if isinstance(m, torch.nn.Conv2d)][-1]
    with torch.no_grad():  # every class mapped nearly everywhere: the drivable area scores above 0
        last.bias.fill_(2.0)
    return str(save_focusbev(model, path, 0.3))


def prior_losses(name: str, cfg, rig, data, steps: int, epochs: int):
    """A ``prior_skip`` method ``name`` built (seed 0), prepared on ``data`` (its prior and feature
    caches) and trained ``steps`` steps: (losses, method). Its prior reads camera-size images."""
    from bev_mapper_core.training.method import method_class  # noqa: PLC0415

    torch.manual_seed(0)
    m = method_class(name)(cfg, rig, cfg.grid)
    assert m.data_needs().image_size is None  # the prior reads camera-size images
    m.prepare(data, lambda _: None)
    return step_losses(m, data, cfg, steps, epochs=epochs), m
