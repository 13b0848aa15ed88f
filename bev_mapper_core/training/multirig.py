"""Frames of many rigs in one training set: what ``bev-train --rig random`` trains on.

A rig-free model (Bi-Mapper without the GV stream, :attr:`~bev_mapper_core.methods.bimapper.model.BiMapper.rig_free`)
reads the calibration from its tables, so it can learn from drives of many rigs, but one batch
must share one rig (one set of tables; the cameras' count and image size differ between rigs).
:class:`MultiRigFrames` holds one :class:`~.data.FrameSet` per rig and offers the FrameSet
interface the trainer and the scoring loop use: every batch comes from one rig and carries it as
``batch["rig"]`` (the method switches its model's tables with it); the epoch's batches of all
rigs are shuffled together.

:func:`random_rig_frameset` loads (rendering and caching as usual) the drives of seeded random
rigs (:func:`~bev_mapper_core.geometry.random_rig.random_rig`): drive ``s`` is driven by rig
``random-<s>``, so training drives (seeds below 900000000) and held-out drives (900000000 on)
have disjoint rigs as well as disjoint worlds.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence

import numpy as np

from ..errors import ConfigError
from ..geometry.grid import BevGrid
from ..geometry.random_rig import random_rig
from ..geometry.rig import Rig
from .data import FrameSet, shard_slice, synth_frameset


class _Joined:
    """Read-only ``a[i]`` over the concatenation of several arrays (no copy)."""

    def __init__(self, arrays: Sequence[np.ndarray]) -> None:
        self.arrays = list(arrays)
        self.offsets = np.cumsum([0] + [len(a) for a in arrays])

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def __getitem__(self, i: int) -> np.ndarray:
        p = int(np.searchsorted(self.offsets, i, side="right") - 1)
        return self.arrays[p][i - self.offsets[p]]


class MultiRigFrames:
    """One :class:`FrameSet` per rig, used as one set (see the module docstring).

    Args:
        parts: ``(rig, frames)`` pairs; each FrameSet's images are that rig's cameras.
    """

    def __init__(self, parts: Sequence[tuple[Rig, FrameSet]]) -> None:
        if not parts:
            raise ConfigError("a multi-rig frame set needs at least one rig")
        self.parts = list(parts)
        self.offsets = np.cumsum([0] + [len(f) for _, f in self.parts])
        self.target = _Joined([f.target for _, f in self.parts])
        self.mask = _Joined([f.mask for _, f in self.parts])
        self.ground_mask = _Joined([f.ground_mask for _, f in self.parts])
        self.class_mask = None  # synthetic drives score every class everywhere they see
        self.camera_names: tuple[str, ...] = ()
        self.rgb = self.poses = self.stamps = self.drives = None
        self.labels = None  # no joint array: the rigs' images differ in count and size

    @property
    def rigs(self) -> list[Rig]:
        """The rigs, in part order."""
        return [r for r, _ in self.parts]

    @property
    def window(self) -> int:
        """Frames per sample: always 1 (random-rig drives train single frames)."""
        return 1

    @window.setter
    def window(self, value: int) -> None:
        if value != 1:
            raise ConfigError("frames of random rigs are single frames (no sequences)")

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def _part(self, idx: np.ndarray) -> tuple[int, np.ndarray]:
        """The one part all of ``idx`` lie in and their ids inside it."""
        p = np.searchsorted(self.offsets, idx, side="right") - 1
        if len(idx) == 0 or np.any(p != p[0]):
            raise ConfigError("a batch of a multi-rig frame set must come from one rig")
        return int(p[0]), idx - self.offsets[p[0]]

    def batch(self, idx: np.ndarray) -> dict:
        """:meth:`FrameSet.batch` of frames of one rig, plus ``rig`` (that :class:`Rig`)."""
        p, local = self._part(np.asarray(idx))
        rig, frames = self.parts[p]
        out = frames.batch(local)
        out["index"] = out["index"] + int(self.offsets[p])
        out["rig"] = rig
        return out

    def scoring_batches(self, batch: int, n: int) -> Iterator[np.ndarray]:
        """Consecutive ids ``0 .. n-1`` in batches of at most ``batch`` that never span two rigs."""
        for p in range(len(self.parts)):
            lo, hi = int(self.offsets[p]), min(int(self.offsets[p + 1]), n)
            for s in range(lo, hi, batch):
                yield np.arange(s, min(s + batch, hi))

    def batch_indices(self, batch_size: int, seed: int, epoch: int, limit: int | None = None,
                      shuffle: bool = True) -> Iterator[np.ndarray]:
        """Ids of each batch of one epoch: every rig's frames shuffled and cut into batches, the
        batches of all rigs then shuffled together (order a function of ``(seed, epoch)``); at
        most ``limit`` frames.
        """
        rng = np.random.default_rng([seed, epoch, 23])
        chunks = []
        for p in range(len(self.parts)):
            ids = np.arange(self.offsets[p], self.offsets[p + 1])
            if shuffle:
                ids = rng.permutation(ids)
            chunks += [ids[i:i + batch_size] for i in range(0, len(ids), batch_size)]
        order = rng.permutation(len(chunks)) if shuffle else np.arange(len(chunks))
        left = len(self) if limit is None else limit
        for c in order:
            if left <= 0:
                return
            yield chunks[c][:left]
            left -= len(chunks[c][:left])

    def batches(self, batch_size: int, seed: int, epoch: int, limit: int | None = None,
                shuffle: bool = True, shard: tuple[int, int] = (0, 1)) -> Iterator[dict]:
        """Batches of one epoch (see :meth:`batch_indices` and :meth:`FrameSet.batches`)."""
        for idx in self.batch_indices(batch_size, seed, epoch, limit, shuffle):
            part = shard_slice(len(idx), *shard)
            if part is not None:
                yield self.batch(idx[part])


def random_rig_frameset(grid: BevGrid, classes: Sequence[str], seeds: Sequence[int], frames: int, stride: int = 3,
                        cache_dir: str | None = None, log: Callable[[str], None] | None = None) -> MultiRigFrames:
    """The drives ``seeds``, drive ``s`` seen by rig ``random-<s>``, label images at camera size."""
    parts = []
    for s in seeds:
        rig = random_rig(int(s))
        parts.append((rig, synth_frameset(rig, grid, classes, [int(s)], frames, stride, cache_dir)))
    if log is not None:
        cams = [len(r.cameras) for r, _ in parts]
        log(f"random rigs: {len(parts)} ({min(cams)}-{max(cams)} cameras)")
    return MultiRigFrames(parts)


__all__ = ["MultiRigFrames", "random_rig_frameset"]
