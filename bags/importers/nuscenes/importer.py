"""``bev-bag import nuscenes``: one bag per scene (see :mod:`bags.importers.nuscenes`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from bev_mapper_core.errors import ConfigError

from ...io.writer import check_output
from ..drive import ImportCounts, write_imported_drive
from ..errors import DatasetError, SceneNotFoundError
from .maps import MAP_SOURCES, NuScenesMap, map_path
from .scene import SceneOptions, scene_drive
from .splits import split_scenes
from .tables import NuScenesTables
from .tables import field as rfield


@dataclass(frozen=True)
class NuScenesImportOptions:
    """What ``bev-bag import nuscenes`` imports.

    Args:
        dataroot: the nuScenes folder (``<version>/``, ``samples/``, ``sweeps/``, ``maps/``).
        version: ``v1.0-mini``, ``v1.0-trainval`` or ``v1.0-test``.
        out: the folder the bags are written into (``<out>/<scene name>/``).
        scenes: scene names; or
        split: an official split (:data:`~bags.importers.nuscenes.splits.SPLITS`).
        scene: the grid, sweeps, box filter and line thickness.
        force: replace existing bags.
    """

    dataroot: Path
    version: str
    out: Path
    scenes: tuple[str, ...] = ()
    split: str | None = None
    scene: SceneOptions = field(default_factory=SceneOptions)
    force: bool = False

    def __post_init__(self) -> None:
        if bool(self.scenes) == (self.split is not None):
            raise ConfigError("name the scenes (--scene NAME) or a split (--split SPLIT), not both")


@dataclass
class SceneResult:
    """One scene's outcome: its bag and counts, or the error that stopped it."""

    name: str
    path: Path
    counts: ImportCounts | None = None
    error: str | None = None
    notes: list[str] = field(default_factory=list)
    left_out_boxes: int = 0


def import_nuscenes(options: NuScenesImportOptions, note: Callable[[str], None] = lambda s: None,
                    done: Callable[[SceneResult], None] = lambda r: None) -> list[SceneResult]:
    """Import the scenes; ``note`` gets each note as it comes, ``done`` each finished scene.

    A scene that fails (no readable image, a table that does not fit) is reported in its
    :class:`SceneResult` and the next one is imported.

    Raises:
        DatasetError: the tables are missing or of another version, a scene does not exist, a map
            expansion is unreadable; nothing is written then.
        BagExistsError: a scene's bag exists and ``force`` is false (checked before any is written).
    """
    tables = NuScenesTables(options.dataroot, options.version)
    names = tables.scene_names()
    if options.split is not None:
        wanted = split_scenes(options.split, options.version, names)
        if not wanted:
            raise SceneNotFoundError(f"no scene of split {options.split!r} in {tables.folder}")
    else:
        unknown = [s for s in options.scenes if s not in names]
        if unknown:
            shown = ", ".join(names[:12]) + (" ..." if len(names) > 12 else "")
            raise SceneNotFoundError(f"no scene {', '.join(unknown)} in {tables.folder} (scenes: {shown})")
        wanted = list(dict.fromkeys(options.scenes))
    for name in wanted:
        check_output(options.out / name, options.force)
    options.out.mkdir(parents=True, exist_ok=True)
    maps: dict[str, NuScenesMap | None] = {}
    results = []
    for name in wanted:
        scene = tables.scene(name)
        location = tables.get("log", rfield(scene, "log_token", "scene")).get("location", "")
        result = SceneResult(name, options.out / name)
        if location not in maps:
            path = map_path(options.dataroot, location)
            maps[location] = NuScenesMap(path) if path.is_file() else None
            if maps[location] is None:
                msg = (f"no map expansion {path} (nuScenes-map-expansion-v1.3): "
                       f"{', '.join(MAP_SOURCES)} left unscored in the scenes of {location or 'an unnamed location'}")
                note(msg)
        if maps[location] is None:
            result.notes.append(f"map layers unscored: no {map_path(options.dataroot, location).name}")
        try:
            drive, summary = scene_drive(tables, scene, options.scene, maps[location])
            result.counts = write_imported_drive(result.path, drive, force=options.force)
            result.left_out_boxes = summary["left_out_boxes"][0]
        except DatasetError as exc:
            result.error = str(exc)
        results.append(result)
        done(result)
    return results


__all__ = ["NuScenesImportOptions", "SceneResult", "import_nuscenes"]
