"""Seeded random camera rigs: the rigs a rig-free model trains on, and held-out rigs to score it.

A model that reads the calibration instead of memorising it (Bi-Mapper's LV stream with the IPM
skip: every parameter is shared by the cameras, the geometry comes from the tables) has to see
many rigs in training, or it learns one. :func:`random_rig` draws one from
:class:`RandomRigConfig`'s ranges: the number of cameras, where they sit on the vehicle body,
their yaw, pitch, roll and height, the horizontal field of view and the image aspect ratio.
The draw is a function of the seed alone, so a rig is named by it: ``random-<seed>``
(:func:`rig_by_name` builds presets and these alike, e.g. ``bev-bag synth --rig random-7``).

Training rigs and held-out rigs are disjoint by seed (as drives are): see
:data:`HELD_OUT_RIG_SEED_BASE`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError
from .camera import CameraModel
from .rig import PRESETS, Rig, RigCamera, preset_rig
from .transforms import ego_from_optical

#: ``random-<seed>`` rigs from this seed on are never trained on (``bev-train --rig random``
#: draws its training rigs from the run's drive seeds, all below it).
HELD_OUT_RIG_SEED_BASE = 900_000_000
RANDOM_PREFIX = "random-"
#: ``bev-train --rig random``: every drive its own random rig (the rig of drive ``s`` is
#: ``random-<s>``), for a rig-free model.
RANDOM_RIGS = "random"
#: Image aspect ratios (width / height) a random camera draws from: 4:3, 16:9, the 1.59:1 of
#: 1936x1216 automotive sensors, 16:10, 2:1.
ASPECTS = (4 / 3, 16 / 9, 1936 / 1216, 16 / 10, 2.0)


@dataclass(frozen=True)
class RandomRigConfig:
    """The ranges a random rig is drawn from (uniform unless said otherwise).

    Args:
        cameras: (min, max) number of cameras.
        hfov_deg: (min, max) horizontal field of view of each camera, degrees.
        height_m: (min, max) mounting height above the ground, metres (one per rig, each
            camera +-0.1 m).
        pitch_deg: (min, max) downward pitch, degrees.
        roll_deg: largest absolute roll, degrees.
        yaw_jitter_deg: largest deviation of each camera's yaw from an even spread around the
            vehicle (the first camera looks forward), degrees.
        width_px: (min, max) delivered image width, pixels (the height follows the aspect).
        body: (length, width) of the vehicle body the cameras sit on, metres; ``base_link`` is
            at the rear axle, the body reaches 0.9 m behind it.
    """

    cameras: tuple[int, int] = (1, 7)
    hfov_deg: tuple[float, float] = (50.0, 120.0)
    height_m: tuple[float, float] = (1.2, 2.2)
    pitch_deg: tuple[float, float] = (-2.0, 14.0)
    roll_deg: float = 2.0
    yaw_jitter_deg: float = 15.0
    width_px: tuple[int, int] = (320, 480)
    body: tuple[float, float] = (4.6, 1.9)

    def __post_init__(self) -> None:
        for name in ("cameras", "hfov_deg", "height_m", "pitch_deg", "width_px"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo <= hi and (lo >= 0 or name == "pitch_deg")):
                raise ConfigError(f"{name} must be (min, max) with min <= max (>= 0 but for pitch), got {(lo, hi)!r}")
        if self.cameras[0] < 1 or self.hfov_deg[1] >= 170 or self.width_px[0] < 32:
            raise ConfigError("random rigs need >= 1 camera, a field of view < 170 degrees and >= 32 px images")


def random_rig(seed: int, config: RandomRigConfig = RandomRigConfig()) -> Rig:
    """The rig ``random-<seed>``: a function of ``seed`` and ``config`` alone.

    Cameras are spread evenly in yaw around the vehicle (the first looks forward), each moved by
    up to ``yaw_jitter_deg``; each sits on the body's outline where its viewing direction leaves
    the body, at the rig's height. All cameras deliver one image size (one aspect ratio a rig);
    each has its own field of view; intrinsics are pinhole without distortion, principal point
    near the image centre.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"a random rig's seed must be an integer >= 0, got {seed!r}")
    rng = np.random.default_rng([int(seed), 7177])
    c = config
    n = int(rng.integers(c.cameras[0], c.cameras[1] + 1))
    height = float(rng.uniform(*c.height_m))
    length, width = c.body
    aspect = ASPECTS[int(rng.integers(len(ASPECTS)))]  # one image size a rig (as most rigs: one sensor model)
    w = int(rng.integers(c.width_px[0] // 2, c.width_px[1] // 2 + 1)) * 2
    h = max(2, int(round(w / aspect / 2)) * 2)
    cams = []
    for i in range(n):
        yaw = 2 * math.pi * i / n + math.radians(float(rng.uniform(-1, 1)) * c.yaw_jitter_deg) * (i > 0)
        yaw = math.atan2(math.sin(yaw), math.cos(yaw))
        # where the viewing direction leaves the body's rectangle (centre 1.4 m ahead of base_link)
        dx, dy = math.cos(yaw), math.sin(yaw)
        s = min(length / 2 / max(abs(dx), 1e-6), width / 2 / max(abs(dy), 1e-6))
        xyz = (1.4 + 0.8 * s * dx, 0.8 * s * dy, height + float(rng.uniform(-0.1, 0.1)))
        pitch = math.radians(float(rng.uniform(*c.pitch_deg)))
        roll = math.radians(float(rng.uniform(-1, 1)) * c.roll_deg)
        hfov = math.radians(float(rng.uniform(*c.hfov_deg)))
        f = (w / 2) / math.tan(hfov / 2)
        cx, cy = w / 2 + float(rng.uniform(-0.02, 0.02)) * w, h / 2 + float(rng.uniform(-0.02, 0.02)) * h
        model = CameraModel(K=((f, 0.0, cx), (0.0, f, cy), (0.0, 0.0, 1.0)), D=(0.0,) * 5, width=w, height=h)
        cams.append(RigCamera(f"cam{i}", model, ego_from_optical(xyz, yaw=yaw, pitch=pitch, roll=roll)))
    return Rig(f"{RANDOM_PREFIX}{int(seed)}", tuple(cams))


def is_random_rig_name(name: str) -> bool:
    """``name`` is ``random-<seed>``."""
    return name.startswith(RANDOM_PREFIX) and name[len(RANDOM_PREFIX):].isdigit()


def rig_by_name(name: str) -> Rig:
    """A preset rig (:data:`~.rig.PRESETS`) or a random one, ``random-<seed>``.

    Raises:
        ConfigError: neither.
    """
    if is_random_rig_name(name):
        return random_rig(int(name[len(RANDOM_PREFIX):]))
    if name in PRESETS:
        return preset_rig(name)
    raise ConfigError(f"unknown rig {name!r}; presets: {sorted(PRESETS)}, or random-<seed> (a seeded random rig)")


def check_rig_name(name: str) -> str:
    """``name`` if :func:`rig_by_name` knows it (an argparse ``type``), else ConfigError."""
    if not (name in PRESETS or is_random_rig_name(name)):
        rig_by_name(name)
    return name


__all__ = ["ASPECTS", "HELD_OUT_RIG_SEED_BASE", "RANDOM_RIGS", "RandomRigConfig", "check_rig_name", "is_random_rig_name",
           "random_rig", "rig_by_name"]
