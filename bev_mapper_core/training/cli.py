"""``bev-train``: train Bi-Mapper, or score a mapper on held-out drives (``bev-train eval``).

Training::

    bev-train --method bimapper --rig surround6 --input labels --out runs/NAME \\
        [--config run.yaml] [--epochs E] [--frames-per-epoch F] [--batch B] [--lr 1e-3] [--seed S]
        [--val-seeds 900000000,900000001 | --val-drives N] [--cache DIR | --no-cache]
        [--device cpu|cuda] [--resume] [--streams both|gv|lv] [--fusion sum|concat]
        [--no-asl] [--mutual async|sync|lv|gv|none] [--bag PATH ... --val-bag PATH ...]

Flags override the YAML file, which overrides the :class:`TrainConfig` defaults.

Evaluation (any registered mapper, through ``create_mapper`` like the node and the bag tool)::

    bev-train eval --rig surround6 --method ipm|bimapper [--weights FILE] [--classes ...]
        [--val-drives N | --val-seeds ...] [--json OUT]

Errors print ``error: ...`` on stderr and exit with status 1 (2 for usage errors).
"""

from __future__ import annotations

import argparse
import json
import sys

from ..errors import BevMapperError

EXIT_ERROR, EXIT_USAGE = 1, 2


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
    """argparse type: an integer >= ``lo``."""
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


def train_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="bev-train", description="Train Bi-Mapper on synthetic drives (or bags with GT).",
                epilog="`bev-train eval --help` scores a mapper on held-out drives.", argument_default=argparse.SUPPRESS)
    p.add_argument("--config", help="YAML file of TrainConfig fields (flags override it)")
    p.add_argument("--method", choices=["bimapper"])
    p.add_argument("--rig", choices=["surround6", "cam2bev4", "front1"])
    p.add_argument("--input", choices=["labels", "rgb"])
    p.add_argument("--classes", help="auto | standard | cam2bev | comma list (auto: cam2bev for cam2bev4)")
    p.add_argument("--out", help="run directory")
    p.add_argument("--epochs", type=_pos_int)
    p.add_argument("--frames-per-epoch", dest="frames_per_epoch", type=_pos_int)
    p.add_argument("--batch", type=_pos_int)
    p.add_argument("--lr", type=_pos_float)
    p.add_argument("--lr-step-epoch", dest="lr_step_epoch", type=_nonneg_int, help="0-based; default paper 10/30 scaled")
    p.add_argument("--mutual-start-epoch", dest="mutual_start_epoch", type=_nonneg_int, help="0-based; default paper 4/30 scaled")
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
    p.add_argument("--threads", type=_pos_int)
    p.add_argument("--resume", action="store_true", default=argparse.SUPPRESS)
    p.add_argument("--streams", choices=["both", "gv", "lv", "none"], help="none: only with --ipm-skip (ablation control)")
    p.add_argument("--fusion", choices=["sum", "concat"])
    p.add_argument("--no-asl", dest="asl", action="store_false", default=argparse.SUPPRESS)
    p.add_argument("--lv-full-res", dest="lv_full_res", action="store_true", default=argparse.SUPPRESS,
                   help="LV stream's IPM samples the camera-size images (as the paper)")
    p.add_argument("--ipm-skip", dest="ipm_skip", action="store_true", default=argparse.SUPPRESS,
                   help="full-resolution IPM prior into the decoder head, logits start at IPM's (not in the paper)")
    p.add_argument("--mutual", choices=["async", "sync", "lv", "gv", "none"])
    p.add_argument("--pos-weight", dest="pos_weight", choices=["auto", "none"], help="BCE class weights (none = paper)")
    p.add_argument("--input-width", dest="input_width", type=_pos_int)
    p.add_argument("--gv-hidden", dest="gv_hidden", type=_pos_int)
    p.add_argument("--time-budget", dest="time_budget_min", type=_pos_float, help="minutes; stop (resumable) after")
    p.add_argument("--bag", nargs="+", help="rosbag2 paths with GT topics to train on")
    p.add_argument("--val-bag", dest="val_bag", nargs="+", help="held-out rosbag2 paths with GT")
    p.add_argument("--no-progress", dest="progress", action="store_false", default=argparse.SUPPRESS)
    return p


def eval_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="bev-train eval", description="Score a mapper on held-out synthetic drives.")
    p.add_argument("--rig", default="surround6", choices=["surround6", "cam2bev4", "front1"])
    p.add_argument("--method", default="bimapper")
    p.add_argument("--weights", default=None, help="Bi-Mapper weights (default: the shipped file)")
    p.add_argument("--classes", default="auto")
    p.add_argument("--val-drives", type=_pos_int, default=6)
    p.add_argument("--val-seeds", type=_int_list, default=None)
    p.add_argument("--frames-per-drive", type=_pos_int, default=20)
    p.add_argument("--stride", type=_pos_int, default=3)
    p.add_argument("--cache", default="data/cache")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=_pos_int, default=2)
    p.add_argument("--json", default=None, help="write the metrics here")
    p.add_argument("--name", default=None, help="row name for the markdown summary")
    return p


def run_eval(argv: list[str]) -> int:
    a = eval_parser().parse_args(argv)
    import torch

    from ..grid import BevGrid
    from ..metrics import format_table
    from ..rig import preset_rig
    from .config import class_set
    from .data import val_seeds
    from .evaluate import evaluate, save_result, summary_header, summary_row

    import os

    from ..models.bimapper_mapper import THREADS_ENV

    os.environ[THREADS_ENV] = str(a.threads)  # the Bi-Mapper Mapper sets its own thread count
    torch.set_num_threads(a.threads)
    classes = class_set(a.classes, a.rig)
    seeds = a.val_seeds or val_seeds(a.val_drives)
    res = evaluate(preset_rig(a.rig), BevGrid(), classes, a.method, a.weights, seeds, a.frames_per_drive, a.stride,
                   a.cache, a.device, progress=True)
    print(format_table(res))
    print(f"{res['ms_per_frame']:.1f} ms/frame (mapper.map, {torch.get_num_threads()} threads)")
    print(summary_header(classes, list(res["iou_by_range"])))
    print(summary_row(a.name or a.method, res, classes))
    if a.json:
        save_result(res, a.json)
    return 0


def run_train(argv: list[str]) -> int:
    a = vars(train_parser().parse_args(argv))
    from .config import TrainConfig
    from .trainer import train

    path = a.pop("config", None)
    cfg = TrainConfig.from_yaml(path, **a) if path else TrainConfig.from_dict(a)
    doc = train(cfg, log=lambda m: print(m, flush=True))
    print(json.dumps({"out": cfg.out, "epoch": doc["epoch"] + 1, "step": doc["step"],
                      "best_val_miou": doc["best_val_miou"], "train_seconds": round(doc["train_seconds"], 1)}))
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv[:1] == ["eval"]:
            return run_eval(argv[1:])
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
