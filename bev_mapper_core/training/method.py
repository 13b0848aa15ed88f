"""Training plug-ins: what a learned method gives the one generic loop in :mod:`.trainer`.

The trainer owns everything that is the same for every method: seeding, the optimizer and its
step lr schedule, epochs, the time budget, checkpoint / resume (weights through the method,
optimizer state as safetensors), progress bars, ``metrics.jsonl``, best / last. A method owns
its model and its objective. A new method's plug-in is ``methods/<name>/train.py`` with a
:class:`TrainMethod` subclass, named in the one table of methods
(:data:`bev_mapper_core.methods.METHODS`); :func:`register_train_method` adds one at run time.

Per run the trainer does, in this order::

    torch.manual_seed(cfg.seed)
    m = method_class(cfg.method)(cfg, rig, grid)     # builds m.model (cfg.model: its config type)
    opt = m.configure_optimizer(cfg.lr)              # Adam over m.trainable_parameters()
    data = source.load(cfg, rig, grid, m.data_needs(), log)
    m.prepare(data, log)                             # statistics of the training set, logs
    for epoch ...:
        m.start_epoch(epoch)
        for batch in data.batches(...):              # what data_needs() asked for
            loss, parts = m.loss(batch, epoch, step) # parts: floats, "total" among them
            opt.zero_grad(); loss.backward(); opt.step()
            m.after_step(step)                       # e.g. an EMA update
        validate(m, data.val, ...)                   # m.predict(batch) -> probs, known: the one scorer
        m.epoch_metrics(log)                         # extra held-out figures (metrics.jsonl only)
        m.save(path)                                 # weights (safetensors: the method's weights.py)

``cfg.model`` is the method's architecture config (:attr:`TrainMethod.model_config_type`, a
frozen dataclass with ``input_kind``, ``classes``, ``to_dict`` / ``from_dict``) and ``cfg.loss``
its training settings (:attr:`TrainMethod.loss_config_type`, a frozen dataclass: loss terms,
schedules). ``bev-train`` flags of the method are declared as :class:`CliFlag` and land on a
field of one of the two (see :meth:`~.config.TrainConfig.from_dict`).

Methods whose batches differ plug in through :meth:`TrainMethod.data_needs`: S2G2 asks for
unlabeled frames beside the labeled ones (batches ``{"labeled": ..., "unlabeled": ...}``),
FocusBEV for windows of consecutive frames with their ego poses. Their plug-ins
(``methods/s2g2/train.py``, ``methods/focusbev/train.py``) are the worked examples.
``predict`` returns ``(probs (B, K, H, W), known (B, H, W))`` numpy arrays on the run's
grid; the trainer scores them with the same scorer as every other method.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from ..errors import ConfigError
from ..geometry.grid import BevGrid
from ..geometry.rig import Rig
from ..methods import trainer_targets
from ..registry import resolve
from .sources import DataNeeds, TrainData

if TYPE_CHECKING:
    import torch

    from .config import TrainConfig


#: :attr:`CliFlag.action` values (None: a flag with a value).
CLI_ACTIONS: tuple[str | None, ...] = (None, "store_true", "store_false", "boolean", "append")


@dataclass(frozen=True)
class CliFlag:
    """One ``bev-train`` flag of a method; ``dest`` is a field of its model or loss config.

    Args:
        flag: option string, e.g. ``--streams``.
        dest: the field it sets (a flat config key, also accepted in ``--config`` YAML).
        help: help text.
        choices: allowed values (take them from the constant that owns them).
        action: ``store_true`` / ``store_false`` for switches; ``boolean`` for a pair
            ``--flag`` / ``--no-flag``; ``append`` for a repeatable flag (a tuple field).
        min_value: integer flag with this lower bound.
        number: a float flag (finite, >= 0).
        metavar: the value's name in the help.
    """

    flag: str
    dest: str
    help: str | None = None
    choices: tuple[str, ...] | None = None
    action: str | None = None
    min_value: int | None = None
    number: bool = False
    metavar: str | None = None

    def __post_init__(self) -> None:
        if self.action not in CLI_ACTIONS:
            raise ConfigError(f"{self.flag}: action must be one of {CLI_ACTIONS[1:]}, got {self.action!r}")


class TrainMethod(ABC):
    """A learned method as the trainer sees it (see the module docstring). One instance per run.

    Attributes:
        cfg: the run's :class:`~.config.TrainConfig` (``cfg.model``, ``cfg.loss`` are this
            method's config objects).
        rig, grid: what the run trains for (from the data source).
        model: the ``torch.nn.Module`` built by :meth:`build_model` (all of its state is saved).
    """

    #: registry name (``--method``)
    name: ClassVar[str]
    #: architecture config type (frozen dataclass with ``input_kind``, ``classes``, ``to_dict``, ``from_dict``)
    model_config_type: ClassVar[type]
    #: training-settings type (frozen dataclass, JSON-able fields)
    loss_config_type: ClassVar[type]
    #: the method's ``bev-train`` flags
    cli_flags: ClassVar[tuple[CliFlag, ...]] = ()

    def __init__(self, cfg: "TrainConfig", rig: Rig, grid: BevGrid) -> None:
        self.cfg, self.rig, self.grid = cfg, rig, grid
        self.model = self.build_model()

    # ------------------------------------------------------------ configuration
    @classmethod
    def default_model_config(cls, classes: tuple[str, ...]) -> Any:
        """The model config trained when the run sets no field (other fields: their defaults)."""
        return cls.model_config_type(classes=tuple(classes))

    # ------------------------------------------------------------------- model
    @abstractmethod
    def build_model(self) -> "torch.nn.Module":
        """The model of ``cfg.model`` for ``rig`` and ``grid`` (torch's RNG is already seeded)."""

    def trainable_parameters(self) -> Iterable["torch.nn.Parameter"]:
        """Parameters the optimizer updates (default: all of the model's)."""
        return self.model.parameters()

    def configure_optimizer(self, lr: float) -> "torch.optim.Optimizer":
        """The optimizer (default Adam); the trainer sets each group's lr every epoch."""
        import torch

        return torch.optim.Adam(self.trainable_parameters(), lr=lr)

    def describe(self) -> str:
        """Model part of the start-up log line (after the parameter count)."""
        return f"classes {list(self.cfg.class_names)}"

    def schedule(self) -> str:
        """Method-specific schedule for the start-up log line ('' = none)."""
        return ""

    # -------------------------------------------------------------------- data
    def data_needs(self) -> DataNeeds:
        """What batches the method trains on (the data source honours it or refuses the run)."""
        return DataNeeds()

    def prepare(self, data: TrainData, log: Callable[[str], None]) -> None:
        """Once per run (also on resume) after the data is loaded: e.g. class statistics."""

    # ---------------------------------------------------------------- training
    def start_epoch(self, epoch: int) -> None:
        """Before the first batch of ``epoch`` (0-based), after the model is put in train mode."""

    @abstractmethod
    def loss(self, batch: dict, epoch: int, step: int) -> tuple["torch.Tensor", dict[str, float]]:
        """``(loss to backpropagate, parts)`` of one batch; parts are floats incl. ``total``.

        ``batch`` holds CPU tensors as :meth:`~.sources.TrainData.batches` yields them; move them
        to the model's device here. ``step`` counts optimizer steps before this one.
        """

    def after_step(self, step: int) -> None:
        """After the optimizer step that made ``step`` steps in all (e.g. an EMA update)."""

    # -------------------------------------------------------------- validation
    def epoch_metrics(self, log: Callable[[str], None]) -> dict[str, Any]:
        """Extra held-out figures of the epoch beside the one scorer's (e.g. the segmenter's pixel
        IoU on real frames): JSON-able, added to the epoch's ``metrics.jsonl`` record; never used
        to choose the best checkpoint. Called on the main process after validation, in eval mode
        without gradients; ``log`` prints.
        """
        return {}

    @abstractmethod
    def predict(self, batch: dict) -> tuple[np.ndarray, np.ndarray]:
        """``(probs (B, K, H, W) float, known (B, H, W) bool)`` numpy for a batch of held-out
        frames (called in eval mode, without gradients).
        """

    # ------------------------------------------------------------------ saving
    @abstractmethod
    def save(self, path) -> None:
        """Write the model's weights (safetensors only) to ``path``."""

    @abstractmethod
    def load(self, path) -> None:
        """Load weights written by :meth:`save` into :attr:`model` (checked against it)."""

    def checkpoint_info(self) -> dict:
        """Extra JSON saved beside each checkpoint."""
        return {"model_config": self.cfg.model.to_dict(), "rig": self.rig.name}

    @property
    def device(self) -> "torch.device":
        """Device of the model's parameters."""
        return next(self.model.parameters()).device


# ----------------------------------------------------------------------- registry
# filled from the one table of methods (:data:`bev_mapper_core.methods.METHODS`)
_REGISTRY: dict[str, str | type[TrainMethod]] = dict(trainer_targets())


def register_train_method(name: str, target: str | type[TrainMethod]) -> None:
    """Register a training plug-in under ``name``: a ``"module:Class"`` string (imported on first
    use) or the class itself.
    """
    _REGISTRY[name] = target


def train_methods() -> tuple[str, ...]:
    """Names of the registered training methods."""
    return tuple(sorted(_REGISTRY))


def method_class(name: str) -> type[TrainMethod]:
    """The plug-in class registered as ``name`` (imported on first use).

    Raises:
        ConfigError: unknown name, or the target is not a :class:`TrainMethod`.
    """
    try:
        target = _REGISTRY[name]
    except KeyError:
        raise ConfigError(f"unknown training method {name!r}; available: {list(train_methods())}") from None
    target = resolve(target)
    if not (isinstance(target, type) and issubclass(target, TrainMethod)):
        raise ConfigError(f"training method {name!r} is registered as {target!r}, not a TrainMethod")
    return target


__all__ = ["CLI_ACTIONS", "CliFlag", "TrainMethod", "method_class", "register_train_method", "train_methods"]
