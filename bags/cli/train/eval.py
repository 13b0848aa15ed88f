"""``bev-train eval``: score any registered mapper on held-out synthetic drives, through
``create_mapper`` like the node and the bag tool::

    bev-train eval --rig surround6 --method ipm|bimapper [--weights FILE] [--classes ...]
        [--val-drives N | --val-seeds ...] [--json OUT]

or, with ``--real``, a segmenter on real labelled frames (pooled pixel IoU in each dataset's own
classes, the common five and their mean, CPU ms/frame; :mod:`bev_mapper_core.methods.segmenter.real`)::

    bev-train eval --method segmenter --real camvid:DIR [--real folder:DIR[:PRESET] ...]
        [--split test] [--segmenter FILE] [--backend B] [--segmenter-precision f32|int8] [--limit N] [--skip-bad] [--threads T] [--json OUT]
"""

from __future__ import annotations

import argparse
import json

from bev_mapper_core.datasets.camvid import SPLITS
from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.rig import PRESETS
from bev_mapper_core.mapper import BACKENDS, INPUT_KINDS, SEGMENTER_PRECISIONS, MapperConfig
from bev_mapper_core.synth.styles import STYLE_CHOICES
from bev_mapper_core.temporal import TemporalConfig
from bev_mapper_core.training.config import AUTO_CLASSES

from .flags import DEFAULTS, add_held_out_flags, grid_help, grid_name, pos_int, rig_name_arg

HELP = "Score a mapper on held-out synthetic drives."


def configure(p: argparse.ArgumentParser, argv: list[str]) -> None:
    """The mapper's and the held-out drives' flags (defaults: TrainConfig's and MapperConfig's)."""
    p.add_argument("--rig", default=DEFAULTS["rig"], type=rig_name_arg, metavar="RIG",
                   help=f"a preset rig ({', '.join(sorted(PRESETS))}) or random-<seed> (default: %(default)s)")
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
    g = p.add_argument_group("real labelled frames (--method segmenter)")
    g.add_argument("--real", action="append", default=None, metavar="KIND:DIR",
                   help="score the segmenter on a real dataset's split instead of synthetic drives: camvid:DIR or "
                        "folder:DIR[:PRESET] (repeatable; a folder dataset has no splits: all its frames)")
    g.add_argument("--split", default="test", choices=list(SPLITS), help="the datasets' split (default: %(default)s)")
    g.add_argument("--segmenter", default=None, metavar="FILE",
                   help="segmenter weights (default: the shipped segmenter)")
    g.add_argument("--limit", type=pos_int, default=None, help="score only the first N frames of each dataset")
    g.add_argument("--skip-bad", action="store_true", help="leave bad frames out (counted) instead of stopping")
    g.add_argument("--backend", default="torch", choices=list(BACKENDS),
                   help="run the segmenter by this backend (its segmenter stage, as the node does) instead of torch's "
                        "logits (default: %(default)s)")
    g.add_argument("--segmenter-precision", default=MapperConfig.segmenter_precision, choices=list(SEGMENTER_PRECISIONS),
                   help="the stage's precision on an exported --backend (int8: bev_mapper_core.methods.segmenter.int8; "
                        "default: %(default)s)")
    g.add_argument("--timing-frames", type=pos_int, default=10, help="segment() calls timed (default: %(default)s)")


def eval_parser() -> argparse.ArgumentParser:
    """The ``bev-train eval`` parser."""
    from .main import subcommand_parser  # noqa: PLC0415 - the dispatcher imports this module

    return subcommand_parser("eval")


def run(a: argparse.Namespace) -> int:
    """Score the mapper on the held-out drives, print tables (and write ``--json``); with
    ``--real``, the segmenter on real frames (:func:`run_real`).
    """
    if a.real:
        return run_real(a)
    if a.segmenter is not None:
        raise ConfigError("--segmenter names the segmenter scored on real frames (--real); segipm's segmenter is "
                          "the shipped one")
    import os

    import torch

    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.random_rig import rig_by_name
    from bev_mapper_core.metrics import format_table
    from bev_mapper_core.nn.runtime import THREADS_ENV
    from bev_mapper_core.training.config import class_set
    from bev_mapper_core.training.data import val_seeds
    from bev_mapper_core.training.evaluate import evaluate, save_result, summary_header, summary_row

    os.environ[THREADS_ENV] = str(a.threads)  # the Bi-Mapper Mapper sets its own thread count
    torch.set_num_threads(a.threads)
    classes = class_set(a.classes, a.rig)
    seeds = a.val_seeds or val_seeds(a.val_drives)
    res = evaluate(rig_by_name(a.rig), a.grid or BevGrid(), classes, a.method, a.weights, seeds, a.frames_per_drive, a.stride,
                   a.cache, a.device, progress=True, ipm_occlusion=a.ipm_occlusion, unknown_below=a.unknown_below,
                   input_kind=a.input_kind, style=a.style, temporal_window=a.temporal_window)
    print(format_table(res))
    print(f"{res['ms_per_frame']:.1f} ms/frame (mapper.map, {torch.get_num_threads()} threads)")
    print(summary_header(classes, list(res["iou_by_range"])))
    print(summary_row(a.name or a.method, res, classes))
    if a.json:
        save_result(res, a.json)
    return 0


def run_real(a: argparse.Namespace) -> int:
    """Score a segmenter on the ``--split`` of every ``--real`` dataset (pooled pixel IoU per
    dataset class, the common five and their mean), time it on the CPU, print (and write ``--json``).
    """
    import torch

    from bev_mapper_core.methods.segmenter.real import format_report, ms_per_frame, open_split, score_reader, stage_ms_per_frame
    from bev_mapper_core.methods.segmenter.stage import GENERAL_SEGMENTER, shipped_segmenter
    from bev_mapper_core.methods.segmenter.weights import load_segmenter

    if a.method != "segmenter":
        raise ConfigError(f"--real scores a segmenter on real frames: use --method segmenter (not {a.method!r})")
    if a.weights is not None:
        raise ConfigError("--real: name the segmenter file with --segmenter, not --weights")
    torch.set_num_threads(a.threads)
    readers = []
    for spec in a.real:
        reader = open_split(spec, a.split, a.skip_bad)
        if reader is None:
            raise ConfigError(f"{spec}: no {a.split!r} split")
        readers.append((spec, reader))
    path = a.segmenter or shipped_segmenter(a.rig)
    if path is None:
        raise ConfigError(f"no segmenter shipped ({GENERAL_SEGMENTER}); name one with --segmenter FILE")
    model = load_segmenter(path)  # CPU, eval mode
    stage = None
    if a.backend != "torch" or a.segmenter_precision != "f32":
        from bev_mapper_core.methods.segmenter.stage import SegmenterStage

        stage = SegmenterStage(path, backend=a.backend, threads=a.threads, precision=a.segmenter_precision)
        print(f"segmenter stage: backend {stage.backend}, precision {stage.precision}")
    results, first = [], None
    for spec, reader in readers:
        rep = score_reader(model, reader, a.limit or 0, stage=stage)
        results.append({"dataset": spec, "split": a.split, **rep})
        for line in format_report(f"{spec} {a.split}", rep):
            print(line)
        if first is None:
            first = next(iter(reader)).image  # the timing frame: the first dataset's first good frame
    ms = ms_per_frame(model, first, a.timing_frames) if stage is None else stage_ms_per_frame(stage, first, a.timing_frames)
    params = sum(p.numel() for p in model.parameters())
    h, w = first.shape[:2]
    print(f"CPU {ms:.1f} ms/frame ({w}x{h}, {torch.get_num_threads()} thread(s)), {params / 1e6:.2f} M params, "
          f"input {model.config.input_size((w, h))} of {path}")
    if a.json:
        from ...files import write_atomic

        doc = {"segmenter": str(path), "backend": stage.backend if stage else "torch",
               "precision": stage.precision if stage else "f32", "config": model.config.to_dict(), "params": params,
               "threads": torch.get_num_threads(),
               "cpu_ms_per_frame": round(ms, 1), "timing_size": [w, h], "results": results}
        write_atomic(a.json, (json.dumps(doc, indent=1, allow_nan=False) + "\n").encode())
    return 0
