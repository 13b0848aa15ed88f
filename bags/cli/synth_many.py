"""``bev-bag synth-many OUT --seeds A..B``: render many synthetic drives as Ray tasks.

One Ray task per seed (``num_cpus=1``), on a local Ray runtime started for the command or on an
existing cluster (``--ray-address``, see :mod:`bags.fleet.ray_tasks`). Two output formats:

* ``--format bag``: ``OUT/drive_<seed>/``, a rosbag2 bag written by ``bev-bag synth``'s own
  :func:`bags.cli.synth.synth_bag`;
* ``--format cache``: ``OUT/<key>/drive_<seed>.npz``, the training drive cache that ``bev-train
  --cache OUT`` reads (:func:`bev_mapper_core.training.data.load_or_render`): a run with the same
  rig, grid, classes, frames per drive, stride (and RGB size / style) finds its drives there.

Every drive is a pure function of its seed and the options, and its files do not depend on the
wall clock, so the output is byte-identical whatever the number of workers or the order in which
they finish. A task renders into a temporary directory of its node and returns the files; this
process writes them into ``OUT`` atomically (temp name + rename), so a drive that is there is
complete, a rerun skips it (``--force`` renders it again), and the cluster's nodes need not share
a filesystem with this machine.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.random_rig import rig_by_name
from bev_mapper_core.geometry.rig import PRESETS
from bev_mapper_core.synth.config import SynthConfig
from bev_mapper_core.synth.styles import STYLE_CHOICES, style_help
from bev_mapper_core.training.config import AUTO_CLASSES, TrainConfig, class_set
from bev_mapper_core.training.data import DriveSpec, drive_path, drive_spec, load_or_render, write_spec

from ..errors import BagError
from ..files import partial_name
from ..fleet.ray_tasks import RayOptions, TaskFailure, add_ray_args, ray_runtime, run_tasks
from ..io.writer import STORAGES, check_output
from .grid_args import add_grid_args, grid_from_args
from .synth import SynthBagOptions, rig_arg, synth_bag

HELP = "render many synthetic drives (one Ray task per seed) into bags or into the training cache"
FORMATS = ("bag", "cache")
#: Most drives one command renders (a typo like 0..10000000000 fails fast).
MAX_SEEDS = 1_000_000


def parse_seeds(text: str) -> tuple[int, ...]:
    """Seeds from ``A..B`` (inclusive: ``3..5`` is 3, 4, 5), a list ``1,2,5`` or both mixed
    (``0..39,900000000..900000005``), in the order given.

    Raises:
        ConfigError: a malformed item, a negative seed, ``B < A``, a seed listed twice, or more
            than :data:`MAX_SEEDS` seeds.
    """
    seeds: list[int] = []
    for item in (s.strip() for s in str(text).split(",")):
        lo, sep, hi = item.partition("..")
        try:
            a, b = int(lo), int(hi if sep else lo)
        except ValueError:
            raise ConfigError(f"bad seeds {text!r}: {item!r} is not a seed N or a range A..B") from None
        if a < 0 or b < a:
            raise ConfigError(f"bad seeds {text!r}: {item!r} must be N >= 0 or A..B with 0 <= A <= B")
        if len(seeds) + b - a + 1 > MAX_SEEDS:
            raise ConfigError(f"bad seeds {text!r}: more than {MAX_SEEDS} drives")
        seeds.extend(range(a, b + 1))
    if len(set(seeds)) != len(seeds):
        dup = sorted({s for s in seeds if seeds.count(s) > 1})[:5] if len(seeds) < 10_000 else "some"
        raise ConfigError(f"bad seeds {text!r}: seeds listed more than once ({dup})")
    return tuple(seeds)


@dataclass(frozen=True)
class SynthManyOptions:
    """Everything ``bev-bag synth-many`` needs.

    Args:
        out: output directory (created).
        seeds: the drives' seeds.
        drive: what each drive is: a :class:`SynthBagOptions` (``--format bag``; its ``out``,
            ``force`` and ``synth.seed`` are replaced per drive) or a
            :class:`~bev_mapper_core.training.data.DriveSpec` (``--format cache``).
        force: render drives that are already in ``out`` again.
        ray: where the tasks run.
        progress: a progress bar over the drives (stderr).
    """

    out: Path
    seeds: tuple[int, ...]
    drive: SynthBagOptions | DriveSpec
    force: bool = False
    ray: RayOptions = field(default_factory=RayOptions)
    progress: bool = True

    def __post_init__(self) -> None:
        if not self.seeds or len(set(self.seeds)) != len(self.seeds) or any(
                isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in self.seeds):
            raise ConfigError(f"seeds must be distinct integers >= 0, got {self.seeds[:5]!r}...")
        if not isinstance(self.drive, (SynthBagOptions, DriveSpec)):
            raise ConfigError(f"drive must be SynthBagOptions or DriveSpec, got {type(self.drive).__name__}")

    @property
    def format(self) -> str:
        """``bag`` or ``cache``."""
        return "bag" if isinstance(self.drive, SynthBagOptions) else "cache"

    def target(self, seed: int) -> Path:
        """Where drive ``seed`` goes: ``OUT/drive_<seed>`` (bag) or ``OUT/<key>/drive_<seed>.npz``."""
        if isinstance(self.drive, SynthBagOptions):
            return Path(self.out) / f"drive_{seed}"
        return drive_path(self.out, self.drive, seed)


def render_seed(seed: int, options: SynthManyOptions) -> dict[str, bytes]:
    """Render drive ``seed`` in a temporary directory (the body of one Ray task): the files of
    :meth:`SynthManyOptions.target`, as ``{path relative to it: bytes}`` (``""``: the file itself).
    """
    with tempfile.TemporaryDirectory(prefix="bev-synth-many-") as tmp:
        if isinstance(options.drive, SynthBagOptions):
            path = Path(tmp) / f"drive_{seed}"  # the storage file is named after the bag
            d = options.drive
            synth_bag(replace(d, out=path, force=False, synth=replace(d.synth, seed=seed)))
            return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}
        spec = options.drive
        load_or_render(rig_by_name(spec.rig), BevGrid(*spec.grid), spec, seed, tmp)
        return {"": drive_path(tmp, spec, seed).read_bytes()}


def _place(options: SynthManyOptions, seed: int, files: dict[str, bytes]) -> None:
    """Write a task's files to ``options.target(seed)`` atomically (a partial copy never shows)."""
    target = options.target(seed)
    tmp = partial_name(target)
    try:
        if isinstance(options.drive, DriveSpec):
            write_spec(target.parent, options.drive)
            tmp.write_bytes(files[""])
        else:
            check_output(target, options.force)  # refuse to replace something that is not a bag
            tmp.mkdir(parents=True)
            for rel, data in files.items():
                (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
                (tmp / rel).write_bytes(data)
            if target.exists():
                shutil.rmtree(target)
        os.replace(tmp, target)
    finally:
        if tmp.is_dir():
            shutil.rmtree(tmp)
        else:
            tmp.unlink(missing_ok=True)


@dataclass(frozen=True)
class SynthManySummary:
    """What :func:`synth_many` did: seeds rendered, skipped (already there) and failed (seed -> why)."""

    rendered: tuple[int, ...]
    skipped: tuple[int, ...]
    failed: dict[int, str]
    seconds: float


def synth_many(options: SynthManyOptions) -> SynthManySummary:
    """Render the drives of ``options.seeds`` not yet in ``options.out`` (all with ``force``) as
    Ray tasks and write them there. A drive that fails is reported in the summary; the others
    complete. Ctrl-C cancels the running tasks and stops Ray; written drives stay.

    Raises:
        BagError: Ray is unavailable or its cluster cannot be joined.
    """
    t0 = time.monotonic()
    Path(options.out).mkdir(parents=True, exist_ok=True)
    skipped = tuple(s for s in options.seeds if not options.force and options.target(s).exists())
    done = frozenset(skipped)
    todo = [s for s in options.seeds if s not in done]
    rendered, failed = [], {}
    if todo:
        from tqdm import tqdm

        cap = options.ray.workers if options.ray.address is not None else None
        with ray_runtime(options.ray) as ray, tqdm(total=len(todo), desc="drives", unit="drive",
                                                   disable=not options.progress, file=sys.stderr) as bar:
            for seed, result in run_tasks(ray, render_seed, todo, options, max_in_flight=cap):
                if isinstance(result, TaskFailure):
                    failed[seed] = result.message
                else:
                    try:
                        _place(options, seed, result)
                        rendered.append(seed)
                    except (OSError, BagError) as exc:
                        failed[seed] = str(exc)
                bar.update(1)
    return SynthManySummary(tuple(rendered), skipped, failed, time.monotonic() - t0)


def configure(p: argparse.ArgumentParser) -> None:
    """Arguments of ``bev-bag synth-many`` (defaults: SynthBagOptions, SynthConfig, TrainConfig)."""
    o, sc, tc = SynthBagOptions, SynthConfig, TrainConfig
    p.add_argument("out", type=Path, help="output directory")
    p.add_argument("--seeds", required=True,
                   help="drive seeds: A..B (inclusive), a list 1,2,5, or both (0..39,900000000..900000005); "
                        "bev-train's training drives of --seed S are S*100000+i, its held-out ones 900000000+i")
    p.add_argument("--format", choices=FORMATS, default=FORMATS[0],
                   help="bag: OUT/drive_<seed>/ rosbag2 bags (as bev-bag synth); cache: OUT/<key>/drive_<seed>.npz, "
                        "the drive cache bev-train --cache OUT reads (default: %(default)s)")
    p.add_argument("--rig", default=o.rig, type=rig_arg, metavar="RIG",
                   help=f"rig preset ({', '.join(sorted(PRESETS))}) or random-<seed> (default: %(default)s)")
    p.add_argument("--frames", type=int, default=None,
                   help=f"frames per drive (default: bag {sc.frames}; cache {tc.frames_per_drive}, bev-train's "
                        "--frames-per-drive)")
    p.add_argument("--style", default=sc.style, choices=STYLE_CHOICES,
                   help=style_help() + " (cache: only with --rgb; label images do not depend on it)")
    add_grid_args(p, "BEV grid of the GT (default surround, bev-train's default)")
    g = p.add_argument_group("--format bag")
    g.add_argument("--scale", type=float, default=None, help=f"image scale of every camera (default {o.scale})")
    g.add_argument("--rate-hz", type=float, default=None, help=f"frame rate (default {sc.rate_hz})")
    g.add_argument("--jitter-ms", type=float, default=None,
                   help=f"max abs per-camera stamp offset from the frame stamp (default {sc.jitter_ms})")
    g.add_argument("--storage", choices=STORAGES, default=None, help=f"rosbag2 storage plugin (default {o.storage})")
    g = p.add_argument_group("--format cache (as bev-train stores its drives)")
    g.add_argument("--stride", type=int, default=None,
                   help=f"render every stride-th frame of the drive (default {tc.stride}, bev-train's --stride)")
    g.add_argument("--classes", default=None,
                   help=f"GT classes: {AUTO_CLASSES} | standard | cam2bev | s2g2 | comma list (default "
                        f"{AUTO_CLASSES}, bev-train's --classes)")
    g.add_argument("--rgb", default=None, metavar="HxW|camera",
                   help="also store the RGB images at this size, as bev-train does for methods that read RGB "
                        "(their input size; camera: the camera's size); default: labels only")
    g = p.add_argument_group("Ray")
    add_ray_args(g, "drives rendered")
    p.add_argument("--force", action="store_true", help="render drives already in OUT again")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")


BAG_ONLY = ("scale", "rate_hz", "jitter_ms", "storage")
CACHE_ONLY = ("stride", "classes", "rgb")


def _rgb_size(text: str | None, rig) -> tuple[int, int] | None:
    """``--rgb``: ``HxW`` or ``camera`` -> ``(h, w)``."""
    if text is None:
        return None
    if text == "camera":
        w, h = rig.cameras[0].model.image_size
        return h, w
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"--rgb must be HxW (e.g. 224x480) or camera, got {text!r}") from None
    if h < 1 or w < 1:
        raise ConfigError(f"--rgb size must be positive, got {text!r}")
    return h, w


def options_from_args(args: argparse.Namespace) -> SynthManyOptions:
    """Validate parsed arguments into :class:`SynthManyOptions` (raises ConfigError/GridError)."""
    seeds = parse_seeds(args.seeds)
    wrong = [n for n in (CACHE_ONLY if args.format == "bag" else BAG_ONLY) if getattr(args, n) is not None]
    if wrong:
        flags = ", ".join("--" + n.replace("_", "-") for n in wrong)
        raise ConfigError(f"{flags} do{'es' if len(wrong) == 1 else ''} not apply to --format {args.format}")
    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames must be >= 1, got {args.frames}")
    grid = grid_from_args(args)
    if args.format == "bag":
        o, sc = SynthBagOptions, SynthConfig
        pick = lambda v, d: d if v is None else v  # noqa: E731 - flag or the dataclass default
        synth = SynthConfig(frames=pick(args.frames, sc.frames), rate_hz=pick(args.rate_hz, sc.rate_hz),
                            jitter_ms=pick(args.jitter_ms, sc.jitter_ms), style=args.style)
        drive = SynthBagOptions(out=Path(args.out), rig=args.rig, scale=pick(args.scale, o.scale),
                                storage=pick(args.storage, o.storage), grid=grid, synth=synth)
    else:
        rig = rig_by_name(args.rig)
        tc = TrainConfig
        rgb = _rgb_size(args.rgb, rig)
        drive = drive_spec(rig, grid, class_set(args.classes or AUTO_CLASSES, args.rig),
                           tc.frames_per_drive if args.frames is None else args.frames,
                           tc.stride if args.stride is None else args.stride, rgb, args.style if rgb else None)
    return SynthManyOptions(out=Path(args.out), seeds=seeds, drive=drive, force=args.force,
                            ray=RayOptions(args.ray_address, args.workers), progress=args.progress)


def run(args: argparse.Namespace) -> int:
    """Run ``bev-bag synth-many``."""
    options = options_from_args(args)
    s = synth_many(options)
    where = options.out if options.format == "bag" else options.target(options.seeds[0]).parent
    rate = f" ({len(s.rendered) / s.seconds:.2f} drives/s)" if s.rendered and s.seconds > 0 else ""
    print(f"{options.format}: {len(s.rendered)} drives rendered, {len(s.skipped)} already there, "
          f"{len(s.failed)} failed, in {where} ({s.seconds:.1f} s){rate}")
    for seed, why in sorted(s.failed.items()):
        print(f"error: seed {seed}: {why}", file=sys.stderr)
    return 1 if s.failed else 0
