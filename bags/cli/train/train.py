r"""``bev-train [train]``: train a learned method on synthetic drives (or bags with GT).

::

    bev-train --method bimapper --rig surround6 --input labels --out runs/NAME \\
        [--config run.yaml] [--epochs E] [--frames-per-epoch F] [--batch B] [--lr 1e-3] [--seed S]
        [--val-seeds 900000000,900000001 | --val-drives N] [--cache DIR | --no-cache]
        [--device cpu|cuda] [--threads T] [--nproc N] [--resume] [--bag PATH ... --val-bag PATH ... [--label-map PRESET|YAML]]
        [--bag DIR ... --split train --val-split val]   (imported datasets: their own split)
        [--unlabeled-drives N [--unlabeled-style STYLE] | --unlabeled BAG ...] [--unlabeled-real camvid:DIR]   (semi-supervised: s2g2)
        [method flags, Bi-Mapper's: --streams both|gv|lv|none --fusion sum|concat --no-asl
         --mutual async|sync|lv|gv|none --pos-weight auto|none --ipm-skip --lv-full-res ...]

Data-parallel: ``--nproc N`` trains in N local processes (``--batch`` stays the global batch);
``torchrun --nproc-per-node N -m bags.cli.train ...`` runs one rank per torchrun worker (see
``bev_mapper_core.training.distributed``).

Flags override the YAML file, which overrides the :class:`TrainConfig` defaults. The method's
flags come from its plug-in (:attr:`TrainMethod.cli_flags`), choices and defaults from the
constants and dataclasses that own them. This command lives in ``bags`` because ``--bag``
needs the bag data source (:class:`bags.io.train_data.BagSource`), which it hands to the core's
trainer; ``bev_mapper_core`` never imports ``bags``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from bev_mapper_core.geometry.random_rig import RANDOM_RIGS
from bev_mapper_core.geometry.rig import PRESETS
from bev_mapper_core.labels.label_maps import PRESET_NAMES
from bev_mapper_core.mapper import INPUT_KINDS
from bev_mapper_core.synth.styles import STYLE_CHOICES, style_help
from bev_mapper_core.training.config import AUTO_CLASSES, TrainConfig
from bev_mapper_core.training.method import method_class, train_methods

from .flags import DEFAULTS, add_method_flag, grid_help, grid_name, int_list, nonneg_int, pos_float, pos_int

HELP = "Train a learned BEV method on synthetic drives (or bags with GT)."


def method_name(argv: list[str]) -> str:
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


def configure(p: argparse.ArgumentParser, argv: list[str]) -> None:
    """TrainConfig's flags (no defaults: the YAML file and the dataclasses have them) and those of
    the method ``argv`` names.
    """
    cls = method_class(method_name(argv))
    p.argument_default = argparse.SUPPRESS
    p.epilog = "`bev-train eval --help` scores a mapper on held-out drives; `bev-train calibrate --help` calibrates weights."
    p.add_argument("--config", help="YAML file of TrainConfig fields (flags override it)")
    p.add_argument("--method", choices=list(train_methods()))
    p.add_argument("--rig", choices=sorted(PRESETS) + [RANDOM_RIGS],
                   help=f"a preset rig, or {RANDOM_RIGS}: every drive its own random rig (a rig-free model: Bi-Mapper's "
                        "LV stream alone)")
    p.add_argument("--input", choices=list(INPUT_KINDS), help="the model's input kind")
    p.add_argument("--classes", help=f"{AUTO_CLASSES} | standard | cam2bev | s2g2 | comma list ({AUTO_CLASSES}: cam2bev for cam2bev4)")
    p.add_argument("--grid", type=grid_name, metavar="NAME", help=grid_help() + " (default surround)")
    p.add_argument("--out", help="run directory")
    p.add_argument("--epochs", type=pos_int)
    p.add_argument("--frames-per-epoch", dest="frames_per_epoch", type=pos_int)
    p.add_argument("--batch", type=pos_int)
    p.add_argument("--lr", type=pos_float)
    p.add_argument("--lr-step-epoch", dest="lr_step_epoch", type=nonneg_int, help="0-based; default paper 10/30 scaled")
    p.add_argument("--grad-clip", dest="grad_clip", type=pos_float,
                   help="clip the gradients' global norm to this before each step (default off)")
    p.add_argument("--seed", type=nonneg_int)
    p.add_argument("--train-drives", dest="train_drives", type=pos_int)
    p.add_argument("--val-drives", dest="val_drives", type=pos_int)
    p.add_argument("--val-seeds", dest="val_seeds", type=int_list)
    p.add_argument("--val-frames", dest="val_frames", type=pos_int, help="held-out frames scored per epoch")
    p.add_argument("--frames-per-drive", dest="frames_per_drive", type=pos_int)
    p.add_argument("--stride", type=pos_int)
    p.add_argument("--cache", help="drive cache directory")
    p.add_argument("--no-cache", dest="cache", action="store_const", const=None)
    p.add_argument("--device", help="cpu | cuda[:N]")
    p.add_argument("--threads", type=pos_int, help="CPU threads of the run (shared by its --nproc processes)")
    p.add_argument("--nproc", type=pos_int,
                   help=f"data-parallel processes (DistributedDataParallel: gloo on CPU, nccl on CUDA), each "
                        f"taking batch/nproc frames of every batch; rank 0 writes the run (default {DEFAULTS['nproc']}; "
                        f"under torchrun its world size)")
    p.add_argument("--resume", action="store_true", default=argparse.SUPPRESS)
    p.add_argument("--time-budget", dest="time_budget_min", type=pos_float, help="minutes; stop (resumable) after")
    p.add_argument("--bag", nargs="+", help="rosbag2 paths with GT topics to train on")
    p.add_argument("--val-bag", dest="val_bag", nargs="+", help="held-out rosbag2 paths with GT")
    p.add_argument("--split", help="train on the bags of --bag whose metadata names this split of their dataset "
                   "(bev-bag import records it: nuScenes train / val / mini_train / mini_val, Argoverse 2 train / val)")
    p.add_argument("--val-split", dest="val_split",
                   help="hold out the bags of --val-bag (else of --bag) in this split (with --split)")
    p.add_argument("--label-map", dest="label_map", metavar="PRESET|YAML",
                   help=f"what the bags' label images hold: one of {', '.join(PRESET_NAMES)} or a YAML file "
                        f"(default {DEFAULTS['label_map']}: this package's ids)")
    p.add_argument("--style", choices=STYLE_CHOICES,
                   help=style_help() + f" (default {DEFAULTS['style']})")
    p.add_argument("--unlabeled-drives", dest="unlabeled_drives", type=nonneg_int,
                   help="semi-supervised methods (s2g2): synthetic drives used as unlabeled frames "
                        f"(default {DEFAULTS['unlabeled_drives']})")
    p.add_argument("--unlabeled-style", dest="unlabeled_style", choices=STYLE_CHOICES,
                   help="appearance style of the unlabeled drives (default: --style)")
    p.add_argument("--unlabeled", dest="unlabeled_bag", nargs="+", metavar="BAG",
                   help="semi-supervised methods: rosbag2 paths of unlabeled frames (the rig's cameras; no GT "
                        "needed), instead of --unlabeled-drives")
    p.add_argument("--unlabeled-real", dest="unlabeled_real", metavar="camvid:DIR|folder:DIR",
                   help="semi-supervised methods on a one-camera rig: a real-image dataset's training images as "
                        "unlabeled frames (centre-cropped to the camera's aspect, labels never read), beside "
                        "--unlabeled-drives")
    p.add_argument("--unlabeled-real-frames", dest="unlabeled_real_frames", type=nonneg_int,
                   help=f"the first N images of --unlabeled-real (default {DEFAULTS['unlabeled_real_frames']}: all)")
    p.add_argument("--no-progress", dest="progress", action="store_false", default=argparse.SUPPRESS)
    g = p.add_argument_group(f"{cls.name} options")
    for f in cls.cli_flags:
        add_method_flag(g, f)


def train_parser(method: str | None = None) -> argparse.ArgumentParser:
    """The ``bev-train`` parser with the flags of training method ``method`` (default: the default)."""
    from .main import subcommand_parser  # noqa: PLC0415 - the dispatcher imports this module

    return subcommand_parser("train", ["--method", method] if method else [])


def run(args: argparse.Namespace) -> int:
    """Build the TrainConfig (YAML + flags), pick the data source, train."""
    a = vars(args)
    from bev_mapper_core.training.distributed import is_main_process
    from bev_mapper_core.training.trainer import train

    path = a.pop("config", None)
    cfg = TrainConfig.from_yaml(path, **a) if path else TrainConfig.from_dict(a)
    source = None  # the trainer's default: synthetic drives
    if cfg.bag:
        from ...io.train_data import BagSource  # rosbags only when training on bags

        source = BagSource()
    if cfg.unlabeled_bag:
        from bev_mapper_core.training.sources import SynthSource

        from ...io.train_data import UnlabeledBagSource

        source = UnlabeledBagSource(source or SynthSource())
    doc = train(cfg, log=lambda m: print(m, flush=True), data=source)
    if not is_main_process():  # a torchrun worker of rank > 0: rank 0 reports
        return 0
    print(json.dumps({"out": cfg.out, "epoch": doc["epoch"] + 1, "step": doc["step"],
                      "best_val_miou": doc["best_val_miou"], "train_seconds": round(doc["train_seconds"], 1)}))
    return 0
