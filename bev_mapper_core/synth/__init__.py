"""Procedural, seeded synthetic drives standing in for recorded bags.

``generate_drive(rig, grid, SynthConfig(...))`` yields :class:`SynthFrame` s: per camera an RGB
and a semantic label image rendered by ray casting a procedural town (roads, lanes, crossings,
curbs, sidewalks, cars, pedestrians, street furniture, buildings), the ego pose and velocities,
and BEV ground truth with a visibility mask, all from the same world.
"""

from .config import SynthConfig
from .drive import CameraFrame, DriveRenderer, SynthFrame, generate_drive
from .world import World, build_world

__all__ = ["CameraFrame", "DriveRenderer", "SynthConfig", "SynthFrame", "World", "build_world",
           "generate_drive"]
