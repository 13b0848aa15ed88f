"""``bev-train eval``: score any registered mapper on held-out synthetic drives, through
``create_mapper`` like the node and the bag tool::

    bev-train eval --rig surround6 --method ipm|bimapper [--weights FILE] [--classes ...]
        [--val-drives N | --val-seeds ...] [--json OUT]
"""

from __future__ import annotations

import argparse

from bev_mapper_core.geometry.rig import PRESETS
from bev_mapper_core.mapper import INPUT_KINDS, MapperConfig
from bev_mapper_core.synth.styles import STYLE_CHOICES
from bev_mapper_core.temporal import TemporalConfig
from bev_mapper_core.training.config import AUTO_CLASSES

from .flags import DEFAULTS, add_held_out_flags, grid_help, grid_name, pos_int

HELP = "Score a mapper on held-out synthetic drives."


def configure(p: argparse.ArgumentParser, argv: list[str]) -> None:
    """The mapper's and the held-out drives' flags (defaults: TrainConfig's and MapperConfig's)."""
    p.add_argument("--rig", default=DEFAULTS["rig"], choices=sorted(PRESETS))
    p.add_argument("--method", default=MapperConfig.method, help="a registered mapper (ipm, bimapper, ...)")
    p.add_argument("--weights", default=None, help="the learned method's weights (default: the shipped file)")
    p.add_argument("--input", dest="input_kind", default=MapperConfig.input_kind, choices=list(INPUT_KINDS),
                   help="what the mapper reads: label images or the RGB camera images (default: %(default)s)")
    p.add_argument("--style", default=None, choices=STYLE_CHOICES,
                   help="appearance style of the held-out drives' RGB images (--input rgb; default: the synthesizer's)")
    p.add_argument("--ipm-occlusion", action=argparse.BooleanOptionalAction,
                   default=MapperConfig.ipm_occlusion,
                   help="IPM's occlusion reasoning (default: %(default)s; --no-ipm-occlusion = the "
                        "classical IPM of the figures in docs/RESULTS.md before 'Honest maps')")
    p.add_argument("--unknown-below", type=float, default=MapperConfig.unknown_below,
                   help="Bi-Mapper with a visibility head: p_visible threshold of known cells (default: %(default)s)")
    p.add_argument("--classes", default=AUTO_CLASSES)
    p.add_argument("--grid", type=grid_name, default=None, metavar="NAME", help=grid_help() + " (default surround)")
    add_held_out_flags(p)
    p.add_argument("--device", default=DEFAULTS["device"])
    p.add_argument("--threads", type=pos_int, default=DEFAULTS["threads"])
    p.add_argument("--temporal-window", type=pos_int, default=TemporalConfig.window, metavar="N",
                   help="fuse the mapper's maps over the last N frames of each drive, aligned by the drive's "
                        "poses (bev_mapper_core.temporal; default %(default)s = off)")
    p.add_argument("--json", default=None, help="write the metrics here")
    p.add_argument("--name", default=None, help="row name for the markdown summary")


def eval_parser() -> argparse.ArgumentParser:
    """The ``bev-train eval`` parser."""
    from .main import subcommand_parser  # noqa: PLC0415 - the dispatcher imports this module

    return subcommand_parser("eval")


def run(a: argparse.Namespace) -> int:
    """Score the mapper on the held-out drives, print tables (and write ``--json``)."""
    import os

    import torch

    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.metrics import format_table
    from bev_mapper_core.nn.runtime import THREADS_ENV
    from bev_mapper_core.training.config import class_set
    from bev_mapper_core.training.data import val_seeds
    from bev_mapper_core.training.evaluate import evaluate, save_result, summary_header, summary_row

    os.environ[THREADS_ENV] = str(a.threads)  # the Bi-Mapper Mapper sets its own thread count
    torch.set_num_threads(a.threads)
    classes = class_set(a.classes, a.rig)
    seeds = a.val_seeds or val_seeds(a.val_drives)
    res = evaluate(preset_rig(a.rig), a.grid or BevGrid(), classes, a.method, a.weights, seeds, a.frames_per_drive, a.stride,
                   a.cache, a.device, progress=True, ipm_occlusion=a.ipm_occlusion, unknown_below=a.unknown_below,
                   input_kind=a.input_kind, style=a.style, temporal_window=a.temporal_window)
    print(format_table(res))
    print(f"{res['ms_per_frame']:.1f} ms/frame (mapper.map, {torch.get_num_threads()} threads)")
    print(summary_header(classes, list(res["iou_by_range"])))
    print(summary_row(a.name or a.method, res, classes))
    if a.json:
        save_result(res, a.json)
    return 0
