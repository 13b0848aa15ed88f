r"""``bev-train``: train a learned method (Bi-Mapper), or score a mapper on held-out drives (``bev-train eval``).

Training::

    bev-train --method bimapper --rig surround6 --input labels --out runs/NAME \\
        [--config run.yaml] [--epochs E] [--frames-per-epoch F] [--batch B] [--lr 1e-3] [--seed S]
        [--val-seeds 900000000,900000001 | --val-drives N] [--cache DIR | --no-cache]
        [--device cpu|cuda] [--threads T] [--nproc N] [--resume] [--bag PATH ... --val-bag PATH ... [--label-map PRESET|YAML]]
        [--unlabeled-drives N [--unlabeled-style STYLE] | --unlabeled BAG ...]   (semi-supervised: s2g2)
        [method flags, Bi-Mapper's: --streams both|gv|lv|none --fusion sum|concat --no-asl
         --mutual async|sync|lv|gv|none --pos-weight auto|none --ipm-skip --lv-full-res ...]

Data-parallel: ``--nproc N`` trains in N local processes (``--batch`` stays the global batch);
``torchrun --nproc-per-node N -m bags.cli.train ...`` runs one rank per torchrun worker (see
``bev_mapper_core.training.distributed``).

Flags override the YAML file, which overrides the :class:`TrainConfig` defaults. The method's
flags come from its plug-in (:attr:`TrainMethod.cli_flags`), choices and defaults from the
constants and dataclasses that own them. This entry point lives in ``bags`` because ``--bag``
needs the bag data source (:class:`bags.io.train_data.BagSource`), which it hands to the core's
trainer; ``bev_mapper_core`` never imports ``bags``.

Evaluation (any registered mapper, through ``create_mapper`` like the node and the bag tool)::

    bev-train eval --rig surround6 --method ipm|bimapper [--weights FILE] [--classes ...]
        [--val-drives N | --val-seeds ...] [--json OUT]

Temperature scaling on validation drives (writes a copy of the weights with ``temperature``)::

    bev-train calibrate --rig surround6 --weights IN --out OUT [--val-seeds ...]

Errors print ``error: ...`` on stderr and exit with status 1 (2 for usage errors).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import fields
from pathlib import Path

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.rig import PRESETS
from bev_mapper_core.labels.label_maps import PRESET_NAMES
from bev_mapper_core.mapper import INPUT_KINDS, MapperConfig
from bev_mapper_core.synth.styles import STYLE_CHOICES, style_help
from bev_mapper_core.temporal import TemporalConfig
from bev_mapper_core.training.config import AUTO_CLASSES, TrainConfig
from bev_mapper_core.training.method import CliFlag, method_class, train_methods

EXIT_ERROR, EXIT_USAGE = 1, 2
#: TrainConfig's field defaults (the flags and the eval command take theirs from here).
DEFAULTS = {f.name: f.default for f in fields(TrainConfig)}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # noqa: D401 - argparse hook
        self.print_usage(sys.stderr)
        print(f"error: {message}", file=sys.stderr)
        raise SystemExit(EXIT_USAGE)


def _int_list(s: str) -> tuple[int, ...]:
    try:
        v = tuple(int(x) for x in s.split(",") if x.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {s!r}") from None
    if not v:
        raise argparse.ArgumentTypeError("empty seed list")
    return v


def _int_at_least(lo: int):
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


_pos_int = _int_at_least(1)
_nonneg_int = _int_at_least(0)


def _pos_float(s: str) -> float:
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {s!r}") from None
    if not v > 0 or v != v or v == float("inf"):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {s}")
    return v


def _nonneg_float(s: str) -> float:
    """A finite float >= 0 (argparse type)."""
    try:
        v = float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {s}") from None
    if not math.isfinite(v) or v < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {s}")
    return v


def _grid_name(s: str):
    """Argparse type: a named grid (:data:`~bev_mapper_core.geometry.grid.GRID_PRESETS`) -> its BevGrid."""
    from bev_mapper_core.geometry.grid import GRID_PRESETS

    if s not in GRID_PRESETS:
        raise argparse.ArgumentTypeError(f"unknown grid {s!r}; named grids: {', '.join(sorted(GRID_PRESETS))}")
    return GRID_PRESETS[s]


def _grid_help() -> str:
    from bev_mapper_core.geometry.grid import GRID_PRESETS

    return "named BEV grid: " + "; ".join(f"{n}: {g.describe()}" for n, g in GRID_PRESETS.items())


def _add_flag(p, f: CliFlag) -> None:
    """Add a method's :class:`CliFlag` (default suppressed: the config dataclass has it)."""
    kw = {"dest": f.dest, "help": f.help, "default": argparse.SUPPRESS}
    if f.action:
        kw["action"] = f.action
    if f.choices is not None:
        kw["choices"] = list(f.choices)
    if f.min_value is not None:
        kw["type"] = _int_at_least(f.min_value)
    if f.number:
        kw["type"] = _nonneg_float
    p.add_argument(f.flag, **kw)


def _method_name(argv: list[str]) -> str:
    """The training method ``argv`` asks for (``--method``, else the ``--config`` file's, else
    the default), to know which method flags to offer; unknown names are left to the parser.
    """
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--method")
    pre.add_argument("--config")
    a, _ = pre.parse_known_args(argv)
    name = a.method
    if name is None and a.config:
        import yaml

        try:
            d = yaml.safe_load(Path(a.config).read_text())
            name = d.get("method") if isinstance(d, dict) else None
        except (OSError, yaml.YAMLError):
            name = None  # TrainConfig.from_yaml reports the file
    return name if name in train_methods() else DEFAULTS["method"]


def train_parser(method: str | None = None) -> argparse.ArgumentParser:
    """The ``bev-train`` parser with the flags of training method ``method`` (default: the default)."""
    cls = method_class(method or DEFAULTS["method"])
    p = _Parser(prog="bev-train", description="Train a learned BEV method on synthetic drives (or bags with GT).",
                epilog="`bev-train eval --help` scores a mapper on held-out drives.", argument_default=argparse.SUPPRESS)
    p.add_argument("--config", help="YAML file of TrainConfig fields (flags override it)")
    p.add_argument("--method", choices=list(train_methods()))
    p.add_argument("--rig", choices=sorted(PRESETS))
    p.add_argument("--input", choices=list(INPUT_KINDS), help="the model's input kind")
    p.add_argument("--classes", help=f"{AUTO_CLASSES} | standard | cam2bev | s2g2 | comma list ({AUTO_CLASSES}: cam2bev for cam2bev4)")
    p.add_argument("--grid", type=_grid_name, metavar="NAME", help=_grid_help() + " (default surround)")
    p.add_argument("--out", help="run directory")
    p.add_argument("--epochs", type=_pos_int)
    p.add_argument("--frames-per-epoch", dest="frames_per_epoch", type=_pos_int)
    p.add_argument("--batch", type=_pos_int)
    p.add_argument("--lr", type=_pos_float)
    p.add_argument("--lr-step-epoch", dest="lr_step_epoch", type=_nonneg_int, help="0-based; default paper 10/30 scaled")
    p.add_argument("--seed", type=_nonneg_int)
    p.add_argument("--train-drives", dest="train_drives", type=_pos_int)
    p.add_argument("--val-drives", dest="val_drives", type=_pos_int)
    p.add_argument("--val-seeds", dest="val_seeds", type=_int_list)
    p.add_argument("--val-frames", dest="val_frames", type=_pos_int, help="held-out frames scored per epoch")
    p.add_argument("--frames-per-drive", dest="frames_per_drive", type=_pos_int)
    p.add_argument("--stride", type=_pos_int)
    p.add_argument("--cache", help="drive cache directory")
    p.add_argument("--no-cache", dest="cache", action="store_const", const=None)
    p.add_argument("--device", help="cpu | cuda[:N]")
    p.add_argument("--threads", type=_pos_int, help="CPU threads of the run (shared by its --nproc processes)")
    p.add_argument("--nproc", type=_pos_int,
                   help=f"data-parallel processes (DistributedDataParallel: gloo on CPU, nccl on CUDA), each "
                        f"taking batch/nproc frames of every batch; rank 0 writes the run (default {DEFAULTS['nproc']}; "
                        f"under torchrun its world size)")
    p.add_argument("--resume", action="store_true", default=argparse.SUPPRESS)
    p.add_argument("--time-budget", dest="time_budget_min", type=_pos_float, help="minutes; stop (resumable) after")
    p.add_argument("--bag", nargs="+", help="rosbag2 paths with GT topics to train on")
    p.add_argument("--val-bag", dest="val_bag", nargs="+", help="held-out rosbag2 paths with GT")
    p.add_argument("--label-map", dest="label_map", metavar="PRESET|YAML",
                   help=f"what the bags' label images hold: one of {', '.join(PRESET_NAMES)} or a YAML file "
                        f"(default {DEFAULTS['label_map']}: this package's ids)")
    p.add_argument("--style", choices=STYLE_CHOICES,
                   help=style_help() + f" (default {DEFAULTS['style']})")
    p.add_argument("--unlabeled-drives", dest="unlabeled_drives", type=_nonneg_int,
                   help="semi-supervised methods (s2g2): synthetic drives used as unlabeled frames "
                        f"(default {DEFAULTS['unlabeled_drives']})")
    p.add_argument("--unlabeled-style", dest="unlabeled_style", choices=STYLE_CHOICES,
                   help="appearance style of the unlabeled drives (default: --style)")
    p.add_argument("--unlabeled", dest="unlabeled_bag", nargs="+", metavar="BAG",
                   help="semi-supervised methods: rosbag2 paths of unlabeled frames (the rig's cameras; no GT "
                        "needed), instead of --unlabeled-drives")
    p.add_argument("--no-progress", dest="progress", action="store_false", default=argparse.SUPPRESS)
    g = p.add_argument_group(f"{cls.name} options")
    for f in cls.cli_flags:
        _add_flag(g, f)
    return p


def eval_parser() -> argparse.ArgumentParser:
    """The ``bev-train eval`` parser (defaults: TrainConfig's and MapperConfig's)."""
    p = _Parser(prog="bev-train eval", description="Score a mapper on held-out synthetic drives.")
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
    p.add_argument("--grid", type=_grid_name, default=None, metavar="NAME", help=_grid_help() + " (default surround)")
    p.add_argument("--val-drives", type=_pos_int, default=DEFAULTS["val_drives"])
    p.add_argument("--val-seeds", type=_int_list, default=None)
    p.add_argument("--frames-per-drive", type=_pos_int, default=DEFAULTS["frames_per_drive"])
    p.add_argument("--stride", type=_pos_int, default=DEFAULTS["stride"])
    p.add_argument("--cache", default=DEFAULTS["cache"])
    p.add_argument("--device", default=DEFAULTS["device"])
    p.add_argument("--threads", type=_pos_int, default=DEFAULTS["threads"])
    p.add_argument("--temporal-window", type=_pos_int, default=TemporalConfig.window, metavar="N",
                   help="fuse the mapper's maps over the last N frames of each drive, aligned by the drive's "
                        "poses (bev_mapper_core.temporal; default %(default)s = off)")
    p.add_argument("--json", default=None, help="write the metrics here")
    p.add_argument("--name", default=None, help="row name for the markdown summary")
    return p


def run_eval(argv: list[str]) -> int:
    """``bev-train eval``: score a mapper on held-out drives, print tables (and write ``--json``)."""
    a = eval_parser().parse_args(argv)
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


def calibrate_parser() -> argparse.ArgumentParser:
    """``bev-train calibrate`` arguments."""
    p = argparse.ArgumentParser(prog="bev-train calibrate",
                                description="fit per-class temperatures of Bi-Mapper weights on validation drives "
                                            "(NLL of the visible cells) and write them into a copy of the file")
    p.add_argument("--rig", default=DEFAULTS["rig"], choices=sorted(PRESETS))
    p.add_argument("--weights", required=True, help="Bi-Mapper weights to calibrate")
    p.add_argument("--out", required=True, help="calibrated weights file to write")
    p.add_argument("--val-drives", type=_pos_int, default=DEFAULTS["val_drives"])
    p.add_argument("--val-seeds", type=_int_list, default=None, help="validation seeds (900000000+, never test seeds)")
    p.add_argument("--frames-per-drive", type=_pos_int, default=DEFAULTS["frames_per_drive"])
    p.add_argument("--stride", type=_pos_int, default=DEFAULTS["stride"])
    p.add_argument("--cache", default=DEFAULTS["cache"])
    p.add_argument("--threads", type=_pos_int, default=DEFAULTS["threads"])
    return p


def run_calibrate(argv: list[str]) -> int:
    """``bev-train calibrate``: temperature scaling of a weights file (see ``training.calibrate``)."""
    a = calibrate_parser().parse_args(argv)
    import torch

    from bev_mapper_core.geometry.grid import BevGrid
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.methods.bimapper.calibrate import calibrate_weights
    from bev_mapper_core.methods.bimapper.weights import WeightsFile
    from bev_mapper_core.training.data import val_seeds
    from bev_mapper_core.training.evaluate import held_out_frames

    torch.set_num_threads(a.threads)
    rig, grid = preset_rig(a.rig), BevGrid()
    classes = WeightsFile.open(a.weights).classes
    seeds = a.val_seeds or val_seeds(a.val_drives)
    frames = held_out_frames(rig, grid, classes, seeds, a.frames_per_drive, a.stride, a.cache, progress=False)
    calibrate_weights(a.weights, a.out, rig, grid, frames, log=lambda m: print(m, flush=True))
    return 0


def run_train(argv: list[str]) -> int:
    """``bev-train [train]``: build the TrainConfig (YAML + flags), pick the data source, train."""
    a = vars(train_parser(_method_name(argv)).parse_args(argv))
    from bev_mapper_core.training.distributed import is_main_process
    from bev_mapper_core.training.trainer import train

    path = a.pop("config", None)
    cfg = TrainConfig.from_yaml(path, **a) if path else TrainConfig.from_dict(a)
    source = None  # the trainer's default: synthetic drives
    if cfg.bag:
        from ..io.train_data import BagSource  # rosbags only when training on bags

        source = BagSource()
    if cfg.unlabeled_bag:
        from bev_mapper_core.training.sources import SynthSource

        from ..io.train_data import UnlabeledBagSource

        source = UnlabeledBagSource(source or SynthSource())
    doc = train(cfg, log=lambda m: print(m, flush=True), data=source)
    if not is_main_process():  # a torchrun worker of rank > 0: rank 0 reports
        return 0
    print(json.dumps({"out": cfg.out, "epoch": doc["epoch"] + 1, "step": doc["step"],
                      "best_val_miou": doc["best_val_miou"], "train_seconds": round(doc["train_seconds"], 1)}))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Console entry point; returns the exit status (0, 1 on errors, 2 on usage errors)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv[:1] == ["eval"]:
            return run_eval(argv[1:])
        if argv[:1] == ["calibrate"]:
            return run_calibrate(argv[1:])
        if argv[:1] == ["train"]:
            argv = argv[1:]
        return run_train(argv)
    except SystemExit as e:
        return int(e.code) if isinstance(e.code, int) else EXIT_USAGE
    except (BevMapperError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("error: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
