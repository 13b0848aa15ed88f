"""Flag types and flag groups shared by ``bev-train``'s subcommands: numbers checked by argparse,
named grids, a method plug-in's :class:`~bev_mapper_core.training.method.CliFlag`, and the
held-out drives that ``eval`` and ``calibrate`` score on. Defaults come from :class:`TrainConfig`
(:data:`DEFAULTS`), never retyped.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import fields

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.method import CliFlag

#: TrainConfig's field defaults (the flags and the eval command take theirs from here).
DEFAULTS = {f.name: f.default for f in fields(TrainConfig)}


def int_list(s: str) -> tuple[int, ...]:
    """Argparse type: comma-separated integers (at least one)."""
    try:
        v = tuple(int(x) for x in s.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {s!r}") from None
    if not v:
        raise argparse.ArgumentTypeError("empty seed list")
    return v


def int_at_least(lo: int):
    """Argparse type: an integer >= ``lo``."""
    def parse(s: str) -> int:
        try:
            v = int(s)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {s!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"must be >= {lo}, got {v}")
        return v
    return parse


pos_int = int_at_least(1)
nonneg_int = int_at_least(0)


def pos_float(s: str) -> float:
    """Argparse type: a finite float > 0."""
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not v > 0 or v != v or v == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {s}")
    return v


def nonneg_float(s: str) -> float:
    """Argparse type: a finite float >= 0."""
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {s}") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {s}")
    return v


def grid_name(s: str):
    """Argparse type: a named grid (:data:`~bev_mapper_core.geometry.grid.GRID_PRESETS`) -> its BevGrid."""
    from bev_mapper_core.geometry.grid import GRID_PRESETS

    if s not in GRID_PRESETS:
        raise argparse.ArgumentTypeError(f"unknown grid {s!r}; named grids: {', '.join(sorted(GRID_PRESETS))}")
    return GRID_PRESETS[s]


def grid_help() -> str:
    """Help of ``--grid``: the named grids."""
    from bev_mapper_core.geometry.grid import GRID_PRESETS

    return "named BEV grid: " + "; ".join(f"{n}: {g.describe()}" for n, g in GRID_PRESETS.items())


def add_method_flag(p, f: CliFlag) -> None:
    """Add a method's :class:`CliFlag` (default suppressed: the config dataclass has it)."""
    kw = {"dest": f.dest, "help": f.help, "default": argparse.SUPPRESS}
    if f.action:
        kw["action"] = argparse.BooleanOptionalAction if f.action == "boolean" else f.action
    if f.metavar:
        kw["metavar"] = f.metavar
    if f.choices is not None:
        kw["choices"] = list(f.choices)
    if f.min_value is not None:
        kw["type"] = int_at_least(f.min_value)
    if f.number:
        kw["type"] = nonneg_float
    p.add_argument(f.flag, **kw)


def add_held_out_flags(p: argparse.ArgumentParser) -> None:
    """The held-out drives ``eval`` and ``calibrate`` render and score (TrainConfig's defaults)."""
    p.add_argument("--val-drives", type=pos_int, default=DEFAULTS["val_drives"])
    p.add_argument("--val-seeds", type=int_list, default=None, help="validation seeds (900000000+, never test seeds)")
    p.add_argument("--frames-per-drive", type=pos_int, default=DEFAULTS["frames_per_drive"])
    p.add_argument("--stride", type=pos_int, default=DEFAULTS["stride"])
    p.add_argument("--cache", default=DEFAULTS["cache"])


def rig_name_arg(s: str) -> str:
    """Argparse type: a preset rig's name or ``random-<seed>`` (:func:`~bev_mapper_core.geometry.random_rig.rig_by_name`)."""
    from bev_mapper_core.geometry.random_rig import check_rig_name

    try:
        return check_rig_name(s)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
