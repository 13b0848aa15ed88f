"""The BEV grid flags of ``bev-bag synth`` and ``bev-bag replay``: a named grid (``--grid``,
:data:`~bev_mapper_core.geometry.grid.GRID_PRESETS`) and per-field overrides (``--grid-x-min`` ...), the
defaults read from :class:`~bev_mapper_core.geometry.grid.BevGrid` and the presets, never retyped.
"""

from __future__ import annotations

import argparse
from dataclasses import replace

from bev_mapper_core.geometry.grid import GRID_PRESETS, BevGrid, grid_preset

#: flag suffix -> BevGrid field
FIELDS = {"x-min": "x_min", "x-max": "x_max", "y-min": "y_min", "y-max": "y_max", "res": "resolution"}


def add_grid_args(p: argparse.ArgumentParser | argparse._ArgumentGroup, what: str) -> None:
    """Add ``--grid NAME`` and the ``--grid-*`` overrides; ``what`` says what the grid is for."""
    names = "; ".join(f"{n}: {g.describe()}" for n, g in GRID_PRESETS.items())
    p.add_argument("--grid", default=None, choices=sorted(GRID_PRESETS), metavar="NAME",
                   help=f"{what}: a named grid ({names})")
    for flag, field in FIELDS.items():
        p.add_argument(f"--grid-{flag}", dest=f"grid_{field}", type=float, default=None,
                       help=f"override the grid's {field} (m; default: the named grid's, "
                            f"surround {getattr(BevGrid(), field)})")


def grid_from_args(args: argparse.Namespace, default: str | None = "surround") -> BevGrid | None:
    """The grid the flags describe: ``--grid`` (else ``default``; ``None``: no grid unless a flag
    is given) with the ``--grid-*`` overrides (raises GridError for an invalid grid).
    """
    over = {f: getattr(args, f"grid_{f}") for f in FIELDS.values() if getattr(args, f"grid_{f}") is not None}
    name = args.grid or (default if default is not None or not over else "surround")
    if name is None:
        return None
    return replace(grid_preset(name), **over)
