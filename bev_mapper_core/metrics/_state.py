"""Exact merging of accumulators: a JSON state of their summed counts, added together.

Both accumulators of the package only ever *sum* per-frame counts (intersections, unions, TP,
FP, Chamfer sums and counts, calibration bins ...) and divide once in ``result()``. So the
counts of several drives accumulated separately add up to the counts of all their frames
accumulated in one accumulator: integer counts exactly, float sums up to the order of the
additions (a few ULP). :class:`Mergeable` gives an accumulator

* :meth:`Mergeable.state`: ``{"kind", "config", "counts"}``, plain JSON (ints, floats, lists;
  Python's float repr round-trips exactly), small (no per-cell data), to send between processes
  or write to disk;
* :meth:`Mergeable.merge` / :meth:`Mergeable.merge_state`: add another accumulator's counts;
  refused (:class:`~bev_mapper_core.errors.ConfigError`) unless kind and configuration (grid,
  classes, bands, threshold ...) are the same, since counts of other definitions do not add;
* :meth:`Mergeable.from_state`: a new accumulator holding a state.
"""

from __future__ import annotations

import json
import math

import numpy as np

from ..errors import ConfigError


def _json_number(v: float) -> float | None:
    """A float for JSON: infinity as ``None`` (JSON has no infinity)."""
    v = float(v)
    return None if math.isinf(v) else v


def _from_json_number(v) -> float:
    return math.inf if v is None else float(v)


class Mergeable:
    """Mixin of an accumulator whose state is the attributes named in ``_COUNTS`` (ints or numpy
    arrays that are summed over frames). A subclass defines ``_COUNTS``, :meth:`_config` (a
    JSON-able dict of what defines the counts) and :meth:`_from_config`.
    """

    _COUNTS: tuple[str, ...] = ()

    def _config(self) -> dict:  # pragma: no cover - defined by the subclasses
        raise NotImplementedError

    @classmethod
    def _from_config(cls, config: dict):  # pragma: no cover - defined by the subclasses
        raise NotImplementedError

    def state(self) -> dict:
        """The accumulated counts and what defines them, as a JSON-serialisable dict."""
        counts = {}
        for name in self._COUNTS:
            value = getattr(self, name)
            counts[name] = value.tolist() if isinstance(value, np.ndarray) else int(value)
        # a JSON round trip makes configs comparable whatever the tuple/list spelling
        return {"kind": type(self).__name__, "config": json.loads(json.dumps(self._config())),
                "counts": counts}

    def check_state(self, state: dict) -> None:
        """Raise :class:`~bev_mapper_core.errors.ConfigError` unless :meth:`merge_state` would
        accept ``state`` (same kind and configuration, counts of the right shapes).
        """
        self._checked_counts(state)

    def _checked_counts(self, state: dict) -> dict:
        mine = self.state()
        if not isinstance(state, dict) or state.get("kind") != mine["kind"]:
            kind = state.get("kind") if isinstance(state, dict) else type(state).__name__
            raise ConfigError(f"cannot merge a {kind} state into a {mine['kind']}")
        theirs = state.get("config") if isinstance(state.get("config"), dict) else {}
        if theirs != mine["config"]:
            diff = sorted(k for k in set(mine["config"]) | set(theirs)
                          if mine["config"].get(k) != theirs.get(k))
            raise ConfigError(f"cannot merge {mine['kind']} states of different configurations "
                              f"(they differ in {diff})")
        counts = state.get("counts") if isinstance(state.get("counts"), dict) else {}
        if set(counts) != set(self._COUNTS):
            raise ConfigError(f"a {mine['kind']} state needs the counts {list(self._COUNTS)}, got "
                              f"{sorted(counts)}")
        out = {}
        for name in self._COUNTS:
            value = getattr(self, name)
            try:
                if isinstance(value, np.ndarray):
                    other = np.asarray(counts[name], dtype=value.dtype)
                    if other.shape != value.shape:
                        raise ConfigError(f"{mine['kind']} state: {name} has shape {other.shape}, "
                                          f"expected {value.shape}")
                else:
                    other = int(counts[name])
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"{mine['kind']} state: {name} is not a count: {exc}") from exc
            out[name] = other
        return out

    def merge_state(self, state: dict) -> None:
        """Add the counts of ``state`` (from :meth:`state` of an accumulator of the same kind and
        configuration) to this accumulator.

        Raises:
            ConfigError: another kind or configuration, or counts of the wrong shape. Nothing
                is added then.
        """
        for name, other in self._checked_counts(state).items():
            setattr(self, name, getattr(self, name) + other)

    def merge(self, other: "Mergeable") -> None:
        """Add the counts of ``other`` (same kind and configuration) to this accumulator."""
        self.merge_state(other.state())

    @classmethod
    def from_state(cls, state: dict):
        """A new accumulator of the configuration of ``state`` holding its counts.

        Raises:
            ConfigError: not a state of this kind, or an invalid configuration or counts.
        """
        if not isinstance(state, dict) or state.get("kind") != cls.__name__:
            raise ConfigError(f"not a {cls.__name__} state")
        acc = cls._from_config(state.get("config") or {})
        acc.merge_state(state)
        return acc
