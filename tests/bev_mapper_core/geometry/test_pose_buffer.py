"""Ego poses at an image's stamp (bev_mapper_core/geometry/pose_buffer.py): interpolation (linear
translation, slerp rotation), gaps and ends without a pose, time going back, bad poses."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.pose_buffer import PoseBuffer, PoseBufferConfig
from bev_mapper_core.geometry.transforms import rpy_to_rot, yaw_of

MS = 1_000_000


def pose(x=0.0, y=0.0, yaw=0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = rpy_to_rot(0.0, 0.0, yaw)
    T[:3, 3] = (x, y, 0.0)
    return T


def test_between_two_poses_translation_is_linear_and_yaw_turns_evenly():
    b = PoseBuffer()
    b.add(100 * MS, pose(0.0, 0.0, 0.0))
    b.add(200 * MS, pose(2.0, 1.0, math.radians(30)))
    T = b.at(125 * MS)
    np.testing.assert_allclose(T[:3, 3], [0.5, 0.25, 0.0], atol=1e-9)
    assert yaw_of(T) == pytest.approx(math.radians(7.5), abs=1e-9)
    np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)  # still a rotation
    np.testing.assert_allclose(b.at(200 * MS), pose(2.0, 1.0, math.radians(30)), atol=1e-12)
    # across +-180 degrees: the short way round
    c = PoseBuffer()
    c.add(0, pose(yaw=math.radians(170)))
    c.add(100 * MS, pose(yaw=math.radians(-170)))
    assert abs(yaw_of(c.at(50 * MS))) == pytest.approx(math.pi, abs=1e-9)


def test_no_pose_outside_the_span_or_across_a_long_gap():
    b = PoseBuffer(PoseBufferConfig(max_gap_s=0.5, max_extrapolation_s=0.05))
    assert b.at(0) is None  # empty
    b.add(1000 * MS, pose(1.0))
    b.add(1100 * MS, pose(2.0))
    b.add(2000 * MS, pose(3.0))  # 0.9 s after the previous one
    assert b.at(1140 * MS) is None  # inside the long gap
    np.testing.assert_allclose(b.at(1030 * MS)[:3, 3], [1.3, 0, 0], atol=1e-9)
    np.testing.assert_allclose(b.at(960 * MS)[:3, 3], [1.0, 0, 0])  # 40 ms before the first: that pose
    assert b.at(940 * MS) is None and b.at(2060 * MS) is None  # farther out: none


def test_time_going_back_empties_the_buffer_and_bad_poses_are_refused():
    b = PoseBuffer()
    b.add(500 * MS, pose(5.0))
    b.add(600 * MS, pose(6.0))
    b.add(100 * MS, pose(1.0))  # a bag loop
    assert len(b) == 1 and b.at(550 * MS) is None
    b.add(100 * MS, pose(1.5))  # the same stamp again: replaced
    assert len(b) == 1 and b.at(100 * MS)[0, 3] == 1.5
    for bad in (np.eye(3), np.full((4, 4), np.nan), np.diag([2.0, 1.0, 1.0, 1.0])):
        with pytest.raises(ConfigError, match="rigid"):
            b.add(700 * MS, bad)
    assert len(b) == 1
    small = PoseBuffer(PoseBufferConfig(size=3, max_extrapolation_s=0.0))
    for i in range(5):
        small.add(i * 10 * MS, pose(float(i)))
    assert len(small) == 3 and small.at(15 * MS) is None and small.at(20 * MS)[0, 3] == 2.0  # the oldest went
    for bad in ({"size": 1}, {"max_gap_s": -1.0}, {"max_extrapolation_s": float("inf")}):
        with pytest.raises(ConfigError):
            PoseBufferConfig(**bad)
