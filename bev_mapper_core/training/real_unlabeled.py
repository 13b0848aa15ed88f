"""Real camera images as unlabeled frames of a one-camera rig: S2G2's semi-supervised idea
(a consistency loss on frames without ground truth) used to bridge from the synthetic town to
real images.

``bev-train --unlabeled-real camvid:DIR`` (``TrainConfig.unlabeled_real``) takes the *training*
split of a real-image dataset (:func:`~bev_mapper_core.datasets.open_dataset`: CamVid's layout
or a team's folder; its labels are never read). Each image is centre-cropped to the camera's
aspect ratio (CamVid's 4:3 to front1's 16:9 keeps the middle rows, where the road and the
horizon are) and resized to the size the model reads, with the models' own resize. The
unlabeled frames of a run are these, beside the synthetic unlabeled drives
(``--unlabeled-drives``) when both are given.

The real camera's intrinsics and mounting differ from the rig's: the frames teach the image
encoder and the consistency loss what real images look like, not the geometry (the paper's
unlabeled frames come from the same rig; here they do not, and the results say what it gives).
"""

from __future__ import annotations

import numpy as np

from ..datasets import open_dataset
from ..errors import ConfigError
from ..geometry.rig import Rig
from .data import FrameSet, resize_rgb
from .sources import DataNeeds


def crop_to_aspect(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """The centred crop of ``image`` ``(H, W, 3)`` with the aspect ratio ``width : height``."""
    H, W = image.shape[:2]
    if W * height > H * width:  # too wide: keep the middle columns
        w = max(1, round(H * width / height))
        x0 = (W - w) // 2
        return image[:, x0:x0 + w]
    h = max(1, round(W * height / width))
    y0 = (H - h) // 2
    return image[y0:y0 + h]


def real_unlabeled_frameset(spec: str, rig: Rig, needs: DataNeeds, limit: int = 0) -> FrameSet:
    """The training images of dataset ``spec`` as unlabeled RGB frames of ``rig``'s one camera,
    ``(M, 1, h, w, 3)`` at ``needs.image_size`` (else the camera's delivered size); the first
    ``limit`` images in the dataset's order (0 = all).

    Raises:
        ConfigError: a rig of more than one camera, label input, or no image.
        DatasetError: an unreadable dataset (the reader's message).
    """
    if len(rig.cameras) != 1:
        raise ConfigError(f"real unlabeled images are frames of a one-camera rig; rig {rig.name!r} has "
                          f"{len(rig.cameras)} cameras")
    if not needs.rgb:
        raise ConfigError("real unlabeled images need RGB input (--input rgb)")
    W, H = rig.cameras[0].model.image_size
    size = needs.image_size or (H, W)
    data = open_dataset(spec, "train")
    count = len(data) if limit <= 0 else min(limit, len(data))
    frames = [resize_rgb(crop_to_aspect(data.read(i).image, W, H), size) for i in range(count)]
    if not frames:
        raise ConfigError(f"{spec}: no training image to use as an unlabeled frame")
    rgb = np.stack(frames)[:, None]  # M x (h, w, 3) -> (M, 1, h, w, 3)
    M = len(frames)
    return FrameSet(np.zeros(rgb.shape[:-1], np.uint8), np.zeros((M, 0, 1, 1), bool), np.zeros((M, 1, 1), bool),
                    camera_names=rig.names, rgb=rgb)


def join_unlabeled(sets: list[FrameSet]) -> FrameSet:
    """One unlabeled frame set of several (their inputs only: label images and RGB)."""
    if len(sets) == 1:
        return sets[0]
    names = sets[0].camera_names
    if any(s.camera_names != names for s in sets) or any((s.rgb is None) != (sets[0].rgb is None) for s in sets):
        raise ConfigError("unlabeled frame sets of different cameras or inputs cannot be joined")
    shapes = {s.labels.shape[1:] for s in sets}
    if len(shapes) != 1:
        raise ConfigError(f"unlabeled frame sets of different image sizes {sorted(shapes)} cannot be joined")
    labels = np.concatenate([s.labels for s in sets])
    rgb = None if sets[0].rgb is None else np.concatenate([s.rgb for s in sets])
    M = len(labels)
    return FrameSet(labels, np.zeros((M, 0, 1, 1), bool), np.zeros((M, 1, 1), bool), camera_names=names, rgb=rgb)
