"""``bev-train calibrate``: temperature scaling of Bi-Mapper weights on validation drives (see
:mod:`bev_mapper_core.methods.bimapper.calibrate`); writes a copy of the weights with ``temperature``::

    bev-train calibrate --rig surround6 --weights IN --out OUT [--val-seeds ...]
"""

from __future__ import annotations

import argparse

from bev_mapper_core.geometry.rig import PRESETS

from .flags import DEFAULTS, add_held_out_flags, pos_int, rig_name_arg

HELP = ("fit per-class temperatures of Bi-Mapper weights on validation drives "
        "(NLL of the visible cells) and write them into a copy of the file")


def configure(p: argparse.ArgumentParser, argv: list[str]) -> None:
    """The weights in and out and the validation drives."""
    p.add_argument("--rig", default=DEFAULTS["rig"], type=rig_name_arg, metavar="RIG",
                   help=f"a preset rig ({', '.join(sorted(PRESETS))}) or random-<seed> (default: %(default)s)")
    p.add_argument("--weights", required=True, help="Bi-Mapper weights to calibrate")
    p.add_argument("--out", required=True, help="calibrated weights file to write")
    add_held_out_flags(p)
    p.add_argument("--threads", type=pos_int, default=DEFAULTS["threads"])


def run(a: argparse.Namespace) -> int:
    """Fit the temperatures and write the calibrated copy."""
    import torch

    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.random_rig import rig_by_name
    from bev_mapper_core.methods.bimapper.calibrate import calibrate_weights
    from bev_mapper_core.methods.bimapper.weights import WeightsFile
    from bev_mapper_core.training.data import val_seeds
    from bev_mapper_core.training.evaluate import held_out_frames

    torch.set_num_threads(a.threads)
    rig, grid = rig_by_name(a.rig), BevGrid()
    classes = WeightsFile.open(a.weights).classes
    seeds = a.val_seeds or val_seeds(a.val_drives)
    frames = held_out_frames(rig, grid, classes, seeds, a.frames_per_drive, a.stride, a.cache, progress=False)
    calibrate_weights(a.weights, a.out, rig, grid, frames, log=lambda m: print(m, flush=True))
    return 0
