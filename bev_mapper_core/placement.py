"""Keeping a mapper's rig placed at each set's camera times, the node's and replay's one way.

:class:`RigPlacer` takes each set's camera stamps, its reference stamp and a pose lookup, places
the cameras (:func:`~bev_mapper_core.geometry.time_placement.place_cameras`) and hands the mapper
the placed rig, calling :meth:`Mapper.set_rig` only when the rounded placement differs from the
mapper's current one. What it did is counted (:attr:`RigPlacer.counts`, for ``/diagnostics`` and
``metrics.json``) and said (:meth:`RigPlacer.place`'s notes: once for what holds for the whole
run, per set for the set's problems, which the caller throttles).

Per method (``Mapper.per_set_rig``): IPM and segipm rebuild numpy tables (~0.2 s for surround6
with occlusion reasoning, ~0.05 s classical), paid once per change of the rounded placement.
Learned methods bake the calibration into their model (Bi-Mapper's set_rig rebuilds its tables,
~0.2 s on torch, and re-exports the model on an exported backend: tens of seconds), so they keep
the calibrated rig and each moved camera's **image** is warped instead
(:mod:`~bev_mapper_core.geometry.ground_warp`: the image the calibrated camera would have taken
of the same ground; :meth:`RigPlacer.warp`), its maps computed once per rounded placement of the
camera and kept; those sets count as ``sets_warped`` (beside ``sets_placed``).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from .geometry.grid import BevGrid
from .geometry.ground_warp import GroundWarp, warp_image
from .geometry.rig import Rig
from .geometry.time_placement import Placement, PoseAt, TimePlacementConfig, place_cameras

#: The counters of :attr:`RigPlacer.counts` (``max_offset_m`` is the largest seen, the rest are
#: counts): sets placed, sets whose corrections all rounded to nothing, sets without an ego pose
#: at the reference stamp, sets placed by warping images (a method that keeps its calibrated rig;
#: also counted in ``sets_placed``), cameras without a pose at their stamp, cameras whose stamp
#: jumped, rebuilds of the mapper's tables or of a camera's warp maps.
PLACEMENT_COUNTS = ("sets_placed", "sets_static", "sets_without_pose", "sets_warped",
                    "cameras_without_pose", "stamp_jumps", "rebuilds")
#: warp maps kept (per camera and rounded placement): a steady speed reuses a handful
WARP_CACHE = 32


class RigPlacer:
    """Places each set's cameras at their own time on a mapper (see the module docstring).

    Args:
        grid: the mapper's grid (sets the rounding step).
        config: the placement settings (None: the defaults).
    """

    def __init__(self, grid: BevGrid, config: TimePlacementConfig | None = None) -> None:
        self.grid, self.config = grid, config if config is not None else TimePlacementConfig()
        self.counts: dict[str, float] = {**dict.fromkeys(PLACEMENT_COUNTS, 0), "max_offset_m": 0.0}
        self.base: Rig | None = None
        self._key: tuple = ()
        self._said: set[str] = set()
        #: the set's image warps (camera -> remap maps) of a method that keeps its rig
        self._warps: dict[str, tuple] = {}
        self._warp_cache: dict[tuple, tuple] = {}
        self._warpers: dict[str, GroundWarp] = {}  # camera -> its rays (computed once)

    def set_base(self, rig: Rig) -> None:
        """The calibrated rig the mapper was just built or re-calibrated with (the placement
        starts from it; the mapper holds it now).
        """
        self.base, self._key = rig, ()
        self._warp_cache.clear()  # maps of the old calibration
        self._warpers.clear()

    def place(self, mapper, stamps: Mapping[str, int | None], ref_stamp_ns: int,
              pose_at: PoseAt) -> tuple[Placement | None, list[tuple[str, str]]]:
        """Place the set's cameras on ``mapper`` (its rig set as needed) and count it.

        Returns ``(placement, notes)``: the placement (None when ``mode`` is off or the method
        keeps its calibrated rig, ``Mapper.per_set_rig`` False: then no pose is looked up) and
        ``(key, text)`` notes to log: ``placement:*`` once per run, ``placement_set:*`` for this
        set's problems (to throttle). Never raises on bad poses or stamps.
        """
        self._warps = {}
        if not self.config.enabled or self.base is None:
            return None, []
        notes: list[tuple[str, str]] = []
        c = self.counts
        keeps_rig = not getattr(mapper, "per_set_rig", False)
        if keeps_rig:
            self._once(notes, "placement:method", f"method {mapper.name}: its model holds the calibration (a new "
                       "rig per set would rebuild or re-export it), so the images of cameras that fired away "
                       "from the set's stamp are warped to their calibrated pose by the ground plane "
                       "(counted: sets_warped)")
        p = place_cameras(self.base, stamps, ref_stamp_ns, pose_at, self.grid, self.config)
        c["cameras_without_pose"] += len(p.no_pose)
        c["stamp_jumps"] += len(p.jumped)
        c["max_offset_m"] = max(c["max_offset_m"], p.max_offset_m)
        with_pose = p.placed or p.static
        if not with_pose and p.no_pose:
            c["sets_without_pose"] += 1
            self._once(notes, "placement:no_pose", "no ego pose (odometry or TF) at the sets' stamps: "
                       "each camera is mapped as calibrated at the set's stamp, as without time placement")
        elif p.placed:
            c["sets_placed"] += 1
        else:
            c["sets_static"] += 1
        if p.no_pose and with_pose:
            notes.append(("placement_set:no_pose", f"no ego pose at the stamps of {list(p.no_pose)}: "
                                                   "mapped as calibrated (counted: cameras_without_pose)"))
        if p.jumped:
            notes.append(("placement_set:jump", f"cameras {list(p.jumped)} stamped more than "
                          f"{self.config.max_offset_s:g} s from the set's stamp: mapped as calibrated "
                          "(counted: stamp_jumps)"))
        if keeps_rig:
            if p.placed:
                c["sets_warped"] += 1
                self._warps = {name: self._warp_maps(name, D) for name, D in p.moves}
        elif p.key != self._key:
            mapper.set_rig(p.rig if p.key else self.base)
            self._key = p.key
            c["rebuilds"] += 1
        return p, notes

    def _warp_maps(self, name: str, D) -> tuple:
        """The ground-plane warp of camera ``name`` moved by ``D`` (kept per rounded move)."""
        key = (name, D.tobytes())
        maps = self._warp_cache.get(key)
        if maps is None:
            cam = self.base[name]
            warper = self._warpers.get(name)
            if warper is None:
                warper = self._warpers[name] = GroundWarp(cam)
            maps = warper.maps(D @ cam.ego_from_cam_array)
            if len(self._warp_cache) >= WARP_CACHE:
                self._warp_cache.pop(next(iter(self._warp_cache)))
            self._warp_cache[key] = maps
            self.counts["rebuilds"] += 1
        return maps

    def warp(self, images: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The set's images, those of moved cameras warped to their calibrated pose (for a
        method that keeps its rig; every image as given otherwise). Call after :meth:`place`.
        """
        if not self._warps:
            return dict(images)
        out = dict(images)
        for name, maps in self._warps.items():
            img = out.get(name)
            if img is not None and tuple(img.shape[:2]) == maps[0].shape:  # a wrong size: the mapper says so
                out[name] = warp_image(img, maps)
        return out

    def _once(self, notes: list, key: str, text: str) -> None:
        if key not in self._said:
            self._said.add(key)
            notes.append((key, text))

    def values(self) -> dict[str, str]:
        """The counts as ``placement_<name>`` strings (``/diagnostics`` key/values)."""
        out = {f"placement_{k}": str(int(v)) for k, v in self.counts.items() if k != "max_offset_m"}
        out["placement_max_offset_m"] = f"{self.counts['max_offset_m']:.3f}"
        return out


__all__ = ["PLACEMENT_COUNTS", "RigPlacer"]
