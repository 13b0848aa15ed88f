"""``bev-bag synth OUT``: write a synthetic drive as a rosbag2 bag.

Uses :func:`bev_mapper_core.synth.generate_drive` for the frames and
:func:`bags.io.writer.write_drive` for the topic layout (see :mod:`bags.io.topics`).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.random_rig import check_rig_name, rig_by_name
from bev_mapper_core.geometry.rig import PRESETS, Rig
from bev_mapper_core.labels.classes import BEV_CLASSES, CAM2BEV_CLASSES, S2G2_CLASSES, class_cover
from bev_mapper_core.synth.config import SynthConfig
from bev_mapper_core.synth.styles import STYLE_CHOICES, resolve_style, style_help

from ..errors import BagError
from ..io.writer import STORAGES, DriveSummary, check_output, write_drive
from .grid_args import add_grid_args, grid_from_args

HELP = "write a synthetic drive (images, labels, CameraInfo, TF, odometry, BEV GT) as a bag"
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SynthBagOptions:
    """Everything ``bev-bag synth`` needs.

    Args:
        out: output rosbag2 directory.
        rig: rig preset name, or ``random-<seed>`` (a seeded random rig, :mod:`~bev_mapper_core.geometry.random_rig`).
        scale: image scale applied to every camera of the rig (0.25 = quarter size).
        storage: ``'mcap'`` or ``'sqlite3'``.
        force: overwrite an existing bag at ``out``.
        compressed: images as ``sensor_msgs/CompressedImage`` on ``<image topic>/compressed``
            (RGB as JPEG, label images as PNG).
        grid: the BEV grid of the GT layers.
        synth: generator settings (frames, seed, rate, jitter, ...).
    """

    out: Path
    rig: str = "surround6"
    scale: float = 1.0
    storage: str = "mcap"
    force: bool = False
    compressed: bool = False
    grid: BevGrid = field(default_factory=BevGrid)
    synth: SynthConfig = field(default_factory=SynthConfig)

    def __post_init__(self) -> None:
        check_rig_name(self.rig)  # a preset or random-<seed>
        if not 0.05 <= self.scale <= 4.0:
            raise ConfigError(f"scale must be in [0.05, 4], got {self.scale}")
        if self.storage not in STORAGES:
            raise ConfigError(f"storage must be one of {list(STORAGES)}, got {self.storage!r}")

    def build_rig(self) -> Rig:
        """The preset (or seeded random) rig at the requested image scale."""
        rig = rig_by_name(self.rig)
        return rig if self.scale == 1.0 else rig.scaled(self.scale)


def synth_bag(options: SynthBagOptions) -> DriveSummary:
    """Generate the drive and write it (refusing to overwrite unless ``options.force``).

    Raises:
        BagExistsError: ``options.out`` exists and ``force`` is false.
        BagError: the generator is unavailable or writing failed.
    """
    check_output(Path(options.out), options.force)  # fail before generating anything
    try:
        from bev_mapper_core.synth import generate_drive
    except ImportError as exc:
        raise BagError(f"the synthetic drive generator is not available: {exc}") from None
    rig = options.build_rig()
    custom = {
        "bev_mapper.rig": rig.name,
        "bev_mapper.scale": repr(options.scale),
        "bev_mapper.grid": json.dumps(options.grid.to_dict()),
        "bev_mapper.synth": json.dumps(asdict(options.synth)),
        # the style the drive was rendered in (``mixed`` resolved): what its RGB images look like
        "bev_mapper.style": resolve_style(options.synth.style, options.synth.seed),
    }
    if options.compressed:
        custom["bev_mapper.compressed"] = "rgb: jpeg, labels: png"
    classes = gt_classes(rig.name)
    frames = generate_drive(rig, options.grid, options.synth, classes)
    return write_drive(options.out, rig, options.grid, frames, classes=classes, storage=options.storage,
                       force=options.force, custom_data=custom, compressed=options.compressed)


def rig_arg(name: str) -> str:
    """Argparse type of ``--rig``: a preset or ``random-<seed>``."""
    try:
        return check_rig_name(name)
    except ConfigError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def gt_classes(rig_name: str) -> tuple:
    """GT layers of a synthetic bag: the standard classes, plus the layers that the standard
    ones cannot express of the rig's other class set, so that models of either set are scored on
    it: Cam2BEV's (``static``: curbs, sidewalks, obstacles, buildings, terrain) for ``cam2bev4``,
    S2G2's (``terrain``, ``obstacle``) for the monocular ``front1``.
    """
    other = {"cam2bev4": CAM2BEV_CLASSES, "front1": S2G2_CLASSES}.get(rig_name)
    if other is None:
        return BEV_CLASSES
    names = {c.name for c in BEV_CLASSES}
    extra = tuple(c for c in other if c.name not in names
                  and class_cover(c.name, tuple(names)) is None)
    return BEV_CLASSES + extra


def configure(p: argparse.ArgumentParser) -> None:
    """Arguments of ``bev-bag synth``."""
    o, sc = SynthBagOptions, SynthConfig  # the defaults live there
    p.add_argument("out", type=Path, help="output rosbag2 directory")
    p.add_argument("--rig", default=o.rig, type=rig_arg, metavar="RIG",
                   help=f"rig preset ({', '.join(sorted(PRESETS))}) or random-<seed>, a seeded random rig "
                        "(default: %(default)s)")
    p.add_argument("--scale", type=float, default=o.scale,
                   help="image scale of every camera (e.g. 0.25 for quick tests)")
    p.add_argument("--frames", type=int, default=sc.frames, help="number of frames")
    p.add_argument("--seed", type=int, default=sc.seed, help="random seed")
    p.add_argument("--rate-hz", type=float, default=sc.rate_hz, help="frame rate")
    p.add_argument("--jitter-ms", type=float, default=sc.jitter_ms,
                   help="max abs per-camera stamp offset from the frame stamp")
    p.add_argument("--stagger-ms", type=float, default=sc.stagger_ms,
                   help="the cameras fire this far apart (rig order, from the frame stamp), each rendered at the "
                        "ego pose of its own time and stamped so (e.g. 43, nuScenes' spread; default: %(default)s)")
    p.add_argument("--style", default=sc.style, choices=STYLE_CHOICES, help=style_help())
    p.add_argument("--storage", choices=STORAGES, default=o.storage, help="rosbag2 storage plugin")
    p.add_argument("--force", action="store_true", help="overwrite an existing bag at OUT")
    p.add_argument("--compressed", action="store_true",
                   help="images as sensor_msgs/CompressedImage on <image topic>/compressed (image_transport's "
                        "convention): RGB as JPEG, label images as PNG (JPEG would change the label ids)")
    add_grid_args(p, "BEV grid of the GT layers (default surround)")


def options_from_args(args: argparse.Namespace) -> SynthBagOptions:
    """Validate parsed arguments into :class:`SynthBagOptions` (raises ConfigError/GridError)."""
    grid = grid_from_args(args)
    synth = SynthConfig(frames=args.frames, seed=args.seed, rate_hz=args.rate_hz,
                        jitter_ms=args.jitter_ms, stagger_ms=args.stagger_ms, style=args.style)
    return SynthBagOptions(out=args.out, rig=args.rig, scale=args.scale, storage=args.storage,
                           force=args.force, compressed=args.compressed, grid=grid, synth=synth)


def run(args: argparse.Namespace) -> int:
    """Run ``bev-bag synth``."""
    options = options_from_args(args)
    t0 = time.monotonic()
    summary = synth_bag(options)
    total = sum(summary.counts.values())
    print(
        f"wrote {summary.frames} frames, {total} messages on {len(summary.counts)} topics "
        f"({options.storage}) to {summary.path} in {time.monotonic() - t0:.1f} s"
    )
    return 0
