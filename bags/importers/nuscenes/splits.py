"""nuScenes' official scene splits (as ``nuscenes.utils.splits`` of the devkit lists them), kept as
scene-number ranges so that ``--split`` needs no devkit. ``tests/bags/importers/nuscenes/
test_nuscenes_devkit.py`` compares them with the devkit's lists where the devkit is installed.
"""

from __future__ import annotations

from ..errors import DatasetError

_VAL = ("3, 12-18, 35-36, 38-39, 92-110, 221, 268-278, 329-332, 344-346, 519-524, 552-565, 625-627, 629-630, "
        "632-638, 770-771, 775, 777-778, 780-784, 794-800, 802, 904-917, 919-931, 962-963, 966-969, 971-972, "
        "1059-1073")
_TEST = ("77-91, 111-119, 140, 142-148, 265-266, 279-282, 307-314, 333-343, 481-498, 547-551, 601-604, 606-624, "
         "827-831, 833-842, 844-846, 932-933, 935-943, 1026-1043")
_MINI_TRAIN = "61, 553, 655, 757, 796, 1077, 1094, 1100"
_MINI_VAL = "103, 916"

#: split -> the version whose tables hold its scenes
SPLIT_VERSION = {"mini_train": "v1.0-mini", "mini_val": "v1.0-mini", "train": "v1.0-trainval",
                 "val": "v1.0-trainval", "test": "v1.0-test", "all": None}
SPLITS = tuple(SPLIT_VERSION)


def _names(ranges: str) -> frozenset[str]:
    out = set()
    for part in ranges.split(","):
        a, _, b = part.strip().partition("-")
        out.update(f"scene-{n:04d}" for n in range(int(a), int(b or a) + 1))
    return frozenset(out)


def split_scenes(split: str, version: str, scene_names: list[str]) -> list[str]:
    """The names of ``scene_names`` (the version's scene table, in its order) in ``split``.

    ``train`` is every ``v1.0-trainval`` scene not in ``val``; ``all`` every scene of the version.

    Raises:
        DatasetError: unknown split, or a split of another version.
    """
    if split not in SPLIT_VERSION:
        raise DatasetError(f"unknown split {split!r}; splits: {', '.join(SPLITS)}")
    wanted = SPLIT_VERSION[split]
    if wanted is not None and wanted != version:
        raise DatasetError(f"split {split!r} is a split of {wanted}, not of {version}")
    if split == "all":
        return list(scene_names)
    if split == "train":
        val = _names(_VAL)
        return [n for n in scene_names if n not in val]
    names = _names({"val": _VAL, "test": _TEST, "mini_train": _MINI_TRAIN, "mini_val": _MINI_VAL}[split])
    return [n for n in scene_names if n in names]


#: version -> its splits that partition it (the one recorded in each scene's bag)
VERSION_SPLITS = {"v1.0-mini": ("mini_train", "mini_val"), "v1.0-trainval": ("train", "val"), "v1.0-test": ("test",)}


def scene_split(version: str, name: str) -> str | None:
    """The official split of scene ``name`` among its version's (:data:`VERSION_SPLITS`:
    ``mini_train`` / ``mini_val`` in v1.0-mini, ``train`` / ``val`` in v1.0-trainval, ``test``),
    or ``None`` for a scene none of them lists (a version this package does not know).
    """
    for split in VERSION_SPLITS.get(version, ()):
        if split_scenes(split, version, [name]):
            return split
    return None


__all__ = ["SPLITS", "SPLIT_VERSION", "VERSION_SPLITS", "scene_split", "split_scenes"]
