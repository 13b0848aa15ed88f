"""Seeded random rigs (issue #38): a function of the seed, inside the configured ranges, named by
the seed, and built by name like the presets.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.random_rig import (
    ASPECTS,
    RandomRigConfig,
    check_rig_name,
    random_rig,
    rig_by_name,
)
from bev_mapper_core.geometry.rig import preset_rig


def test_a_random_rig_is_a_function_of_its_seed():
    a, b = random_rig(12), random_rig(12)
    assert a == b and a.name == "random-12"
    others = [random_rig(s) for s in range(13, 20)]
    assert any(len(r.cameras) != len(a.cameras) for r in others)
    assert len({r.cameras[0].model.image_size for r in others}) > 1


def test_cameras_lie_in_the_configured_ranges():
    cfg = RandomRigConfig()
    counts = set()
    for s in range(40):
        rig = random_rig(s, cfg)
        counts.add(len(rig.cameras))
        assert cfg.cameras[0] <= len(rig.cameras) <= cfg.cameras[1]
        sizes = {c.model.image_size for c in rig.cameras}
        assert len(sizes) == 1  # one sensor model a rig
        w, h = sizes.pop()
        assert cfg.width_px[0] <= w <= cfg.width_px[1]
        assert min(abs(w / h - a) for a in ASPECTS) < 0.02
        for c in rig.cameras:
            T = c.ego_from_cam_array
            assert cfg.height_m[0] - 0.11 <= T[2, 3] <= cfg.height_m[1] + 0.11
            f = c.model.K_array[0, 0]
            hfov = math.degrees(2 * math.atan(w / 2 / f))
            assert cfg.hfov_deg[0] - 1e-6 <= hfov <= cfg.hfov_deg[1] + 1e-6
            optical_z = T[:3, 2]  # the viewing direction in base_link
            assert -math.sin(math.radians(cfg.pitch_deg[1])) - 1e-6 <= optical_z[2] <= \
                -math.sin(math.radians(cfg.pitch_deg[0])) + 1e-6
        look = rig.cameras[0].ego_from_cam_array[:3, 2]
        assert look[0] > 0.9  # the first camera looks forward
    assert counts == set(range(cfg.cameras[0], cfg.cameras[1] + 1))


def test_rigs_by_name_and_bad_names():
    assert rig_by_name("surround6") == preset_rig("surround6")
    assert rig_by_name("random-3") == random_rig(3)
    assert check_rig_name("random-900000001") == "random-900000001"
    for bad in ("random", "random-x", "mine", "random--1"):
        with pytest.raises(ConfigError, match="random-<seed>"):
            check_rig_name(bad)
    with pytest.raises(ConfigError):
        random_rig(-1)
    with pytest.raises(ConfigError):
        RandomRigConfig(cameras=(3, 2))
    with pytest.raises(ConfigError):
        RandomRigConfig(hfov_deg=(60.0, 179.0))


def test_a_narrow_config_gives_what_it_asks():
    cfg = RandomRigConfig(cameras=(5, 5), hfov_deg=(70.0, 70.0), width_px=(400, 400), height_m=(1.5, 1.5))
    rig = random_rig(4, cfg)
    assert len(rig.cameras) == 5
    yaws = sorted(math.degrees(math.atan2(c.ego_from_cam_array[1, 2], c.ego_from_cam_array[0, 2])) % 360
                  for c in rig.cameras)
    gaps = np.diff(yaws + [yaws[0] + 360])
    assert np.all(gaps > 72 - 2 * cfg.yaw_jitter_deg - 1e-6)  # spread around the vehicle
