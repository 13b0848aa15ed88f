"""What the monocular learned mappers (S2G2, FocusBEV) share: their weights file (given, or the
shipped ``weights/<method>_<rig>_<input>.safetensors``), the start-up checks of it against the
configuration, and the output classes read from its header.

A subclass sets :attr:`MonocularMapper.title`, :attr:`~MonocularMapper.train_hint` and the two
functions of its weights module (:meth:`~MonocularMapper.read_metadata`,
:meth:`~MonocularMapper.validate`).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from ..errors import ConfigError
from ..geometry.grid import BevGrid
from ..geometry.rig import Rig
from ..mapper import Mapper, MapperConfig
from ..methods import WEIGHTS_DIR, alternatives, shipped_weights
from .backends import resolve_backend
from .mono_geometry import check_one_camera
from .weights import WeightsError


class MonocularMapper(Mapper):
    """Base of the learned one-camera mappers (see the module docstring)."""

    #: the method's name in messages (``S2G2``, ``FocusBEV``)
    title: str = ""
    #: the command that trains weights, for the error when none are shipped
    train_hint: str = ""

    @staticmethod
    def read_metadata(path: Path) -> dict:
        """The weights file's checked metadata document (header only)."""
        raise NotImplementedError

    @staticmethod
    def validate(path: Path) -> dict:
        """The full check of a weights file (every tensor against its stored architecture)."""
        raise NotImplementedError

    @staticmethod
    def load(path: Path, rig: Rig, grid: BevGrid, device) -> tuple:
        """``(model in eval mode, metadata)`` of a weights file built for ``rig`` and ``grid``."""
        raise NotImplementedError

    def set_rig(self, rig: Rig) -> None:
        """Load the model on first use (``self.model`` None); afterwards hand it the new
        calibration (its ``set_rig`` rebuilds the calibration-dependent tables).
        """
        check_one_camera(rig, self.title)
        super().set_rig(rig)
        if self.model is None:
            self.model, _ = self.load(self.weights_file, rig, self.grid, self.device)
        else:
            self.model.set_rig(rig)

    @classmethod
    def weights_path(cls, config: MapperConfig, rig_name: str) -> Path:
        """``config.weights``, or the shipped file of the rig and input kind.

        Raises:
            ConfigError: none given and none shipped for this rig and input kind.
        """
        if config.weights:
            return Path(config.weights)
        path = shipped_weights(cls.name, rig_name, config.input_kind)
        if not path.is_file():
            shipped = sorted(p.name for p in WEIGHTS_DIR.glob(f"{cls.name}_*.safetensors"))
            raise ConfigError(f"no {cls.title} weights given and none shipped for rig {rig_name!r} / input "
                              f"{config.input_kind!r} (shipped: {', '.join(shipped) or 'none'}); "
                              f"{alternatives(cls.name, config.input_kind, rig_name, 1)}")
        return path

    @classmethod
    def preflight(cls, config: MapperConfig, rig_name: str, grid: BevGrid | None = None,
                  cameras: tuple[str, ...] | None = None) -> None:
        """One camera (when the camera names are given), and a weights file of this method for
        this input kind, rig, classes, camera and (when given) grid, every tensor of which fits
        the stored architecture: a node never starts with weights it cannot run.

        Raises:
            ConfigError: more than one camera; no weights given; a ``backend`` named explicitly
                that is not installed.
            WeightsError: the first mismatch.
        """
        resolve_backend(config.backend)
        if cameras is not None and len(cameras) != 1:
            raise ConfigError(f"{cls.title} is monocular: rig {rig_name!r} has {len(cameras)} cameras "
                              f"{list(cameras)}; use a one-camera rig (e.g. front1), or another method: "
                              f"{alternatives(cls.name, config.input_kind, rig_name, len(cameras))}")
        path = cls.weights_path(config, rig_name)
        meta = cls.read_metadata(path)
        if meta["input_kind"] != config.input_kind:
            raise WeightsError(f"{path} is for input {meta['input_kind']!r}, configured input is {config.input_kind!r}")
        if rig_name and meta["rig"] != rig_name:
            raise WeightsError(f"{path} was trained for rig {meta['rig']!r}, not {rig_name!r}")
        unknown = [c for c in config.classes or () if c not in meta["classes"]]
        if unknown:
            raise WeightsError(f"{path}: classes {unknown} are not among the weights' classes {meta['classes']}")
        if cameras is not None and list(cameras) != list(meta["cameras"]):
            raise WeightsError(f"{path}: weights were trained for camera {meta['cameras']}, but {list(cameras)} "
                               "is configured")
        stored = BevGrid.from_dict(meta["grid"])
        if grid is not None and not grid.isclose(stored):
            raise WeightsError(f"{path}: weights were trained for grid {stored.describe()}, but {grid.describe()} "
                               f"is configured; use weights trained for this grid; "
                               f"{alternatives(cls.name, config.input_kind, rig_name)}")
        cls.validate(path)

    @classmethod
    def output_classes(cls, config: MapperConfig, rig_name: str) -> tuple[str, ...]:
        """``config.classes``, or the classes the weights were trained for (header only)."""
        if config.classes is not None:
            return tuple(config.classes)
        return tuple(cls.read_metadata(cls.weights_path(config, rig_name))["classes"])

    def open_weights(self, rig: Rig, grid: BevGrid, config: MapperConfig) -> tuple[MapperConfig, dict]:
        """Preflight, then ``(config with the weights' classes when it names none, metadata)``;
        sets :attr:`weights_file` and ``_layers`` (the output layers to return, in the
        configured order: a subset is allowed).
        """
        check_one_camera(rig, self.title, alternatives(self.name, config.input_kind, rig.name, len(rig.cameras)))
        self.preflight(config, rig.name, grid, rig.names)
        self.weights_file = self.weights_path(config, rig.name)
        meta = self.read_metadata(self.weights_file)
        weight_classes = tuple(meta["classes"])
        if config.classes is None:
            config = replace(config, classes=weight_classes)
        self._layers = [weight_classes.index(c) for c in config.classes]
        return config, meta


__all__ = ["MonocularMapper"]
