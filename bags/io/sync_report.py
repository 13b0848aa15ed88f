"""What the synchronization of a bag's cameras did: sets, cameras missing from them, split frames.

:class:`SyncReport` is filled by :meth:`bags.io.reader.BagReader.frames` as it yields frames and
goes into ``metrics.json`` (key ``sync``) and the replay's summary: a camera that never appears
in a bag, or a rig whose cameras fire further apart than the window, is said, not silent.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field


@dataclass
class SyncReport:
    """Counts over the synchronized sets yielded so far.

    Attributes:
        cameras: the rig's cameras, in rig order.
        sets: sets yielded.
        complete: sets with every camera.
        missing_by_camera: camera -> sets that lacked it (absent, or its image did not decode).
        split: frames whose cameras spread wider than the window, yielded as two partial sets
            (:attr:`msg_adapters.sync.SyncStats.split`).
        window_ms: the synchronizer's window (its latest value: it narrows to half the measured
            frame period when that is shorter).
        cameras_without_images: cameras of the rig with no image topic in the bag at all.
    """

    cameras: tuple[str, ...] = ()
    sets: int = 0
    complete: int = 0
    missing_by_camera: dict[str, int] = field(default_factory=dict)
    split: int = 0
    window_ms: float = 0.0
    cameras_without_images: tuple[str, ...] = ()

    def add(self, valid: Mapping[str, bool], sync=None) -> None:
        """Count one yielded set (``valid``: camera -> present); ``sync``: its synchronizer."""
        self.sets += 1
        missing = [c for c, ok in valid.items() if not ok]
        if not missing:
            self.complete += 1
        for c in missing:
            self.missing_by_camera[c] = self.missing_by_camera.get(c, 0) + 1
        if sync is not None:
            self.split = sync.stats.split
            self.window_ms = sync.window_ns / 1e6

    @property
    def partial(self) -> int:
        """Sets mapped without some camera."""
        return self.sets - self.complete

    def summary(self) -> str | None:
        """One sentence for the user, ``None`` when every set had every camera."""
        if not self.partial:
            return None
        parts = [f"{self.partial} of {self.sets} set(s) were mapped without some camera ("
                 + ", ".join(f"{c}: {n}" for c, n in self.missing_by_camera.items()) + ")"]
        if self.cameras_without_images:
            parts.append(f"camera(s) {list(self.cameras_without_images)} have no image topic in the bag")
        if self.split:
            parts.append(f"{self.split} frame(s) were split in two: their cameras' stamps spread wider than the "
                         f"{self.window_ms:.0f} ms window (widen it with --sync-slop-ms)")
        return "; ".join(parts)

    def to_metrics(self) -> dict:
        """The ``metrics.json`` value (key ``sync``)."""
        return {
            "sets": self.sets,
            "complete_sets": self.complete,
            "partial_sets": self.partial,
            "missing_by_camera": {c: self.missing_by_camera.get(c, 0) for c in self.cameras},
            "split_frames": self.split,
            "window_ms": round(self.window_ms, 3),
            "cameras_without_images": list(self.cameras_without_images),
        }
