"""Typed, frozen configuration of the synthetic drive generator."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from ..errors import ConfigError
from .styles import MIXED, check_style

#: Stamp of frame 0: 1_700_000_000 s after the Unix epoch, in nanoseconds.
EPOCH_NS = 1_700_000_000 * 1_000_000_000


@dataclass(frozen=True)
class SynthConfig:
    """Knobs of a synthetic drive.

    Args:
        frames: number of frames to generate.
        seed: seed of everything random (layout, objects, look, noise, trajectory, and the
            style ``mixed`` picks).
        rate_hz: frame rate.
        jitter_ms: max abs per-camera stamp offset from the frame stamp (for the bag writer).
        stagger_ms: the cameras fire this far apart (issue #38): camera ``i`` of ``N`` (rig order)
            at ``i / (N - 1) * stagger_ms`` after the frame stamp, rendered at the ego pose of that
            time (interpolated between the frames' poses; other objects as at the frame) and
            stamped so; GT, visibility and odometry stay at the frame stamp. 0 = every camera at
            the frame's pose (the drives before it, bit for bit).
        vehicle_density: multiplier of the number of parked and moving vehicles (0 = none).
        pedestrian_density: multiplier of the number of pedestrians (0 = none).
        obstacle_density: multiplier of poles, cones and bins on sidewalks (0 = none).
        building_density: probability scale of a building plot being built (0 = none).
        min_speed, max_speed: ego speed range in m/s.
        turn_probability: chance of turning at an intersection where going straight is possible.
        image_noise: scale of the RGB sensor noise (0 = noise free).
        cull_distance: objects farther than this from the ego (m) are not rendered.
        raster_resolution: cell size (m) of the world ground raster near the ego.
        style: appearance style (:mod:`~bev_mapper_core.synth.styles`): a style name, or
            ``"mixed"`` (one of the training styles per seed, never the held-out one). Changes
            the RGB images only.
    """

    frames: int = 50
    seed: int = 0
    rate_hz: float = 10.0
    jitter_ms: float = 0.0
    stagger_ms: float = 0.0
    vehicle_density: float = 1.0
    pedestrian_density: float = 1.0
    obstacle_density: float = 1.0
    building_density: float = 1.0
    min_speed: float = 5.0
    max_speed: float = 14.0
    turn_probability: float = 0.35
    image_noise: float = 1.0
    cull_distance: float = 70.0
    raster_resolution: float = 0.05
    style: str = MIXED

    def __post_init__(self) -> None:
        check_style(self.style)
        for f in fields(self):
            if f.name == "style":
                continue
            v = getattr(self, f.name)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(f"SynthConfig.{f.name} must be a number, got {v!r}")
            if not math.isfinite(v):
                raise ConfigError(f"SynthConfig.{f.name} must be finite, got {v}")
        if not isinstance(self.frames, int) or self.frames < 1:
            raise ConfigError(f"frames must be an integer >= 1, got {self.frames!r}")
        if not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed must be an integer >= 0, got {self.seed!r}")
        if not 0.1 <= self.rate_hz <= 1000.0:
            raise ConfigError(f"rate_hz must be in [0.1, 1000], got {self.rate_hz}")
        if self.jitter_ms < 0 or self.jitter_ms * 1e-3 >= 0.5 / self.rate_hz:
            raise ConfigError(
                f"jitter_ms must be >= 0 and below half the frame period, got {self.jitter_ms}"
            )
        if self.stagger_ms < 0 or (self.stagger_ms + self.jitter_ms) * 1e-3 >= 0.5 / self.rate_hz:
            raise ConfigError(f"stagger_ms must be >= 0 and, with jitter_ms, below half the frame period, "
                              f"got {self.stagger_ms}")
        for name in ("vehicle_density", "pedestrian_density", "obstacle_density", "building_density"):
            if not 0.0 <= getattr(self, name) <= 5.0:
                raise ConfigError(f"{name} must be in [0, 5], got {getattr(self, name)}")
        if not 0.5 <= self.min_speed <= self.max_speed <= 30.0:
            raise ConfigError(
                f"need 0.5 <= min_speed <= max_speed <= 30 m/s, got {self.min_speed}, {self.max_speed}"
            )
        if not 0.0 <= self.turn_probability <= 1.0:
            raise ConfigError(f"turn_probability must be in [0, 1], got {self.turn_probability}")
        if not 0.0 <= self.image_noise <= 10.0:
            raise ConfigError(f"image_noise must be in [0, 10], got {self.image_noise}")
        if not 5.0 <= self.cull_distance <= 500.0:
            raise ConfigError(f"cull_distance must be in [5, 500] m, got {self.cull_distance}")
        if not 0.01 <= self.raster_resolution <= 0.2:
            raise ConfigError(
                f"raster_resolution must be in [0.01, 0.2] m, got {self.raster_resolution}"
            )

    @property
    def duration_s(self) -> float:
        """Time from the first to the last frame, in seconds."""
        return (self.frames - 1) / self.rate_hz

    def frame_stamp_ns(self, index: int) -> int:
        """Stamp of frame ``index`` in nanoseconds."""
        return EPOCH_NS + int(round(index * 1e9 / self.rate_hz))
