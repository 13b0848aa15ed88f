"""Real labelled images in the segmenter's training and scoring: the recipe's parts that
``bev-train --method segmenter --real ...`` (:mod:`.train`), ``bev-train eval --method segmenter
--real ...`` and ``experiments/segmenter_real.py`` / ``experiments/eval_camvid.py`` share.

* Loading: a dataset split (:func:`~bev_mapper_core.datasets.open_dataset`) into tensors, at
  the camera size (:func:`read_split`) or pre-shrunk to :data:`BASE_FACTOR` x the model input
  (:func:`load_split`, :func:`base_copy`: antialiased images, nearest labels), so that the
  augmentation's bilinear resampling does not alias.
* Training: one code space for several label spaces (:func:`~bev_mapper_core.nn.label_space.joint_cover`;
  a frame's targets are its dataset's class ids plus the dataset's offset), class weights over
  it (:func:`joint_class_weights`: softened median frequency per space), batches drawn and
  augmented from a seeded generator (:func:`sample_batch`), and the mixed-batch loss
  (:func:`mixed_loss`: the partial-label loss of every part, weighted and summed: a coarse real
  label supervises the sum of the fine labels it covers).
* Scoring: pooled pixel IoU in a dataset's own classes (fine argmax, each fine label mapped to
  its home class: :func:`~bev_mapper_core.nn.label_space.coarse_predict`; unlabelled pixels left
  out), the five common classes and their mean (:func:`iou_report`), and CPU time per frame.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from bev_mapper_core.datasets import KINDS, open_dataset
from bev_mapper_core.errors import ConfigError
from bev_mapper_core.labels.spaces import CAMVID, COMMON_CAMVID, IGNORE, LabelSpace
from bev_mapper_core.nn.augment import Augment, step_generator
from bev_mapper_core.nn.label_space import coarse_predict, confusion, iou_from_confusion, marginal_nll

from .model import Segmenter, SegmenterConfig, class_weights

#: Real frames are kept at most this factor x the model input (before augmentation).
BASE_FACTOR = 1.5
#: Dataset kinds of a ``--real`` spec (``kind:DIR``): the readers' own table.
REAL_KINDS: tuple[str, ...] = tuple(KINDS)


def check_spec(spec: str) -> str:
    """``spec`` if it is ``camvid:DIR`` or ``folder:DIR[:PRESET]`` (no file is read).

    Raises:
        ConfigError: another form.
    """
    kind, _, rest = str(spec).partition(":")
    if kind not in REAL_KINDS or not rest:
        raise ConfigError(f"real data must be one of {list(KINDS.values())}, got {spec!r}")
    return spec


def open_split(spec: str, split: str, skip_bad: bool = False):
    """The reader of ``spec``'s ``split``, or None where the dataset has no such split: a CamVid
    folder without ``DIR/<split>/`` (``train`` is required); a folder dataset has no splits
    (every split is all its frames).

    Raises:
        DatasetError: see the readers.
    """
    kind, _, rest = check_spec(spec).partition(":")
    if kind == "camvid" and split != "train" and Path(rest).is_dir() and not (Path(rest) / split).is_dir():
        return None
    return open_dataset(spec, split, skip_bad)


# ------------------------------------------------------------------------------- loading
def base_size(frame_hw: tuple[int, int], out_hw: tuple[int, int], factor: float = BASE_FACTOR) -> tuple[int, int]:
    """``(h, w)`` real frames of ``frame_hw`` are kept at: ``factor`` x the model input
    ``out_hw``, never above the frame's own size.
    """
    return min(frame_hw[0], round(out_hw[0] * factor)), min(frame_hw[1], round(out_hw[1] * factor))


def base_copy(images: torch.Tensor, labels: torch.Tensor, size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """``(N, H, W, 3)`` uint8 images (bilinear, antialiased) and ``(N, H, W)`` labels (nearest)
    resized to ``size`` = ``(h, w)``: ``(N, 3, h, w)`` uint8 and ``(N, h, w)`` uint8.
    """
    H, W = images.shape[1:3]
    imgs, labs = [], []
    for i in range(0, len(images), 64):
        x = images[i:i + 64].permute(0, 3, 1, 2).float()  # (b, H, W, 3) -> (b, 3, H, W)
        if tuple(size) != (H, W):
            x = F.interpolate(x, size=tuple(size), mode="bilinear", align_corners=False, antialias=True)
        imgs.append(x.round().clamp(0, 255).to(torch.uint8))
        y = labels[i:i + 64].unsqueeze(1).float()
        labs.append(F.interpolate(y, size=tuple(size), mode="nearest-exact").squeeze(1).to(torch.uint8))
    return torch.cat(imgs), torch.cat(labs)


def read_split(reader, limit: int = 0, device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """The first ``limit`` (0: all) good frames of a reader at their own size: ``(images (N, H,
    W, 3) uint8, labels (N, H, W) uint8)`` on ``device`` (bad frames skipped if the reader skips).

    Raises:
        DatasetError: a bad frame (see the readers), a frame of another size than the first, no frames.
    """
    from bev_mapper_core.datasets import DatasetError  # noqa: PLC0415

    samples = list(itertools.islice(iter(reader), limit or None))
    if not samples:
        raise DatasetError(f"{_where(reader)}: no labelled frames")
    size = samples[0].image.shape
    for s in samples:
        if s.image.shape != size:
            raise DatasetError(f"{_where(reader)}: frame {s.name} is {s.image.shape[1]}x{s.image.shape[0]}, the first "
                               f"{samples[0].name} {size[1]}x{size[0]}; these frames must be of one size")
    imgs = torch.from_numpy(np.stack([s.image for s in samples]))
    labs = torch.from_numpy(np.stack([s.labels for s in samples]))
    return imgs.to(device), labs.to(device)


@dataclass
class RealSet:
    """A dataset split in memory for training (see :func:`load_split`).

    Attributes:
        name: the dataset spec (``camvid:DIR`` ...).
        space: its classes as sets of fine labels.
        images: ``(N, 3, h, w)`` uint8 at the base size.
        labels: ``(N, h, w)`` uint8 class ids of ``space``, :data:`IGNORE` where unlabelled.
        input_hw: the model input ``(h, w)`` of these frames (batches are drawn at this size).
        skipped: ``(file, reason)`` of the frames left out (``skip_bad``).
    """

    name: str
    space: LabelSpace
    images: torch.Tensor
    labels: torch.Tensor
    input_hw: tuple[int, int]
    skipped: list[tuple[str, str]] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.images)

    def counts(self) -> torch.Tensor:
        """``(K,)`` labelled pixels per class of :attr:`space` (at the base size)."""
        y = self.labels[self.labels != IGNORE].long()
        return torch.bincount(y.flatten(), minlength=self.space.num_classes)[:self.space.num_classes].cpu()


def load_split(reader, config: SegmenterConfig, limit: int = 0, device: torch.device | str = "cpu",
               name: str = "") -> RealSet:
    """A reader's frames (the first ``limit``; 0: all) for training a segmenter of ``config``:
    each frame read, checked and resized at once to the base size of the first frame (frames of
    another size are resized to it too), so the full-size frames are never all in memory.

    Raises:
        DatasetError: a bad frame (unless the reader skips them), or no frames.
    """
    from bev_mapper_core.datasets import DatasetError  # noqa: PLC0415

    imgs, labs, size, input_hw = [], [], None, None
    for s in itertools.islice(iter(reader), limit or None):
        if size is None:
            H, W = s.image.shape[:2]
            input_hw = config.input_size((W, H))
            size = base_size((H, W), input_hw)
        x, y = base_copy(torch.from_numpy(s.image)[None], torch.from_numpy(s.labels)[None], size)
        imgs.append(x)
        labs.append(y)
    if not imgs:
        raise DatasetError(f"{_where(reader)}: no labelled frames")
    skipped = list(getattr(reader, "skipped", []))
    return RealSet(name or _where(reader), reader.space, torch.cat(imgs).to(device), torch.cat(labs).to(device),
                   input_hw, skipped)


def _where(reader) -> str:
    root = getattr(reader, "root", "")
    split = getattr(reader, "split", "")
    return f"{root}" + (f" ({split})" if split else "")


# ------------------------------------------------------------------------------ training
def joint_class_weights(counts: Sequence[torch.Tensor | None], sizes: Sequence[int], enabled: bool = True,
                        mode: str = "median") -> torch.Tensor:
    """Class weights over a joint code space (:func:`~bev_mapper_core.nn.label_space.joint_cover`
    of spaces of ``sizes`` classes): per space the weights of its pixel ``counts``
    (:func:`~.model.class_weights` of ``mode``: ``median`` or ``enet``), ones where the counts
    are None or ``enabled`` is off.
    """
    parts = [class_weights(c, mode=mode) if (enabled and c is not None) else torch.ones(n)
             for c, n in zip(counts, sizes)]
    return torch.cat(parts)


def sample_batch(images: torch.Tensor, labels: torch.Tensor, n: int, out_hw: tuple[int, int], offset: int,
                 generator: torch.Generator, augment: Augment | None, mean: torch.Tensor,
                 std: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` frames drawn with replacement from ``(N, 3, h, w)`` uint8 ``images`` and ``(N, h,
    w)`` ``labels`` (on the generator's device), augmented (``augment``; else resized) to
    ``out_hw``: ``(normalised input (n, 3, *out_hw), targets (n, *out_hw) long)``, targets in the
    joint code space (``labels + offset``, :data:`IGNORE` kept).
    """
    idx = torch.randint(len(images), (n,), generator=generator, device=images.device)
    x, y = images[idx].float() / 255.0, labels[idx].long()
    if augment is not None:
        x, y = augment(x, y, out_hw)
    elif tuple(x.shape[-2:]) != tuple(out_hw):
        x = F.interpolate(x, size=tuple(out_hw), mode="bilinear", align_corners=False, antialias=True)
        y = F.interpolate(y[:, None].float(), size=tuple(out_hw), mode="nearest-exact")[:, 0].long()
    y = torch.where(y == IGNORE, y, y + offset)
    return (x - mean) / std, y


def mixed_loss(model: Segmenter, parts: Sequence[tuple[torch.Tensor, torch.Tensor, float]], cover: torch.Tensor,
               weight: torch.Tensor | None, hard_fraction: float = 1.0) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """``(sum_i w_i * marginal_nll(model(x_i), y_i), [each part's loss])`` of the parts ``(x_i,
    y_i, w_i)`` (a synthetic batch in fine codes, a real one in its dataset's codes: one
    :func:`~bev_mapper_core.nn.label_space.marginal_nll` over the joint ``cover``; OHEM below
    ``hard_fraction`` 1).
    """
    losses = [marginal_nll(model(x), y, cover, weight, hard_fraction=hard_fraction) for x, y, _ in parts]
    total = sum(w * loss for (_, _, w), loss in zip(parts, losses))
    return total, losses


# ------------------------------------------------------------------------------- scoring
@torch.no_grad()
def frame_confusion(model: Segmenter, images: torch.Tensor, labels: torch.Tensor, space: LabelSpace,
                    amp: bool = False) -> torch.Tensor:
    """``(K, K + 1)`` confusion (:func:`~bev_mapper_core.nn.label_space.confusion`) of the model's
    prediction at the frames' own size: ``(B, H, W, 3)`` images, ``(B, H, W)`` class ids of ``space``.
    """
    x = model.preprocess(images)
    with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=amp):
        logits = model(x, size=tuple(images.shape[1:3]))
    return confusion(coarse_predict(logits.float(), space), labels, space.num_classes)


@torch.no_grad()
def pooled_iou(model: Segmenter, images: torch.Tensor, labels: torch.Tensor, space: LabelSpace,
               amp: bool = False, batch: int = 16) -> np.ndarray:
    """Pooled pixel IoU ``(K,)`` per class of ``space`` over ``(N, H, W, 3)`` images (the model
    is put in eval mode).
    """
    model.eval()
    conf = torch.zeros(space.num_classes, space.num_classes + 1, dtype=torch.long)
    for i in range(0, len(images), batch):
        conf += frame_confusion(model, images[i:i + batch], labels[i:i + batch], space, amp)
    return iou_from_confusion(conf)


def common_classes(space: LabelSpace) -> dict[str, str]:
    """The common five (road with markings, sidewalk, vehicle, pedestrian, building) -> the
    space's class: CamVid's (:data:`~bev_mapper_core.nn.label_space.COMMON_CAMVID`), else the
    classes of those names.
    """
    if space.classes == CAMVID.classes:
        return dict(COMMON_CAMVID)
    return {k: k for k in COMMON_CAMVID if k in space.classes}


def iou_report(iou: np.ndarray, space: LabelSpace) -> dict:
    """IoU (%) per class of ``space`` (NaN: the class is in neither truth nor prediction, None in
    the report), the common five and their mean.
    """
    per = {c: (None if not np.isfinite(v) else round(100 * float(v), 2)) for c, v in zip(space.classes, iou)}
    common = {k: per[c] for k, c in common_classes(space).items()}
    vals = [v for v in common.values() if v is not None]
    return {"per_class": per, "common": common, "common_mean": round(float(np.mean(vals)), 2) if vals else None}


@torch.no_grad()
def score_reader(model: Segmenter, reader, limit: int = 0, stage=None) -> dict:
    """Pooled pixel IoU of ``model`` over a reader's frames (the first ``limit``; 0: all), one
    frame at a time at its own size: ``{"frames", "skipped", **iou_report}``. ``stage``: a
    :class:`~.stage.SegmenterStage` of the same weights whose labels are scored instead (its
    backend and precision; the same fine argmax, each label mapped to its home class).

    Raises:
        DatasetError: a bad frame (unless the reader skips them), or no frames.
    """
    from bev_mapper_core.datasets import DatasetError  # noqa: PLC0415

    space = reader.space
    conf = torch.zeros(space.num_classes, space.num_classes + 1, dtype=torch.long)
    n = 0
    dev = next(model.parameters()).device
    home = torch.from_numpy(space.coarse_of_fine())
    for s in itertools.islice(iter(reader), limit or None):
        if stage is not None:
            labels = torch.from_numpy(stage.segment({"frame": s.image})["frame"])
            conf += confusion(home[labels.long()][None], torch.from_numpy(s.labels)[None], space.num_classes)
            n += 1
            continue
        conf += frame_confusion(model, torch.from_numpy(s.image)[None].to(dev), torch.from_numpy(s.labels)[None].to(dev),
                                space)
        n += 1
    if not n:
        raise DatasetError(f"{_where(reader)}: no labelled frames")
    return {"frames": n, "skipped": [list(x) for x in getattr(reader, "skipped", [])],
            **iou_report(iou_from_confusion(conf), space)}


@torch.inference_mode()
def ms_per_frame(model: Segmenter, image: np.ndarray, frames: int = 10) -> float:
    """Milliseconds per :meth:`~.model.Segmenter.segment` call (resize, network, upsampling to the
    image's size, argmax) on one ``(H, W, 3)`` image, after one warm-up call.
    """
    img = torch.from_numpy(image)[None].to(next(model.parameters()).device)
    model.segment(img)
    t = time.perf_counter()
    for _ in range(frames):
        model.segment(img)
    return (time.perf_counter() - t) / frames * 1000


def stage_ms_per_frame(stage, image: np.ndarray, frames: int = 10) -> float:
    """:func:`ms_per_frame` of a :class:`~.stage.SegmenterStage` (its backend and precision)."""
    stage.segment({"frame": image})
    t = time.perf_counter()
    for _ in range(frames):
        stage.segment({"frame": image})
    return (time.perf_counter() - t) / frames * 1000


def format_report(name: str, rep: dict) -> list[str]:
    """The printed lines of one dataset's :func:`score_reader` result."""
    def pct(v):
        return "-" if v is None else f"{v:.1f}"

    mean = rep["common_mean"]
    lines = [f"{name}: {rep['frames']} frames, pooled pixel IoU %"
             + (f" ({len(rep['skipped'])} bad frames skipped)" if rep.get("skipped") else ""),
             "  " + "  ".join(f"{c} {pct(v)}" for c, v in rep["per_class"].items()),
             "  common: " + "  ".join(f"{k} {pct(v)}" for k, v in rep["common"].items())
             + f"  mean {pct(mean)}"]
    return lines


__all__ = ["BASE_FACTOR", "REAL_KINDS", "RealSet", "base_copy", "base_size", "check_spec", "common_classes",
           "format_report", "frame_confusion", "iou_report", "joint_class_weights", "load_split", "mixed_loss",
           "ms_per_frame", "open_split", "pooled_iou", "read_split", "sample_batch", "score_reader", "stage_ms_per_frame",
           "step_generator"]
