"""``bev-bag import DATASET ...``: public datasets' drives into bags (:mod:`bags.importers`).

``bev-bag import nuscenes DATAROOT --version v1.0-mini --scene scene-0061 --out DIR`` writes
``DIR/scene-0061/``; see ``bev-bag import nuscenes --help`` and docs/BAGS.md, "A public dataset".
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .grid_args import add_grid_args, grid_from_args

HELP = "import a public dataset's drives (nuScenes, Argoverse 2) into bags, with ground-truth layers"

_NUSCENES_EPILOG = """\
One MCAP bag per scene, OUT/<scene>/: the six cameras' JPEGs as sensor_msgs/CompressedImage on
/cameras/<cam>/image_raw/compressed (copied, not re-encoded) with CameraInfo, /tf_static, /tf and
/odom from ego_pose, and at each key frame /bev/gt/<class> on the grid: drivable, ped_crossing,
sidewalk (filled drivable_area, ped_crossing, walkway polygons), lane_divider (road and lane
dividers) and road_boundary (the outline of road segments and lanes), both 5 cells wide as
HDMapNet draws them, from maps/expansion/<location>.json (absent: those classes are left unscored,
with a note); vehicle (vehicle.*) and pedestrian (human.pedestrian.*) from the annotation boxes.
Missing or corrupt images are skipped and counted. nuScenes is CC BY-NC-SA 4.0 (non-commercial):
the bags are derived data under the same terms. The devkit is not needed.
"""


def configure(p: argparse.ArgumentParser) -> None:
    """Arguments of ``bev-bag import``: one sub-command per dataset."""
    sub = p.add_subparsers(dest="dataset", metavar="DATASET", required=True)
    from bags.importers.nuscenes.objects import BoxFilter
    from bags.importers.nuscenes.splits import SPLITS
    from bags.importers.nuscenes.tables import VERSIONS

    n = sub.add_parser("nuscenes", help="nuScenes (v1.0-mini, v1.0-trainval, v1.0-test) with its map expansion",
                       description="Import nuScenes scenes into bags.", epilog=_NUSCENES_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    n.add_argument("dataroot", type=Path, help="the nuScenes folder (holding <version>/, samples/, sweeps/, maps/)")
    n.add_argument("--version", required=True, choices=VERSIONS, help="the tables' version")
    which = n.add_mutually_exclusive_group(required=True)
    which.add_argument("--scene", action="append", default=[], metavar="NAME", help="a scene (repeatable)")
    which.add_argument("--split", choices=SPLITS, help="an official split ('all': every scene of the version)")
    n.add_argument("--out", type=Path, required=True, help="folder of the bags (one per scene)")
    n.add_argument("--sweeps", action="store_true", help="also the cameras' frames between key frames (~12 Hz)")
    n.add_argument("--min-visibility", type=int, default=BoxFilter.min_visibility, choices=(1, 2, 3, 4),
                   help="lowest visibility level of a scored box (1: 0-40 %% ... 4: 80-100 %%); others are -1")
    n.add_argument("--min-points", type=int, default=BoxFilter.min_points,
                   help="fewest lidar + radar points of a scored box (default 1, the devkit's evaluation filter)")
    n.add_argument("--force", action="store_true", help="replace existing bags")
    add_grid_args(n, "BEV grid of the GT layers (default surround)")
    n.set_defaults(_dataset_run=_run_nuscenes)

    a = sub.add_parser("av2", help="an Argoverse 2 sensor log (needs pyarrow: pip install 'bev_mapper_ros[av2]')",
                       description="Import one Argoverse 2 sensor log into a bag: the ring cameras' JPEGs, "
                       "calibration, poses, the vector map's drivable areas, crossings, lane dividers and "
                       "road outline, and the cuboids. Argoverse 2 is CC BY-NC-SA 4.0.")
    a.add_argument("logdir", type=Path, help="the log's folder (<split>/<log_id>/)")
    a.add_argument("--out", type=Path, required=True, help="folder of the bag (OUT/<log_id>/)")
    a.add_argument("--force", action="store_true", help="replace an existing bag")
    add_grid_args(a, "BEV grid of the GT layers (default surround)")
    a.set_defaults(_dataset_run=_run_av2)


def run(args: argparse.Namespace) -> int:
    """Run ``bev-bag import``."""
    return args._dataset_run(args)


def _run_av2(args: argparse.Namespace) -> int:
    from bags.importers.av2 import LICENSE, import_av2_log

    t0 = time.monotonic()
    out = args.out / args.logdir.resolve().name
    counts, notes = import_av2_log(args.logdir, out, grid=grid_from_args(args), force=args.force)
    for n in notes + [f"skipped {w}" for w in counts.skipped]:
        print(f"note: {n}", file=sys.stderr)
    print(f"{out.name}: {counts.key_frames} key frames, {counts.images} images -> {out} "
          f"in {time.monotonic() - t0:.1f} s")
    print(f"license: {LICENSE}")
    return 0


def _run_nuscenes(args: argparse.Namespace) -> int:
    from bags.importers.nuscenes import BoxFilter, NuScenesImportOptions, SceneOptions, SceneResult, import_nuscenes
    from bags.importers.nuscenes.scene import LICENSE

    scene = SceneOptions(grid=grid_from_args(args), sweeps=args.sweeps,
                         boxes=BoxFilter(args.min_visibility, args.min_points))
    options = NuScenesImportOptions(args.dataroot, args.version, args.out, tuple(args.scene), args.split,
                                    scene, args.force)
    t0 = time.monotonic()

    def done(r: SceneResult) -> None:
        if r.error:
            print(f"error: {r.name}: {r.error}", file=sys.stderr)
            return
        c = r.counts
        skipped = c.missing_images + c.corrupt_images
        print(f"{r.name}: {c.key_frames} key frames, {c.images} images -> {r.path}"
              + (f" ({c.missing_images} missing, {c.corrupt_images} corrupt images skipped)" if skipped else ""))
        for what in c.skipped:
            print(f"note: skipped {what}", file=sys.stderr)
        if r.left_out_boxes:
            print(f"note: {r.name}: {r.left_out_boxes} boxes below the visibility / point filter left unscored",
                  file=sys.stderr)

    results = import_nuscenes(options, note=lambda s: print(f"note: {s}", file=sys.stderr), done=done)
    ok = [r for r in results if r.error is None]
    frames = sum(r.counts.key_frames for r in ok)
    dt = time.monotonic() - t0
    print(f"imported {len(ok)} of {len(results)} scenes, {frames} key frames in {dt:.1f} s "
          f"({frames / max(dt, 1e-9):.1f} key frames/s)")
    print(f"license: {LICENSE}")
    return 0 if len(ok) == len(results) else 1
