"""What :class:`~bags.io.reader.BagReader` hands out: :class:`BagMessage` (one message of a
topic) and :class:`BagFrame` (one synchronized frame), and the default synchronization.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from msg_adapters import OdometryState, SyncConfig

MS = 1_000_000
#: Default synchronization of bag frames: :meth:`SyncConfig.replay` (the node's window, cameras
#: of one frame within 50 ms of each other and half the frame period; a longer timeout).
DEFAULT_SYNC = SyncConfig.replay()


@dataclass(frozen=True)
class BagMessage:
    """One deserialized message (rosbags dataclass) with its topic, type and log time."""

    topic: str
    msgtype: str
    log_ns: int
    msg: Any


@dataclass(frozen=True)
class BagFrame:
    """One synchronized frame of a bag.

    Attributes:
        index: 0-based count of yielded frames.
        stamp_ns: the frame's reference stamp: the matched GT (else odometry) header stamp,
            else the mean of the camera stamps.
        camera_stamps: per camera, the header stamp of its image (``None`` if missing).
        valid: per camera (rig order), True when all requested images are present and decoded.
        rgb, labels: per valid camera, ``(H, W, 3)`` uint8 RGB / ``(H, W)`` uint8 label ids
            (only the kinds requested).
        gt_classes: names of the GT layers, in layer order.
        gt: ``(C, H, W)`` float32 in [0, 1] (100 -> 1.0), or ``None`` if no GT matched; bool
            (the cells ``>= 0.5``) when read with ``gt_half``.
        gt_known: ``(C, H, W)`` bool, False where the layer was -1 (not visible).
        odom: the matched odometry, or ``None``.
        ground_visibility: ``(H, W)`` bool, cells whose ground point some camera sees (from
            ``/bev/visibility/ground``), or ``None`` when the bag has no such layer.
        visibility: ``(H, W)`` bool, cells some camera sees (from ``/bev/visibility/any``), or
            ``None`` when the bag has no such layer (then ``gt_known`` tells the same).
        truth: ``(C, H, W)`` float32 0/1 (bool with ``gt_half``), what is in every cell whether seen or not (from
            ``/bev/truth/<class>``, layers in ``gt_classes`` order), or ``None`` when the bag
            lacks a truth layer of one of the GT classes (bags written before they existed).
        stamp_poses: the ego pose ``world_from_ego`` (4x4) at ``stamp_ns`` and at each camera's
            stamp, interpolated in the bag's odometry (or ``/tf``), None where there is none;
            ``None`` when odometry was not asked for or the bag has none (each camera at its own
            time, :mod:`bev_mapper_core.placement`).
    """

    index: int
    stamp_ns: int
    camera_stamps: dict[str, int | None]
    valid: dict[str, bool]
    rgb: dict[str, np.ndarray]
    labels: dict[str, np.ndarray]
    gt_classes: tuple[str, ...]
    gt: np.ndarray | None
    gt_known: np.ndarray | None
    odom: OdometryState | None
    ground_visibility: np.ndarray | None = None
    visibility: np.ndarray | None = None
    truth: np.ndarray | None = None
    stamp_poses: dict[int, np.ndarray | None] | None = None

    def pose_at(self, stamp_ns: int) -> np.ndarray | None:
        """The ego pose at one of the frame's stamps (:attr:`stamp_poses`), else None."""
        return None if self.stamp_poses is None else self.stamp_poses.get(int(stamp_ns))

    @property
    def valid_mask(self) -> np.ndarray:
        """Validity as a bool array in rig order."""
        return np.array(list(self.valid.values()), dtype=bool)

