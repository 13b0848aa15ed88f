"""Training data from rosbag2 files that carry GT topics (``/bev/gt/<class>``), for ``bev-train --bag``.

Lives outside ``bev_mapper_core`` because reading bags needs rosbags; the ``bev-train`` entry
point (:mod:`bags.cli.train`) hands :class:`BagSource` to the core's trainer when ``--bag`` is
given, and wraps the run's source in :class:`UnlabeledBagSource` when ``--unlabeled`` names bags
of unlabeled frames (semi-supervised methods; no GT needed) (the core never imports ``bags``). Frames become the same in-memory
:class:`~bev_mapper_core.training.data.FrameSet` as the synthetic drives:

* label images of every camera in rig order, mapped to Label ids by ``TrainConfig.label_map``
  (frames where a camera's labels are missing or undecodable are skipped, and counted);
* ``target`` = GT layers of the requested classes thresholded at 0.5;
* ``mask`` = cells whose GT is known (not -1) in every requested layer; ``ground_mask`` = the
  bag's ``/bev/visibility/ground`` when present, else ``mask``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import Rig
from bev_mapper_core.labels.label_maps import NATIVE, label_map
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import FrameSet, resize_labels
from bev_mapper_core.training.sources import DataNeeds, DataSource, TrainData

from .reader import BagReader

log = logging.getLogger(__name__)


def bag_rig_grid(path: str | Path) -> tuple[Rig, BevGrid]:
    """The rig and GT grid recorded in a bag (ConfigError if it has no GT)."""
    with BagReader(path) as r:
        rig, grid = r.rig(), r.grid()
    if grid is None:
        raise ConfigError(f"{path}: no /bev/gt/<class> topics: cannot train on it")
    return rig, grid


def bag_frameset(paths: Sequence[str | Path], classes: Sequence[str], rig: Rig, grid: BevGrid,
                 input_size: tuple[int, int] | None = None, label_map_spec: str = NATIVE) -> FrameSet:
    """All complete frames of ``paths`` (see module docstring) for ``rig`` and ``grid``; their
    label images hold what ``label_map_spec`` says (:func:`bev_mapper_core.labels.label_maps.label_map`).

    Raises:
        ConfigError: a bag lacks a requested GT class, has other cameras, another grid, or no
            usable frame at all.
    """
    L, T, M, G = [], [], [], []
    skipped = 0
    lm = label_map(label_map_spec)
    for path in paths:
        with BagReader(path) as r:
            missing = [c for c in classes if c not in r.gt_classes]
            if missing:
                raise ConfigError(f"{path}: no GT topics for classes {missing} (has {list(r.gt_classes)})")
            if r.rig().names != rig.names:
                raise ConfigError(f"{path}: cameras {list(r.rig().names)} differ from {list(rig.names)}")
            if not r.grid().isclose(grid):
                raise ConfigError(f"{path}: GT grid {r.grid().describe()} differs from {grid.describe()}")
            for f in r.frames(rgb=False, labels=True, gt=True, odom=False, label_map=lm):
                if f.gt is None or not all(n in f.labels for n in rig.names):
                    skipped += 1
                    continue
                idx = [f.gt_classes.index(c) for c in classes]
                lab = np.stack([f.labels[n] for n in rig.names]).astype(np.uint8)
                L.append(lab if input_size is None else resize_labels(lab, input_size))
                T.append(f.gt[idx] >= 0.5)
                known = f.gt_known[idx].all(0)
                M.append(known)
                G.append(known if f.ground_visibility is None else (f.ground_visibility & known))
    if not L:
        raise ConfigError(f"no usable frame (labels of every camera + GT) in {list(map(str, paths))}")
    if skipped:
        log.warning("skipped %d incomplete frame(s) of %s", skipped, list(map(str, paths)))
    return FrameSet(np.stack(L), np.stack(T), np.stack(M), np.stack(G), rig.names)


def unlabeled_frameset(paths: Sequence[str | Path], rig: Rig, needs: DataNeeds,
                       label_map_spec: str = NATIVE) -> FrameSet:
    """The frames of ``paths`` as unlabeled training frames (no GT is read, none is needed):
    the images of every camera of ``rig`` (the same names), RGB when ``needs.rgb`` (else label
    images, mapped by ``label_map_spec``), resized to ``needs.image_size`` with the models' own
    resize (:func:`~bev_mapper_core.training.data.resize_rgb` / ``resize_labels``). The bags'
    cameras may deliver another size (same aspect); without an ``image_size`` they must deliver
    the rig's. Frames missing a camera's image are skipped (and counted in the log).

    Raises:
        ConfigError: a bag with other cameras or sizes, or no usable frame at all.
    """
    from bev_mapper_core.training.data import resize_rgb

    size = needs.image_size
    L, R = [], []
    skipped = 0
    lm = label_map(label_map_spec) if not needs.rgb else None
    for path in paths:
        with BagReader(path) as r:
            bag_rig = r.rig()
            if bag_rig.names != rig.names:
                raise ConfigError(f"{path}: cameras {list(bag_rig.names)} differ from the run's {list(rig.names)}")
            if size is None and any(a.model.image_size != b.model.image_size for a, b in zip(bag_rig.cameras, rig.cameras)):
                raise ConfigError(f"{path}: camera image sizes differ from the rig's")
            for f in r.frames(rgb=needs.rgb, labels=not needs.rgb, gt=False, odom=False, label_map=lm):
                imgs = f.rgb if needs.rgb else f.labels
                if not all(n in imgs for n in rig.names):
                    skipped += 1
                    continue
                stack = [imgs[n] for n in rig.names]
                if needs.rgb:
                    R.append(np.stack([img if size is None else resize_rgb(img, size) for img in stack]))
                else:
                    L.append(np.stack([img if size is None else resize_labels(img, size) for img in stack]))
    frames = R if needs.rgb else L
    if not frames:
        raise ConfigError(f"no usable unlabeled frame (images of every camera) in {list(map(str, paths))}")
    if skipped:
        log.warning("skipped %d incomplete frame(s) of %s", skipped, list(map(str, paths)))
    M = len(frames)
    rgb = np.stack(R) if needs.rgb else None
    labels = np.stack(L) if L else np.zeros(rgb.shape[:-1], np.uint8)  # RGB only: no label images needed
    return FrameSet(labels, np.zeros((M, 0, 1, 1), bool), np.zeros((M, 1, 1), bool), camera_names=rig.names, rgb=rgb)


class UnlabeledBagSource(DataSource):
    """Another source's labeled and held-out frames plus unlabeled frames from the bags
    ``cfg.unlabeled_bag`` (``bev-train --unlabeled``), for semi-supervised methods (S2G2).
    """

    name = "unlabeled-bag"

    def __init__(self, base: DataSource) -> None:
        self.base = base
        self.supports = frozenset(base.supports | {"unlabeled"})

    def rig_grid(self, cfg: TrainConfig) -> tuple[Rig, BevGrid]:
        """The base source's rig and grid."""
        return self.base.rig_grid(cfg)

    def load(self, cfg: TrainConfig, rig: Rig, grid: BevGrid, needs: DataNeeds,
             log: Callable[[str], None]) -> TrainData:
        """The base source's frames (asked without ``unlabeled``) and the bags' unlabeled frames."""
        self.check(needs)
        if not needs.unlabeled:
            raise ConfigError(f"method {cfg.method!r} does not train on unlabeled frames; drop --unlabeled")
        if not cfg.unlabeled_bag:
            raise ConfigError("the unlabeled-bag data source needs bags (--unlabeled)")
        data = self.base.load(cfg, rig, grid, replace(needs, unlabeled=False), log)
        unlabeled = unlabeled_frameset(cfg.unlabeled_bag, rig, needs, cfg.label_map)
        log(f"data: {len(unlabeled)} unlabeled frames from {len(cfg.unlabeled_bag)} bag(s)")
        return TrainData(data.train, data.val, unlabeled)


class BagSource(DataSource):
    """``cfg.bag`` for training, ``cfg.val_bag`` held out; rig and grid from the first bag."""

    name = "bag"

    def rig_grid(self, cfg: TrainConfig) -> tuple[Rig, BevGrid]:
        """The rig and GT grid recorded in the first training bag."""
        if not cfg.bag:
            raise ConfigError("the bag data source needs bags (--bag)")
        return bag_rig_grid(cfg.bag[0])

    def load(self, cfg: TrainConfig, rig: Rig, grid: BevGrid, needs: DataNeeds,
             log: Callable[[str], None]) -> TrainData:
        """The frames of ``cfg.bag`` (training) and ``cfg.val_bag`` (held out)."""
        self.check(needs)
        train = bag_frameset(cfg.bag, cfg.class_names, rig, grid, needs.image_size, cfg.label_map)
        if not cfg.val_bag:
            raise ConfigError("training on bags needs held-out bags (--val-bag)")
        return TrainData(train, bag_frameset(cfg.val_bag, cfg.class_names, rig, grid, needs.image_size, cfg.label_map))


__all__ = ["BagSource", "UnlabeledBagSource", "bag_frameset", "bag_rig_grid", "unlabeled_frameset"]
