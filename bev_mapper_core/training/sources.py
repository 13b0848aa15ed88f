"""Where training frames come from: a data source the entry point hands to :func:`~.trainer.train`.

A method declares what it trains on as :class:`DataNeeds` (image size, RGB, unlabeled frames;
later frame sequences, ego poses); the trainer asks the run's :class:`DataSource` for a
:class:`TrainData` that honours them. A source that cannot provide a need says so with a
:class:`~bev_mapper_core.errors.ConfigError` before any training starts.

Sources here (framework-free): :class:`SynthSource` (seeded synthetic drives, cached) and
:class:`InMemorySource` (ready FrameSets, for tests and notebooks). The rosbag2 source lives in
``bags.io.train_data`` (it needs rosbags) and is passed in by the ``bev-train`` entry point.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from typing_extensions import override

from ..errors import ConfigError
from ..geometry.grid import BevGrid
from ..geometry.random_rig import RANDOM_RIGS, random_rig
from ..geometry.rig import Rig, preset_rig
from .data import FrameSet, shard_slice, synth_frameset, train_seeds
from .multirig import random_rig_frameset

if TYPE_CHECKING:  # typing only: config imports the method registry, not this module
    from .config import TrainConfig


@dataclass(frozen=True)
class DataNeeds:
    """What a training method needs from the data side.

    Args:
        image_size: ``(h, w)``: store label images resized to this model input size (exactly
            as the model's preprocess would); ``None``: camera-size images.
        unlabeled: also a stream of frames without GT (S2G2's consistency loss).
        sequence_length: frames per sample; > 1 = windows of consecutive frames of one drive
            (FocusBEV's temporal fusion).
        poses: each frame carries its ego pose (FocusBEV warps its memory bank with them).
        rgb: each frame also carries its RGB camera images ``(N, h, w, 3)`` uint8 (batches:
            ``rgb``), at ``image_size`` (``None``: camera size), resized as the models' own
            preprocess would.
        labels: the camera label images are read (model input, segmentation targets); False:
            an RGB model that never reads them, which a source of RGB images alone (an imported
            dataset's bags) can serve (its frames then hold zero label images).
    """

    image_size: tuple[int, int] | None = None
    unlabeled: bool = False
    sequence_length: int = 1
    poses: bool = False
    rgb: bool = False
    labels: bool = True

    def __post_init__(self) -> None:
        if self.sequence_length < 1:
            raise ConfigError(f"sequence_length must be >= 1, got {self.sequence_length}")

    def extras(self) -> frozenset[str]:
        """Needs beyond labeled single frames: ``unlabeled``, ``sequences``, ``poses``, ``rgb``."""
        return frozenset(n for n, on in (("unlabeled", self.unlabeled), ("sequences", self.sequence_length > 1),
                                         ("poses", self.poses), ("rgb", self.rgb)) if on)


#: Keys of an unlabeled batch: the inputs and the frames' ids in their set (a FrameSet batch
#: without ``target`` / ``mask``).
UNLABELED_KEYS = ("images", "rgb", "index")


@dataclass
class TrainData:
    """The frames of one run: ``train`` (labeled), ``val`` (held out, scored every epoch) and,
    for semi-supervised methods, ``unlabeled`` (frames whose ground truth is never read).
    """

    train: FrameSet
    val: FrameSet
    unlabeled: FrameSet | None = None

    def steps(self, batch: int, limit: int | None = None) -> int:
        """Batches in one epoch of :meth:`batches` (one per ``batch`` labeled frames)."""
        return math.ceil(min(limit or len(self.train), len(self.train)) / batch)

    def batches(self, batch: int, seed: int, epoch: int, limit: int | None = None,
                shard: tuple[int, int] = (0, 1)) -> Iterator[dict]:
        """One epoch of training batches, order a function of ``(seed, epoch)`` (see FrameSet.batches).

        Without unlabeled frames: the labeled FrameSet's batches. With them: ``{"labeled":
        <labeled batch>, "unlabeled": <batch of as many unlabeled frames>}`` (S2G2: 2 + 2), the
        unlabeled frames in their own seeded order, cycled when there are fewer of them; an
        unlabeled batch holds only the inputs (:data:`UNLABELED_KEYS`).

        ``shard = (rank, world)`` (data-parallel training): rank ``rank``'s part of every batch,
        labeled and unlabeled frames alike (see :meth:`~.data.FrameSet.batches`); the parts of
        all ranks together are the batch of ``shard = (0, 1)``.
        """
        if self.unlabeled is None:
            yield from self.train.batches(batch, seed, epoch, limit=limit, shard=shard)
            return
        n = len(self.unlabeled)
        if n == 0:
            raise ConfigError("the unlabeled frame set is empty")
        order = np.random.default_rng([seed, epoch, 29]).permutation(n)
        pos = 0
        for lab_idx in self.train.batch_indices(batch, seed, epoch, limit=limit):
            take = len(lab_idx)
            idx = order[np.arange(pos, pos + take) % n]
            pos += take
            part = shard_slice(take, *shard)
            if part is None:
                continue
            lab, unl = self.train.batch(lab_idx[part]), self.unlabeled.batch(idx[part])
            yield {"labeled": lab, "unlabeled": {k: unl[k] for k in UNLABELED_KEYS if k in unl}}


class DataSource(ABC):
    """Gives a run its rig, grid and frames."""

    #: short name for messages
    name: ClassVar[str] = "data"
    #: :meth:`DataNeeds.extras` this source can provide
    supports: ClassVar[frozenset[str]] = frozenset()

    def check(self, needs: DataNeeds) -> None:
        """Raise ConfigError if ``needs`` asks for something this source cannot provide."""
        missing = sorted(needs.extras() - self.supports)
        if missing:
            raise ConfigError(f"the {self.name} data source cannot provide {missing}, which the method needs")

    @abstractmethod
    def rig_grid(self, cfg: "TrainConfig") -> tuple[Rig, BevGrid]:
        """The rig and BEV grid the run trains for."""

    @abstractmethod
    def load(self, cfg: "TrainConfig", rig: Rig, grid: BevGrid, needs: DataNeeds,
             log: Callable[[str], None]) -> TrainData:
        """The run's frames, honouring ``needs`` (call :meth:`check` first)."""


class SynthSource(DataSource):
    """Seeded synthetic drives of the preset rig (``cfg.train_drives`` / held-out seeds), cached;
    unlabeled frames from ``cfg.unlabeled_drives`` more drives (style ``cfg.unlabeled_style``).
    """

    name = "synthetic"
    supports = frozenset({"rgb", "unlabeled", "sequences", "poses"})

    @override
    def rig_grid(self, cfg: "TrainConfig") -> tuple[Rig, BevGrid]:
        if cfg.bag:
            raise ConfigError("training on bags needs the bag data source (the bev-train command passes it)")
        if cfg.rig == RANDOM_RIGS:  # the model is built for the first training drive's rig
            return random_rig(train_seeds(cfg.seed, 1)[0]), cfg.grid
        return preset_rig(cfg.rig), cfg.grid

    @override
    def load(self, cfg: "TrainConfig", rig: Rig, grid: BevGrid, needs: DataNeeds,
             log: Callable[[str], None]) -> TrainData:
        self.check(needs)
        if cfg.rig == RANDOM_RIGS:
            return self._load_random(cfg, grid, needs, log)
        if needs.unlabeled and cfg.unlabeled_bag:
            raise ConfigError("unlabeled bags need the unlabeled-bag data source (the bev-train command passes it)")
        if needs.unlabeled and not (cfg.unlabeled_drives or cfg.unlabeled_real):
            raise ConfigError(f"method {cfg.method!r} also trains on unlabeled frames: set unlabeled_drives "
                              "(bev-train --unlabeled-drives N), real images (--unlabeled-real camvid:DIR) or "
                              "give unlabeled bags (--unlabeled BAG ...)")
        if (cfg.unlabeled_drives or cfg.unlabeled_real) and not needs.unlabeled:
            raise ConfigError(f"method {cfg.method!r} does not train on unlabeled frames; drop unlabeled_drives "
                              "/ unlabeled_real")
        t0 = time.time()
        rgb = None
        if needs.rgb:
            w, h = rig.cameras[0].model.image_size
            rgb = needs.image_size or (h, w)
        train = synth_frameset(rig, grid, cfg.class_names, train_seeds(cfg.seed, cfg.train_drives),
                               cfg.frames_per_drive, cfg.stride, cfg.cache, needs.image_size, progress=cfg.progress,
                               rgb=rgb, style=cfg.style)
        val = synth_frameset(rig, grid, cfg.class_names, cfg.held_out_seeds, cfg.frames_per_drive, cfg.stride,
                             cfg.cache, needs.image_size, progress=cfg.progress, rgb=rgb, style=cfg.style)
        unlabeled, parts = None, []
        if needs.unlabeled and cfg.unlabeled_drives:
            parts.append(synth_frameset(rig, grid, cfg.class_names, cfg.unlabeled_seeds, cfg.frames_per_drive,
                                        cfg.stride, cfg.cache, needs.image_size, progress=cfg.progress, rgb=rgb,
                                        style=cfg.unlabeled_style or cfg.style))
        if needs.unlabeled and cfg.unlabeled_real:
            from .real_unlabeled import join_unlabeled, real_unlabeled_frameset  # noqa: PLC0415

            parts.append(real_unlabeled_frameset(cfg.unlabeled_real, rig, needs, cfg.unlabeled_real_frames))
            log(f"data: {len(parts[-1])} real unlabeled frames from {cfg.unlabeled_real}")
            parts = [join_unlabeled(parts)]
        if parts:
            unlabeled = parts[0]
        extra = "" if unlabeled is None else f" / {len(unlabeled)} unlabeled"
        log(f"data: {len(train)} training{extra} / {len(val)} held-out frames ({time.time() - t0:.1f} s)")
        return with_window(TrainData(train, val, unlabeled), needs)


    @staticmethod
    def _load_random(cfg: "TrainConfig", grid: BevGrid, needs: DataNeeds, log: Callable[[str], None]) -> TrainData:
        """Training and held-out drives, each seen by its own random rig (:mod:`.multirig`):
        label images at camera size, no RGB, single frames.
        """
        if needs.rgb or needs.unlabeled or needs.sequence_length > 1 or needs.poses:
            raise ConfigError(f"random rigs give single labeled frames of label images; method {cfg.method!r} "
                              "needs more (RGB, unlabeled frames or sequences)")
        t0 = time.time()
        train = random_rig_frameset(grid, cfg.class_names, train_seeds(cfg.seed, cfg.train_drives),
                                    cfg.frames_per_drive, cfg.stride, cfg.cache, log)
        val = random_rig_frameset(grid, cfg.class_names, cfg.held_out_seeds, cfg.frames_per_drive, cfg.stride,
                                  cfg.cache, log)
        log(f"data: {len(train)} training / {len(val)} held-out frames of random rigs ({time.time() - t0:.1f} s)")
        return TrainData(train, val)


class InMemorySource(DataSource):
    """FrameSets already in memory (stored at the size the method needs), for the preset rig;
    ``unlabeled`` frames (their GT is never read) when given; RGB when every set holds it.
    """

    name = "in-memory"

    def __init__(self, train: FrameSet, val: FrameSet, unlabeled: FrameSet | None = None) -> None:
        self.data = TrainData(train, val, unlabeled)
        sets = [s for s in (train, val, unlabeled) if s is not None]
        extras = {"unlabeled"} if unlabeled is not None else set()
        if all(s.rgb is not None for s in sets):
            extras.add("rgb")
        if all(s.poses is not None for s in sets):
            extras |= {"poses", "sequences"}
        self.supports = frozenset(type(self).supports | extras)

    @override
    def rig_grid(self, cfg: "TrainConfig") -> tuple[Rig, BevGrid]:
        return preset_rig(cfg.rig), cfg.grid

    @override
    def load(self, cfg: "TrainConfig", rig: Rig, grid: BevGrid, needs: DataNeeds,
             log: Callable[[str], None]) -> TrainData:
        self.check(needs)
        return with_window(self.data, needs)


def with_window(data: TrainData, needs: DataNeeds) -> TrainData:
    """``data`` with every frame set's :attr:`~.data.FrameSet.window` set to ``needs.sequence_length``."""
    for fs in (data.train, data.val, data.unlabeled):
        if fs is not None:
            fs.window = needs.sequence_length
    return data


__all__ = ["UNLABELED_KEYS", "DataNeeds", "DataSource", "InMemorySource", "SynthSource", "TrainData"]
