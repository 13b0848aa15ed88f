"""The synthetic world: road network, ground raster, objects and the ego trajectory.

Everything is drawn from ``SynthConfig.seed`` through independent random streams, so the same
config always builds the same world (bit for bit) and different seeds build different towns.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..geometry.transforms import make_transform, rpy_to_rot
from .config import SynthConfig
from .objects import Boxes
from .populate import (
    Catalog,
    add_buildings,
    add_furniture,
    add_moving_cars,
    add_parked_cars,
    add_pedestrians,
)
from .raster import GroundRaster, ground_features
from .roads import RoadNetwork
from .trajectory import PathMotion


def _rng(seed: int, stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, stream])


@dataclass
class World:
    """A built world for one drive of ``config.frames`` frames.

    Attributes:
        net: the road network.
        ground: the flat ground raster (labels + materials).
        ego: ``(T, 3)`` base_link pose ``(x, y, yaw)`` in ``odom`` per frame.
        ego_speed, ego_yaw_rate: ``(T,)`` m/s and rad/s per frame.
        parts: every object part in its object's frame (``parts.obj`` = object id).
        obj_pose: ``(N_obj, 3)`` pose of each object at frame 0 (static ones never move).
        tracks: ``{object id: (T, 3) pose per frame}`` of the moving objects; NaN while an
            object is absent (movers come and go out of the ego's sight).
    """

    config: SynthConfig
    net: RoadNetwork
    ground: GroundRaster
    ego: np.ndarray
    ego_speed: np.ndarray
    ego_yaw_rate: np.ndarray
    parts: Boxes
    obj_pose: np.ndarray
    tracks: dict

    def __post_init__(self) -> None:
        self._dyn_ids = np.array(sorted(self.tracks), dtype=np.int64)
        self._dyn_pose = (np.stack([self.tracks[i] for i in self._dyn_ids])
                          if len(self._dyn_ids) else np.zeros((0, len(self.ego), 3)))

    @property
    def frames(self) -> int:
        """Number of ego poses (frames) of the drive."""
        return len(self.ego)

    def ego_pose(self, k: int) -> np.ndarray:
        """``world_from_ego`` (4x4, odom <- base_link) of frame ``k``."""
        x, y, yaw = self.ego[k]
        return make_transform(rpy_to_rot(0.0, 0.0, yaw), (x, y, 0.0))

    def ego_pose_after(self, k: int, dt_s: float) -> np.ndarray:
        """``world_from_ego`` ``dt_s`` seconds after frame ``k``: x, y and yaw linear between the
        frames' poses (the last frame's segment extended past the end).
        """
        if dt_s == 0.0 or self.frames < 2:
            return self.ego_pose(k)
        a = min(k, self.frames - 2)
        f = (k - a) + dt_s * self.config.rate_hz  # fraction of the segment a -> a + 1
        (x0, y0, w0), (x1, y1, w1) = self.ego[a], self.ego[a + 1]
        dw = (w1 - w0 + math.pi) % (2 * math.pi) - math.pi  # the short way round
        return make_transform(rpy_to_rot(0.0, 0.0, w0 + f * dw), (x0 + f * (x1 - x0), y0 + f * (y1 - y0), 0.0))

    def object_poses(self, k: int) -> np.ndarray:
        """``(N_obj, 3)`` pose of every object at frame ``k`` (NaN: absent)."""
        pose = self.obj_pose.copy()
        if len(self._dyn_ids):
            pose[self._dyn_ids] = self._dyn_pose[:, k]
        return pose

    def boxes_at(self, k: int, radius: float | None = None) -> Boxes:
        """World-frame boxes of frame ``k``; with ``radius``, only those reaching within
        ``radius`` m of the ego.
        """
        pose = self.object_poses(k)
        p = self.parts.subset(np.isfinite(pose[self.parts.obj, 0]))  # present objects only
        op = pose[p.obj]  # (N_parts, 3)
        c, s = np.cos(op[:, 2]), np.sin(op[:, 2])
        center = op[:, :2] + np.stack([c * p.center[:, 0] - s * p.center[:, 1],
                                       s * p.center[:, 0] + c * p.center[:, 1]], 1)
        boxes = Boxes(center, p.z0, p.size, op[:, 2] + p.yaw, p.label, p.color, p.kind, p.obj)
        if radius is None:
            return boxes
        d = np.hypot(*(center - self.ego[k, :2]).T) - p.radius()
        return boxes.subset(d <= radius)


def build_world(config: SynthConfig) -> World:
    """Build the world of a drive: network, ground, ego trajectory, objects."""
    seed = config.seed
    net = RoadNetwork(_rng(seed, 1))
    ground = GroundRaster(ground_features(net, _rng(seed, 2)), net.bounds, res=config.raster_resolution)
    times = np.arange(config.frames) / config.rate_hz
    ego, speed, yaw_rate = _ego_track(net, config, _rng(seed, 3), times)
    cat = Catalog()
    add_parked_cars(net, cat, _rng(seed, 4), config.vehicle_density)
    add_furniture(net, cat, _rng(seed, 5), config.obstacle_density)
    add_buildings(net, cat, _rng(seed, 6), config.building_density, ground)
    tracks: dict = {}
    far = config.cull_distance + 10.0  # movers appear and vanish only out of sight
    vehicles = add_moving_cars(net, cat, _rng(seed, 7), config.vehicle_density, times, ego, tracks,
                               far)
    add_pedestrians(net, cat, _rng(seed, 8), config.pedestrian_density, times, ego, vehicles,
                    tracks, far)
    parts = cat.boxes() if cat.parts else Boxes.make(np.zeros((0, 2)), 0, 0, 0, 0, 0)
    obj_pose = np.array(cat.poses, np.float64).reshape(-1, 3)  # (N_obj, 3), also when empty
    return World(config, net, ground, ego, speed, yaw_rate, parts, obj_pose, tracks)


def _ego_track(net: RoadNetwork, config: SynthConfig, rng, times: np.ndarray):
    """Ego ``(T, 3)`` poses, speeds and yaw rates: lane following from a random lane."""
    long_roads = [r for r in net.roads if r.length >= 45.0] or [max(net.roads, key=lambda r: r.length)]
    r = long_roads[int(rng.integers(len(long_roads)))]
    d, k = int(rng.choice([-1, 1])), int(rng.integers(r.lanes))
    length = config.duration_s * config.max_speed + 30.0
    route = net.route(rng, r.index, d, k, rng.uniform(0.25, 0.55) * r.length, length,
                      config.turn_probability)
    cap = net.intersection_caps(route, rng, config.min_speed + 1.0, config.min_speed + 5.0)
    motion = PathMotion(route, config.min_speed, config.max_speed, rng,
                        a_acc=rng.uniform(1.0, 2.0), a_dec=rng.uniform(1.5, 3.0), cap=cap)
    x, y, yaw, v, w = motion.sample(times)
    yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
    return np.stack([x, y, yaw], 1), v, w
