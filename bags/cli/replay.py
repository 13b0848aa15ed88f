"""``bev-bag replay BAG --out DIR``: map every frame of a bag offline and score it (see
:mod:`bags.replay`).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from bev_mapper_core.geometry.time_placement import PLACEMENT_MODES, TimePlacementConfig
from bev_mapper_core.labels.label_maps import PRESET_NAMES
from bev_mapper_core.mapper import BACKENDS, INPUT_KINDS, SEGMENTER_PRECISIONS, MapperConfig, available_methods
from bev_mapper_core.metrics import SCOPES, format_table, format_whole_grid_table
from bev_mapper_core.temporal import TemporalConfig
from msg_adapters.errors import SyncConfigError
from msg_adapters.sync import SyncConfig

from ..errors import BagError
from ..io.rig_source import RigChoice
from ..io.writer import STORAGES
from ..memory import keep_freed_memory
from ..replay import ReplayOptions, replay
from ..replay.options import SCORE_PROCESS
from ..replay.score_process import AUTO_MIN_FRAMES, AUTO_MIN_SPARE
from .grid_args import add_grid_args, grid_from_args

HELP = ("map every frame of a bag offline (no DDS), write a BEV bag, pictures, report.html and "
        "metrics.json")

_EPILOG = """\
outputs in DIR (each written under a temporary name and renamed when complete):
  bev_bag/            rosbag2 with the input camera_info + /tf_static, /bev/<class>
                      OccupancyGrids and /bev/image (rgb8 picture) per frame
  frames/*.png        prediction | ground truth | legend, of every --frames-every'th
                      frame (default {every}; 1 = every frame): class colours (colour-
                      blind safe), the frame's IoU per class and mIoU, the ego footprint
                      (4.6 x 1.9 m), axes and a metres scale bar; cells the mapper does
                      not know or the GT cannot see are hatched in both panels
  replay.gif          with --gif, of the same pictures (Pillow, else OpenCV's GIF
                      encoder, else skipped)
  report.html         self-contained page (no network): metrics table, IoU by range
                      and per class, latency histogram, per-frame mIoU and a viewer of
                      frames/*.png (keep it beside frames/); --no-report skips it
  reliability.png     reliability diagram of the published probabilities per class
                      on the visible cells (with their ECE)
  metrics.json        IoU / Chamfer per class, mIoU, IoU by range, latency p50/p95;
                      "occlusion" and "calibration": the whole-grid scores below
                      (written last)

whole-grid scores (a second table; the visible-cell IoU above stays the headline):
  hidden claim%  of the cells no camera sees (/bev/visibility/any; old bags: GT -1),
                 the share published known with p >= 0.5 for the class; false%: of
                 those, where the class is absent in /bev/truth/<class> (bags that
                 have it); also as m^2 per frame
  unknown recall hidden cells published as unknown (-1); known precision: published-
                 known cells that some camera sees
  ECE%           expected calibration error of the published probabilities on the
                 visible known cells, 10 equal-width bins

scoring scope (--scope), for bags with /bev/gt/<class> layers:
  visible  cells whose GT is known, i.e. not -1 in the /bev/gt/<class> grids (the
           synthetic GT marks cells no camera can see as -1). Default.
  ground   like visible, and flat classes (drivable, lane_divider, ped_crossing,
           road_boundary, sidewalk) only where the cell's ground point is seen, from
           /bev/visibility/ground when the bag has it: e.g. the road under a parked car
           is hidden and IPM can only map ground it sees. Object classes (vehicle,
           pedestrian) hide their own ground, so they keep the visible scope.
Frames without GT are mapped but not scored. A damaged bag is replayed up to the
damage, its outputs completed, then 'error: ...' is printed and the exit status is 1.
"""


def configure(p: argparse.ArgumentParser) -> None:
    """Arguments of ``bev-bag replay``."""
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = _EPILOG.format(every=ReplayOptions.frames_every)
    p.add_argument("bag", type=Path, help="input bag: rosbag2 directory, .mcap or .db3")
    p.add_argument("--out", type=Path, required=True, help="output directory")
    add_replay_args(p)


def add_replay_args(p: argparse.ArgumentParser) -> None:
    """The flags of one bag's replay (method, scoring, outputs) but not the bag and ``--out``:
    shared by ``bev-bag replay`` and ``bev-bag evaluate``, read back by :func:`options_from_args`.
    """
    p.add_argument("--method", default=MapperConfig.method, choices=available_methods(),
                   help=f"mapping method (default {MapperConfig.method}: the shipped weights of the bag's rig)")
    p.add_argument("--weights", default=MapperConfig.weights, help="safetensors weights (learned methods)")
    p.add_argument("--device", default=MapperConfig.device, help="torch device of learned methods")
    p.add_argument("--backend", default=MapperConfig.backend, choices=BACKENDS,
                   help="inference runtime of learned methods: torch, onnxruntime or openvino (the model exported to "
                        "ONNX, cached), auto = the fastest installed (default %(default)s)")
    p.add_argument("--segmenter-precision", default=MapperConfig.segmenter_precision, choices=SEGMENTER_PRECISIONS,
                   help="RGB input: the segmenter's arithmetic on an exported backend: auto = bf16 on OpenVINO where "
                        "the CPU has it, else f32; int8 = the export quantized once, cached (default %(default)s)")
    p.add_argument("--input", dest="input_kind", default=MapperConfig.input_kind, choices=INPUT_KINDS,
                   help="camera images to map: semantic labels or RGB")
    p.add_argument("--label-map", default=MapperConfig.label_map, metavar="PRESET|YAML",
                   help=f"what the bag's label images hold: one of {', '.join(PRESET_NAMES)} (cam2bev: "
                        "rgb8 palette images) or a YAML file of upstream id (or colour) -> label name "
                        "(default: %(default)s, this package's own ids)")
    p.add_argument("--ipm-occlusion", action=argparse.BooleanOptionalAction,
                   default=MapperConfig.ipm_occlusion,
                   help="IPM: cells behind the near edge of an object a camera sees are unknown to "
                        "that camera, not the object's flat-ground smear (default: %(default)s)")
    p.add_argument("--unknown-below", type=float, default=MapperConfig.unknown_below,
                   help="Bi-Mapper with a visibility head: cells predicted seen with probability below "
                        "this are unknown, but for those a camera's labels show as a mapped object "
                        "(--ipm-occlusion) (0 = every in-frustum cell known; default: %(default)s)")
    p.add_argument("--segmenter", default=MapperConfig.segmenter, metavar="auto|camvid|open|none|FILE",
                   help="RGB input: the 2-D segmenter of segipm and of label weights run on RGB (auto = camvid, "
                        "trained with CamVid: non-commercial; open: commercial use allowed; default: %(default)s)")
    p.add_argument("--temporal-window", type=int, default=TemporalConfig.window, metavar="N",
                   help="fuse the method's output over the last N frames, aligned by the bag's odometry, in "
                        "log-odds (any method; 1 = off; default: %(default)s)")
    tp = TimePlacementConfig
    p.add_argument("--time-placement", choices=PLACEMENT_MODES, default=tp.mode,
                   help="place each camera with the ego pose (the bag's /odom or /tf) of its own stamp, in base_link "
                        "at the frame's stamp (IPM, segipm: a placed rig; learned methods: moved images warped); "
                        "auto: where the bag has poses (default: %(default)s)")
    p.add_argument("--placement-step-cells", type=float, default=tp.step_cells, metavar="CELLS",
                   help="round each camera's correction to this many grid cells (under half of it: skipped, "
                        "counted as static; 0 = exact, tables rebuilt every frame; default: %(default)s)")
    p.add_argument("--classes", nargs="+", default=None, metavar="CLASS",
                   help="BEV classes to produce (default: the method's)")
    p.add_argument("--scope", default=ReplayOptions.scope, choices=SCOPES,
                   help="cells that are scored (see below)")
    p.add_argument("--max-frames", type=int, default=ReplayOptions.max_frames,
                   help="stop after N mapped frames")
    p.add_argument("--no-pictures", action="store_true", help="write no PNG pictures")
    p.add_argument("--frames-every", "--picture-every", dest="frames_every", type=int,
                   default=ReplayOptions.frames_every, metavar="N",
                   help="a picture of every N-th mapped frame, frame 0 included; 1 = every frame "
                        f"(default {ReplayOptions.frames_every}; --picture-every is an old name)")
    p.add_argument("--gif", action="store_true", help="also write an animated replay.gif")
    p.add_argument("--no-report", action="store_true", help="write no report.html")
    p.add_argument("--pipeline", type=int, default=ReplayOptions.pipeline, metavar="N",
                   help="frames in flight between the threads that read, map, score and write (0 = one "
                        "thread, every stage in turn; the outputs are the same; default: %(default)s)")
    p.add_argument("--score-process", choices=SCORE_PROCESS, default=ReplayOptions.score_process,
                   help="score the frames in a process of their own (auto: drives of "
                        f"{AUTO_MIN_FRAMES} frames or more on 2 cores or more, where other jobs leave "
                        f"{AUTO_MIN_SPARE} of a core free; the outputs are the same; default: %(default)s)")
    p.add_argument("--storage", choices=STORAGES, default=ReplayOptions.storage, help="storage of bev_bag/")
    p.add_argument("--force", action="store_true", help="replace existing outputs in DIR")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    rig = p.add_argument_group(
        "a bag recorded elsewhere (what the bag lacks; its own CameraInfo and /tf_static win where present)")
    rig.add_argument("--rig", default=RigChoice.name, metavar="NAME",
                     help="the bag's rig: a preset (its cameras, in its order, their extrinsics and intrinsics, and "
                          "its shipped weights) or any name; default: the bag's metadata, else a preset whose "
                          "cameras and calibration the bag has, else the bag's file name")
    rig.add_argument("--params-file", type=Path, default=RigChoice.params_file, metavar="FILE",
                     help="the node's parameter file (e.g. config/surround6.yaml): rig, cameras, image_topic / "
                          "camera_info_topic patterns, extrinsics.<camera>, base_frame, grid")
    rig.add_argument("--ego-mask", action="append", default=[], metavar="CAM=PNG",
                     help="the ego vehicle's own pixels in camera CAM (a PNG of its image size, nonzero = ego body), "
                          "ignored by the method; repeatable; wins over the --params-file's ego_mask.<camera> "
                          "(bev-bag propose-mask proposes masks from a drive)")
    live = SyncConfig.replay()
    sync = p.add_argument_group("synchronization of the cameras' images into sets")
    sync.add_argument("--sync-slop-ms", type=float, default=None, metavar="MS",
                      help=f"the widest stamp spread of one set (default {live.slop_ns / 1e6:g} ms, the node's "
                           f"sync_slop_s; never more than {SyncConfig.max_slop_fraction:g} x the cameras' frame period)")
    sync.add_argument("--sync-timeout-ms", type=float, default=None, metavar="MS",
                      help=f"a set waits this long (bag time) for its missing cameras (default {live.timeout_ns / 1e6:g} ms)")
    grid = p.add_argument_group("grid of bags without GT layers (default: the surround grid, or the --params-file's)")
    add_grid_args(grid, "the grid to map onto")


def options_from_args(args: argparse.Namespace) -> ReplayOptions:
    """Validate parsed arguments into :class:`ReplayOptions`."""
    grid = grid_from_args(args, default=None)
    mapper = MapperConfig(method=args.method, input_kind=args.input_kind,
                          classes=tuple(args.classes) if args.classes else None,
                          weights=args.weights, device=args.device, backend=args.backend,
                          ipm_occlusion=args.ipm_occlusion, unknown_below=args.unknown_below,
                          segmenter=args.segmenter, label_map=args.label_map,
                          segmenter_precision=args.segmenter_precision)
    return ReplayOptions(
        bag=args.bag, out=args.out, mapper=mapper, grid=grid, scope=args.scope,
        max_frames=args.max_frames, pictures=not args.no_pictures,
        frames_every=args.frames_every, gif=args.gif, report=not args.no_report,
        storage=args.storage, force=args.force,
        progress=not args.quiet and sys.stderr.isatty(),
        temporal=TemporalConfig(window=args.temporal_window), pipeline=args.pipeline,
        score_process=args.score_process,
        rig=RigChoice(name=args.rig, params_file=args.params_file),
        sync=sync_from_args(args),
        ego_masks=ego_masks_from_args(args.ego_mask),
        placement=TimePlacementConfig(mode=args.time_placement, step_cells=args.placement_step_cells),
    )


def ego_masks_from_args(values: list[str]) -> tuple:
    """``--ego-mask CAM=PNG`` values -> ``(camera, path)`` pairs.

    Raises:
        BagError: a value without ``=``, an empty side, or a camera given twice.
    """
    out: dict[str, str] = {}
    for v in values:
        cam, sep, path = v.partition("=")
        if not sep or not cam or not path:
            raise BagError(f"--ego-mask wants CAM=PNG, got {v!r}")
        if cam in out:
            raise BagError(f"--ego-mask given twice for camera {cam!r}")
        out[cam] = path
    return tuple(out.items())


def sync_from_args(args: argparse.Namespace) -> SyncConfig:
    """``--sync-slop-ms`` / ``--sync-timeout-ms`` -> :meth:`SyncConfig.replay` (a longer timeout
    follows a slop given wider than it).

    Raises:
        BagError: a value that is not a finite number >= 0.
    """
    ms = {}
    for name in ("sync_slop_ms", "sync_timeout_ms"):
        v = getattr(args, name)
        if v is not None and not (math.isfinite(v) and 0 <= v <= 60_000):
            raise BagError(f"--{name.replace('_', '-')} must be a number of milliseconds in [0, 60000], got {v}")
        ms[name] = None if v is None else round(v * 1e6)
    slop, timeout = ms["sync_slop_ms"], ms["sync_timeout_ms"]
    if timeout is None and slop is not None:
        timeout = max(SyncConfig.replay().timeout_ns, slop)
    try:
        return SyncConfig.replay(slop_ns=slop, timeout_ns=timeout)
    except SyncConfigError as exc:
        raise BagError(f"--sync-slop-ms / --sync-timeout-ms: {exc}") from None


def run(args: argparse.Namespace) -> int:
    """Run ``bev-bag replay``: print the metrics table; 1 (after writing) on a damaged bag."""
    options = options_from_args(args)
    keep_freed_memory()  # per-frame arrays reuse the heap (bags/memory.py)
    t0 = time.monotonic()
    result = replay(options)
    m = result.metrics
    if m["frames_scored"]:
        print(format_table(m))
        over = m["miou_classes"]
        print(f"mIoU over {len(over)} class(es): {', '.join(over)}"
              + (f"; NOT scored (no GT of that definition): {', '.join(m['unscored_classes'])}"
                 if m["unscored_classes"] else ""))
        print(f"scope: {m['scope_used']}")
        print()
        print(format_whole_grid_table(m))
    lat = m["latency_ms"]
    lat_text = f"; mapping p50 {lat['p50']} ms, p95 {lat['p95']} ms" if lat["p50"] is not None else ""
    sync = m["sync"]
    sync_text = (f"; {sync['partial_sets']} set(s) without some camera (metrics.json: sync)"
                 if sync["partial_sets"] else "")
    tp = m.get("placement", {})
    tp_text = (f"; {tp['sets_placed']} set(s) with each camera at its own time (up to {tp['max_offset_m']:.2f} m; "
               "metrics.json: placement)" if tp.get("sets_placed") else "")
    print(f"replayed {m['frames']} frame(s) ({m['frames_scored']} scored) with {m['method']} on rig "
          f"{m['rig']['name']!r} in {time.monotonic() - t0:.1f} s{lat_text}{sync_text}{tp_text}; outputs in {result.out}")
    for note in result.notes:
        print(f"note: {note}", file=sys.stderr)
    if result.damage:
        print(f"error: {result.damage}; the outputs are incomplete: they cover {m['frames']} frame(s)",
              file=sys.stderr)
        return 1
    return 0
