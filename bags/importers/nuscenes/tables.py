"""The nuScenes JSON tables (``<DATAROOT>/<version>/*.json``) read without the devkit.

Only the tables the importer uses are loaded, each once, and indexed by token
(:class:`NuScenesTables`). Every record is checked for the fields the importer reads when it is
used; a missing table, a file that is not a JSON list of records, or a version folder that is not
there (another one is) is an error that names the file.
"""

from __future__ import annotations

import json
from collections import defaultdict
from functools import cached_property
from pathlib import Path
from typing import Any

from ..errors import DatasetLayoutError, DatasetVersionError

VERSIONS = ("v1.0-mini", "v1.0-trainval", "v1.0-test")
#: the tables the importer reads
TABLES = ("scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor", "log",
          "sample_annotation", "instance", "category", "visibility")


def table_dir(dataroot: Path, version: str) -> Path:
    """``<dataroot>/<version>``, checked.

    Raises:
        DatasetVersionError: that folder is absent and another version's is there.
        DatasetLayoutError: ``dataroot`` is not a directory, or holds no version folder.
    """
    root = Path(dataroot)
    if not root.is_dir():
        raise DatasetLayoutError(f"{root} is not a directory (the nuScenes DATAROOT)")
    folder = root / version
    if folder.is_dir():
        return folder
    others = sorted(p.name for p in root.glob("v1.0-*") if p.is_dir())
    if others:
        raise DatasetVersionError(f"{root} holds {', '.join(others)}, not {version}: pass --version {others[0]}")
    raise DatasetLayoutError(f"{folder} not found: the tables of {version} are read from <DATAROOT>/{version}/*.json")


class NuScenesTables:
    """The tables of one nuScenes version (see the module docstring).

    Args:
        dataroot: the folder holding ``<version>/``, ``samples/``, ``sweeps/`` and ``maps/``.
        version: ``v1.0-mini``, ``v1.0-trainval`` or ``v1.0-test``.
    """

    def __init__(self, dataroot: str | Path, version: str) -> None:
        if version not in VERSIONS:
            raise DatasetVersionError(f"unknown nuScenes version {version!r}; versions: {', '.join(VERSIONS)}")
        self.dataroot = Path(dataroot)
        self.version = version
        self.folder = table_dir(self.dataroot, version)
        missing = [f"{name}.json" for name in TABLES if not (self.folder / f"{name}.json").is_file()]
        if missing:
            raise DatasetLayoutError(f"{self.folder} lacks the table(s) {', '.join(missing)}")
        self._tables: dict[str, list[dict]] = {}
        self._index: dict[str, dict[str, dict]] = {}

    def table(self, name: str) -> list[dict]:
        """The records of table ``name`` (loaded on first use)."""
        if name not in self._tables:
            path = self.folder / f"{name}.json"
            try:
                with open(path, "rb") as f:
                    records = json.load(f)
            except json.JSONDecodeError as exc:
                raise DatasetLayoutError(f"{path}: not valid JSON ({exc})") from None
            if not isinstance(records, list) or not all(isinstance(r, dict) and "token" in r for r in records):
                raise DatasetLayoutError(f"{path}: not a JSON list of records with a 'token'")
            self._tables[name] = records
        return self._tables[name]

    def get(self, name: str, token: str) -> dict:
        """The record of table ``name`` with ``token``.

        Raises:
            DatasetLayoutError: no such record (the tables do not belong together).
        """
        if name not in self._index:
            self._index[name] = {r["token"]: r for r in self.table(name)}
        try:
            return self._index[name][token]
        except KeyError:
            raise DatasetLayoutError(f"{self.folder / name}.json has no record {token!r}") from None

    @cached_property
    def sample_data_by_sample(self) -> dict[str, list[dict]]:
        """``sample_token`` -> its sample_data records (key frames and sweeps)."""
        out: dict[str, list[dict]] = defaultdict(list)
        for r in self.table("sample_data"):
            out[field(r, "sample_token", "sample_data")].append(r)
        return out

    @cached_property
    def annotations_by_sample(self) -> dict[str, list[dict]]:
        """``sample_token`` -> its sample_annotation records."""
        out: dict[str, list[dict]] = defaultdict(list)
        for r in self.table("sample_annotation"):
            out[field(r, "sample_token", "sample_annotation")].append(r)
        return out

    def channel(self, sample_data: dict) -> str:
        """The sensor channel (``CAM_FRONT`` ...) of a sample_data record."""
        cs = self.get("calibrated_sensor", field(sample_data, "calibrated_sensor_token", "sample_data"))
        return field(self.get("sensor", field(cs, "sensor_token", "calibrated_sensor")), "channel", "sensor")

    def scene_names(self) -> list[str]:
        """Names of the version's scenes, in the table's order."""
        return [field(s, "name", "scene") for s in self.table("scene")]

    def scene(self, name: str) -> dict:
        """The scene record named ``name`` (``None`` handled by the caller)."""
        for s in self.table("scene"):
            if s.get("name") == name:
                return s
        raise KeyError(name)

    def scene_samples(self, scene: dict) -> list[dict]:
        """The scene's samples in time order (following ``next`` from ``first_sample_token``)."""
        out, token, seen = [], field(scene, "first_sample_token", "scene"), set()
        while token and token not in seen:
            seen.add(token)
            sample = self.get("sample", token)
            out.append(sample)
            token = sample.get("next", "")
        return out


def field(record: dict, key: str, table: str) -> Any:
    """``record[key]``, or an error naming the table and the field."""
    try:
        return record[key]
    except KeyError:
        raise DatasetLayoutError(f"a record of {table}.json lacks the field {key!r}") from None


__all__ = ["TABLES", "VERSIONS", "NuScenesTables", "field", "table_dir"]
