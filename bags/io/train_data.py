"""Training data from rosbag2 files that carry GT topics (``/bev/gt/<class>``), for ``bev-train --bag``.

Lives outside ``bev_mapper_core`` because reading bags needs rosbags; the ``bev-train`` entry
point (:mod:`bags.cli.train`) hands :class:`BagSource` to the core's trainer when ``--bag`` is
given, and wraps the run's source in :class:`UnlabeledBagSource` when ``--unlabeled`` names bags
of unlabeled frames (semi-supervised methods; no GT needed) (the core never imports ``bags``). Frames become the same in-memory
:class:`~bev_mapper_core.training.data.FrameSet` as the synthetic drives:

* label images of every camera in rig order, mapped to Label ids by ``TrainConfig.label_map``
  (frames where a camera's labels are missing or undecodable are skipped, and counted); RGB
  images (``Image`` or ``CompressedImage`` cameras) when the method trains on them, and no label
  images when it never reads them (an imported dataset's bags have none);
* ``target`` = GT layers of the requested classes thresholded at 0.5;
* ``mask`` = cells whose GT is known (not -1) in some requested layer, and ``class_mask`` = the
  known cells of each class where they differ between classes (an imported dataset's class
  without a source, listed as unscored in the bag's metadata, is unknown everywhere: masked,
  never trained as absent); ``ground_mask`` = the bag's ``/bev/visibility/ground`` when
  present, else ``mask``.

``--split`` / ``--val-split`` pick the bags of a dataset's own split (``bev_mapper.split`` in
their metadata, recorded by ``bev-bag import``).
"""

from __future__ import annotations

import json
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


def bag_unscored(reader: BagReader) -> frozenset[str]:
    """The classes an imported bag's metadata lists as left unscored (``bev_mapper.source``'s
    ``unscored``: the dataset has no source for them), whose missing GT topic is unknown ground
    truth, not an error.
    """
    try:
        info = json.loads(reader.custom_data.get("bev_mapper.source", "{}"))
    except ValueError:
        return frozenset()
    unscored = info.get("unscored") if isinstance(info, dict) else None
    return frozenset(c for c in unscored if isinstance(c, str)) if isinstance(unscored, list) else frozenset()


def bag_frameset(paths: Sequence[str | Path], classes: Sequence[str], rig: Rig, grid: BevGrid,
                 input_size: tuple[int, int] | None = None, label_map_spec: str = NATIVE, *,
                 rgb: bool = False, labels: bool = True,
                 report: Callable[[str, int], None] | None = None) -> FrameSet:
    """All complete frames of ``paths`` (see module docstring) for ``rig`` and ``grid``; their
    label images hold what ``label_map_spec`` says (:func:`bev_mapper_core.labels.label_maps.label_map`).

    ``rgb``: the frames also carry the cameras' RGB images (``CompressedImage`` cameras too),
    resized to ``input_size`` as the models' preprocess would. ``labels`` False: no label image
    is read (an RGB model; the frames hold zero label images), so bags of RGB cameras alone (an
    imported dataset) serve. A requested class that a bag's metadata lists as unscored (an
    imported dataset without a source for it), and cells a layer marks unknown (-1), are left out
    of that class only: the frames then carry a ``class_mask``. ``report(path, frames)`` hears
    how many frames each bag gave.

    Raises:
        ConfigError: a bag lacks a requested GT class (and does not list it as unscored), has
            other cameras, another grid, no label images where they are needed, or no usable
            frame at all; or no bag has GT of a requested class.
    """
    from bev_mapper_core.training.data import resize_rgb

    L, R, T, K, G = [], [], [], [], []
    skipped = 0
    lm = label_map(label_map_spec) if labels else None
    scored: set[str] = set()
    for path in paths:
        before = len(T)
        with BagReader(path) as r:
            have = set(r.gt_classes)
            missing = [c for c in classes if c not in have and c not in bag_unscored(r)]
            if missing:
                raise ConfigError(f"{path}: no GT topics for classes {missing} (has {list(r.gt_classes)})")
            scored |= have
            if r.rig().names != rig.names:
                raise ConfigError(f"{path}: cameras {list(r.rig().names)} differ from {list(rig.names)}")
            if not r.grid().isclose(grid):
                raise ConfigError(f"{path}: GT grid {r.grid().describe()} differs from {grid.describe()}")
            if labels and not any(r.image_topic(n, "labels") in r.topics for n in rig.names):
                raise ConfigError(f"{path}: no label images (an imported dataset's bags hold RGB cameras only): "
                                  "train a model on RGB input (--input rgb)")
            for f in r.frames(rgb=rgb, labels=labels, gt=True, odom=False, label_map=lm):
                if f.gt is None or not all(n in (f.labels if labels else f.rgb) for n in rig.names):
                    skipped += 1
                    continue
                cells = grid.shape
                t = np.zeros((len(classes), *cells), bool)  # (K, Hg, Wg); an absent class: unknown
                k = np.zeros((len(classes), *cells), bool)
                for j, c in enumerate(classes):
                    if c in f.gt_classes:
                        i = f.gt_classes.index(c)
                        t[j], k[j] = f.gt[i] >= 0.5, f.gt_known[i]
                T.append(t)
                K.append(k)
                if labels:
                    lab = np.stack([f.labels[n] for n in rig.names]).astype(np.uint8)
                    L.append(lab if input_size is None else resize_labels(lab, input_size))
                if rgb:
                    R.append(np.stack([f.rgb[n] if input_size is None else resize_rgb(f.rgb[n], input_size)
                                       for n in rig.names]))
                G.append(f.ground_visibility)
        if report is not None:
            report(str(path), len(T) - before)
    if not T:
        raise ConfigError(f"no usable frame ({'label images' if labels else 'images'} of every camera + GT) "
                          f"in {list(map(str, paths))}")
    never = [c for c in classes if c not in scored]
    if never:
        raise ConfigError(f"no bag of {list(map(str, paths))} has GT of {never}: nothing to train them on")
    if skipped:
        log.warning("skipped %d frame(s) without GT or a camera's image in %s", skipped, list(map(str, paths)))
    known = np.stack(K)  # (M, K, Hg, Wg)
    mask = known.any(1)  # (M, Hg, Wg): cells some class's ground truth is known in
    class_mask = None if (known == mask[:, None]).all() else known
    ground = np.stack([mask[i] if g is None else g & mask[i] for i, g in enumerate(G)])
    rgb_arr = np.stack(R) if rgb else None
    if labels:
        lab_arr = np.stack(L)
    else:  # an RGB model never reads them: zero label images of the RGB images' size
        lab_arr = np.zeros(rgb_arr.shape[:-1], np.uint8)  # (M, N, h, w, 3) -> (M, N, h, w)
    return FrameSet(lab_arr, np.stack(T), mask, ground, rig.names, rgb=rgb_arr, class_mask=class_mask)


def select_split(paths: Sequence[str | Path], split: str) -> list[Path]:
    """The bags named by ``paths`` (a folder stands for the bags in it) whose metadata records
    ``split`` (``bev_mapper.split``, which ``bev-bag import`` writes).

    Raises:
        ConfigError: a path names no bag, or no bag is in ``split``.
    """
    bags = find_training_bags(paths)
    picked, seen = [], {}
    for b in bags:
        with BagReader(b) as r:
            s = r.custom_data.get("bev_mapper.split")
        seen[str(b)] = s
        if s == split:
            picked.append(b)
    if not picked:
        found = sorted({str(s) for s in seen.values()})
        raise ConfigError(f"no bag of split {split!r} among {len(bags)} bag(s) (their splits: {', '.join(found)})")
    return picked


def find_training_bags(paths: Sequence[str | Path]) -> list[Path]:
    """The bags ``paths`` name: a bag, or a folder searched for bags (ConfigError if none)."""
    from ..errors import BagError
    from ..fleet.replay_tasks import find_bags

    try:
        return find_bags(map(Path, paths))
    except BagError as exc:
        raise ConfigError(str(exc)) from None


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
    """``cfg.bag`` for training, ``cfg.val_bag`` held out; rig and grid from the first bag. A
    folder stands for the bags in it; with ``cfg.split`` only the bags of that split of their
    dataset train and those of ``cfg.val_split`` (from ``val_bag``, else ``bag``) are held out.
    The frames carry RGB images when the method asks for them (``supports`` rgb).
    """

    name = "bag"
    supports = frozenset({"rgb"})

    def bags(self, cfg: TrainConfig) -> tuple[list[Path], list[Path]]:
        """The training and held-out bags of ``cfg`` (see the class docstring)."""
        if not cfg.bag:
            raise ConfigError("the bag data source needs bags (--bag)")
        if cfg.split is None:
            if not cfg.val_bag:
                raise ConfigError("training on bags needs held-out bags (--val-bag)")
            return find_training_bags(cfg.bag), find_training_bags(cfg.val_bag)
        train = select_split(cfg.bag, cfg.split)
        val = (select_split(cfg.val_bag or cfg.bag, cfg.val_split) if cfg.val_split is not None
               else find_training_bags(cfg.val_bag))
        both = {b.resolve() for b in train} & {b.resolve() for b in val}
        if both:
            raise ConfigError(f"bags both trained on and held out: {sorted(map(str, both))}")
        return train, val

    def rig_grid(self, cfg: TrainConfig) -> tuple[Rig, BevGrid]:
        """The rig and GT grid recorded in the first training bag."""
        return bag_rig_grid(self.bags(cfg)[0][0])

    def load(self, cfg: TrainConfig, rig: Rig, grid: BevGrid, needs: DataNeeds,
             log: Callable[[str], None]) -> TrainData:
        """The frames of the training and held-out bags, each bag's count in the log."""
        self.check(needs)
        train_bags, val_bags = self.bags(cfg)
        sets = []
        for what, bags, split in (("train", train_bags, cfg.split), ("val", val_bags, cfg.val_split)):
            def report(path: str, n: int, what=what, split=split) -> None:
                log(f"data: {what} bag {path}{f' (split {split})' if split else ''}: {n} frames")

            sets.append(bag_frameset(bags, cfg.class_names, rig, grid, needs.image_size, cfg.label_map,
                                     rgb=needs.rgb, labels=needs.labels, report=report))
            fs = sets[-1]
            unknown = "" if fs.class_mask is None else (
                "; unknown ground truth left out per class: "
                + ", ".join(f"{c} {100 * (1 - fs.class_mask[:, j].mean()):.0f} %" for j, c in enumerate(cfg.class_names)))
            log(f"data: {what}: {len(fs)} frames from {len(bags)} bag(s){unknown}")
        return TrainData(sets[0], sets[1])


__all__ = ["BagSource", "UnlabeledBagSource", "bag_frameset", "bag_rig_grid", "bag_unscored", "find_training_bags",
           "select_split", "unlabeled_frameset"]
