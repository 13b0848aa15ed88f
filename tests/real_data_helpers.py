"""Tiny real-image datasets written in tmp folders, in the CamVid layout and the folder layout
(Cityscapes ids through a label-map YAML), and a segmenter that predicts one label everywhere."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from bev_mapper_core.methods.segmenter.model import Segmenter, SegmenterConfig

H, W = 36, 48
#: a small segmenter (input 32 px wide)
TINY_SEG = SegmenterConfig(input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3, decoder_channels=8)
_PALETTE = np.array([[120, 160, 220], [90, 80, 70], [0, 0, 0], [110, 110, 110], [180, 170, 150], [0, 0, 0],
                     [0, 0, 0], [0, 0, 0], [200, 20, 20], [0, 0, 0], [0, 0, 0], [0, 0, 0]], np.uint8)


def camvid_frame(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """An RGB frame and its CamVid ids: sky, buildings, road, a pavement corner, a car, one Unlabelled pixel."""
    rng = np.random.default_rng(seed)
    lab = np.zeros((H, W), np.uint8)
    lab[9:18] = 1
    lab[18:] = 3
    lab[30:, :8] = 4
    r, c = int(rng.integers(20, 28)), int(rng.integers(8, 30))
    lab[r:r + 6, c:c + 12] = 8
    lab[0, 0] = 11
    img = np.clip(_PALETTE[lab].astype(int) + rng.integers(-8, 9, (H, W, 3)), 0, 255).astype(np.uint8)
    return img, lab


def write_image(path: Path, array: np.ndarray) -> None:
    """Write an RGB image or a mono8 label PNG (OpenCV, BGR on disk)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), array[..., ::-1] if array.ndim == 3 else array)


def write_camvid(root: Path, n: int = 3, splits=("train", "val", "test")) -> Path:
    """``n`` frames per split in the CamVid layout under ``root``."""
    for k, split in enumerate(splits):
        for i in range(n):
            img, lab = camvid_frame(100 * k + i)
            write_image(root / split / f"f{i}.png", img)
            write_image(root / f"{split}annot" / f"f{i}.png", lab)
    return root


#: CamVid id -> Cityscapes id (sky 23, building 11, road 7, sidewalk 8, car 26; Unlabelled 0)
_CITYSCAPES = {0: 23, 1: 11, 3: 7, 4: 8, 8: 26, 11: 0}


def write_folder(root: Path, n: int = 3) -> Path:
    """``n`` frames in the folder layout (JPEG images, Cityscapes-id labels, ``label_map.yaml``)."""
    for i in range(n):
        img, lab = camvid_frame(50 + i)
        write_image(root / "images" / f"a{i}.jpg", img)
        write_image(root / "labels" / f"a{i}.png", np.vectorize(_CITYSCAPES.get)(lab).astype(np.uint8))
    (root / "label_map.yaml").write_text("encoding: mono8\nlabels:\n  7: road\n  8: sidewalk\n  11: building\n"
                                         "  23: unlabeled\n  26: vehicle\nignore: [0]\n")
    return root


def constant_segmenter(label: int, config: SegmenterConfig = TINY_SEG) -> Segmenter:
    """A segmenter whose every pixel is ``label`` (classifier weights 0, that label's bias 10)."""
    torch.manual_seed(0)
    model = Segmenter(config)
    with torch.no_grad():
        model.classifier.weight.zero_()
        model.classifier.bias.zero_()
        model.classifier.bias[label] = 10.0
    return model.eval()
