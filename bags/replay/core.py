"""Offline, deterministic replay of a bag through a BEV mapper (no ROS graph, no DDS).

:func:`replay` reads a bag with :class:`~bags.io.reader.BagReader`, builds the rig from the bag's
own CameraInfo and ``/tf_static`` and the grid from its GT layers (``options.grid`` or
``BevGrid()`` when the bag has no GT), maps every synchronized frame with
:func:`~bev_mapper_core.mapper.create_mapper` and writes into ``options.out``:

* ``bev_bag/``: a rosbag2 (MCAP by default) with the input CameraInfo and ``/tf_static`` plus
  ``/bev/<class>`` OccupancyGrids and ``/bev/image`` (rgb8 picture) per frame, written by
  :class:`~bags.io.writer.BagWriter` (temporary directory + rename);
* ``frames/frame_NNNN.png``: prediction vs ground truth for every ``frames_every``-th frame
  (every frame with ``frames_every=1``), with a legend (class colours, the frame's IoU per
  class), the ego footprint, axes and a scale bar, and the frame's mIoU in the caption (see
  :func:`~bags.report.pictures.comparison_picture`); ``replay.gif`` of the same pictures on request;
* ``report.html``: a self-contained page (inline CSS, SVG charts and a few lines of JS, nothing
  fetched) with the metrics table, IoU by range and per class, the latency histogram, the
  per-frame mIoU and a viewer of ``frames/*.png`` (see :mod:`bags.report.html`); unless
  ``report=False``;
* ``reliability.png``: the reliability diagram of the published probabilities per class on
  the visible cells (:mod:`bags.report.reliability`), when frames were scored;
* ``metrics.json``: :class:`~bev_mapper_core.metrics.MetricAccumulator` results over the frames
  with GT, the scoring scope and mapping latency percentiles, and beside them the whole-grid
  scores of :class:`~bev_mapper_core.metrics.WholeGridAccumulator` (keys ``occlusion`` and
  ``calibration``: occluded claims, unknown recall, known precision, ECE). Written last.

Every file appears under its final name only when complete. A damaged bag is replayed up to
the damage: the outputs of the frames before it are completed and :attr:`ReplayResult.damage`
says what happened (the CLI then exits non-zero). The same holds for damage that does not stop
the reading: messages the reader skipped (undecodable, of the wrong size, invalid stamps),
cameras without calibration, storage the integrity checks found damaged, and a frame the
mapper fails on (the replay stops there). ``metrics.json`` counts the skipped messages
(``decode_errors``, ``bad_stamps``, ``input_problems`` per topic,
``cameras_without_calibration``) and says ``complete: false`` with the ``damage``.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.labels.classes import bev_picture, class_cover, resolve_classes
from bev_mapper_core.labels.label_maps import label_map
from bev_mapper_core.mapper import BevPrediction, MapperConfig, create_mapper
from bev_mapper_core.metrics import SCOPES, MetricAccumulator, WholeGridAccumulator, scope_masks
from bev_mapper_core.temporal import TemporalConfig, TemporalFusion
from msg_adapters import make_image, make_occupancy_grid

from ..errors import BagContentError, BagCorruptError, BagError, BagExistsError
from ..io import topics as T
from ..io.reader import BagReader
from ..io.writer import STORAGES, BagWriter
from ..report.html import render_report
from ..report.pictures import comparison_picture, encode_gif, encode_png, partial_name, write_atomic
from ..report.reliability import reliability_picture
from .frame_scores import FrameScores
from .pipeline import InOrder, Prefetch

log = logging.getLogger(__name__)

OUT_PREFIX = "/bev/"
IMAGE_TOPIC = "/bev/image"
BAG_DIR, FRAMES_DIR, METRICS_FILE, GIF_FILE = "bev_bag", "frames", "metrics.json", "replay.gif"
REPORT_FILE, RELIABILITY_FILE = "report.html", "reliability.png"


@dataclass(frozen=True)
class ReplayOptions:
    """Everything :func:`replay` needs.

    Args:
        bag: input bag (rosbag2 directory, ``.mcap`` or ``.db3``).
        out: output directory (created if needed).
        mapper: method settings.
        grid: grid used only when the bag has no GT layers (``None`` = ``BevGrid()``).
        scope: ``'visible'`` scores cells whose GT is not -1; ``'ground'`` additionally requires,
            for flat classes, ``/bev/visibility/ground`` (the cell's ground point is seen by a
            camera); object classes keep the visible scope (see :class:`ReplayScorer`).
        max_frames: stop after this many mapped frames (``None`` = all).
        pictures: write PNG pictures; ``frames_every``: of every k-th mapped frame (frame 0
            included; 1 = every frame). The default 10 keeps long drives cheap: a picture
            (drawing + PNG) costs about as much as mapping the frame with IPM (~6 ms) and
            ~100 kB on disk.
        gif: also write an animated GIF of the pictures.
        report: write ``report.html``.
        storage: storage of the output bag.
        force: replace existing outputs in ``out``.
        progress: show a tqdm progress bar on stderr.
        temporal: method-independent temporal fusion of the mapper's output over the last
            frames, aligned by the bag's odometry (:mod:`bev_mapper_core.temporal`; window 1 =
            off). Frames without odometry are mapped alone and counted.
        pipeline: frames in flight between the stages of the replay's pipeline
            (:mod:`bags.replay.pipeline`: one thread reads and decodes the next frames, this one maps,
            one scores and writes the frames mapped before); 0 = one thread, every stage in turn.
            The outputs are the same either way, but the mapping latencies in ``metrics.json``
            are measured while the other stages run (0: the mapper's time alone).
    """

    bag: Path
    out: Path
    mapper: MapperConfig = field(default_factory=MapperConfig)
    grid: BevGrid | None = None
    scope: str = "visible"
    max_frames: int | None = None
    pictures: bool = True
    frames_every: int = 10
    gif: bool = False
    report: bool = True
    storage: str = "mcap"
    force: bool = False
    progress: bool = False
    temporal: TemporalConfig = field(default_factory=TemporalConfig)
    pipeline: int = 4

    def __post_init__(self) -> None:
        if self.scope not in SCOPES:
            raise BagError(f"scope must be one of {list(SCOPES)}, got {self.scope!r}")
        if self.max_frames is not None and self.max_frames < 1:
            raise BagError(f"--max-frames must be >= 1, got {self.max_frames}")
        if self.pipeline < 0:
            raise BagError(f"--pipeline must be >= 0, got {self.pipeline}")
        if self.frames_every < 1:
            raise BagError(f"--frames-every must be >= 1, got {self.frames_every}")
        if self.storage not in STORAGES:
            raise BagError(f"storage must be one of {list(STORAGES)}, got {self.storage!r}")


@dataclass
class ReplayResult:
    """What :func:`replay` did: the metrics dict, output paths, damage note, GIF note, and per
    mapped frame its mapping latency (ms) and, per scored frame, its IoU per class.
    """

    metrics: dict
    out: Path
    bag_path: Path
    pictures: list[Path]
    gif: Path | None = None
    gif_note: str = ""
    damage: str | None = None
    notes: list[str] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    frame_scores: FrameScores = field(default_factory=FrameScores)
    report: Path | None = None
    reliability: Path | None = None
    #: the mergeable scoring state (:meth:`ReplayScorer.state`; ``None``: nothing scored), so
    #: that several replays add up exactly (``bev-bag evaluate``)
    scoring: dict | None = None


def _check_outputs(out: Path, force: bool) -> None:
    if out.exists() and not out.is_dir():
        raise BagExistsError(f"{out} exists and is not a directory")
    existing = [n for n in (BAG_DIR, FRAMES_DIR, METRICS_FILE, GIF_FILE, REPORT_FILE, RELIABILITY_FILE)
                if (out / n).exists()]
    if existing and not force:
        raise BagExistsError(f"{out} already holds replay outputs {existing}; pass --force to "
                             "replace them")


def _percentiles(values: list[float]) -> dict:
    if not values:
        return {"p50": None, "p95": None, "mean": None, "max": None}
    a = np.asarray(values, np.float64)
    return {"p50": round(float(np.percentile(a, 50)), 3), "p95": round(float(np.percentile(a, 95)), 3),
            "mean": round(float(a.mean()), 3), "max": round(float(a.max()), 3)}


class _InfoCopier:
    """Copies CameraInfo and ``/tf_static`` of the input bag into the output bag, in time order.

    A second reader on the same bag streams those topics lazily; :meth:`upto` writes what was
    logged up to a time. Damage on this stream just ends the copy (the frame stream reports it).
    """

    def __init__(self, bag: Path, reader: BagReader, writer: BagWriter) -> None:
        self.topics = [T.camera_info_topic(c) for c in reader.camera_names]
        if T.TF_STATIC in reader.topics:
            self.topics.insert(0, T.TF_STATIC)
        for t in self.topics:
            writer.add_topic(t, reader.topics[t].msgtype, latched=t == T.TF_STATIC)
        self._writer = writer
        quiet = logging.getLogger("bags.io.sources")  # the frame reader already warned about damage
        level = quiet.level
        quiet.setLevel(logging.ERROR)
        try:
            self._reader = BagReader(bag)
        finally:
            quiet.setLevel(level)
        self._it: Iterator | None = self._reader.messages(self.topics)
        self._next = None

    def upto(self, log_ns: int) -> None:
        """Write every copied message logged at or before ``log_ns``."""
        while self._it is not None:
            if self._next is None:
                try:
                    self._next = next(self._it)
                except (StopIteration, BagCorruptError):
                    self._it = None
                    return
            if self._next.log_ns > log_ns and self._next.topic != T.TF_STATIC:
                return
            m, self._next = self._next, None
            self._writer.write(m.topic, m.msg, m.log_ns)

    def close(self) -> None:
        """Release the second reader."""
        self._it = None
        self._reader.close()


def _frame_time(frame) -> int:
    stamps = [s for s in frame.camera_stamps.values() if s is not None]
    return max(stamps + [frame.stamp_ns])


def replay(options: ReplayOptions, progress: Callable | None = None) -> ReplayResult:
    """Replay ``options.bag`` through the mapper and write the outputs (see module docstring).

    ``progress(total)``, when given, replaces the tqdm bar of ``options.progress``: it is called
    once with the number of frames expected (``None``: unknown) and returns an object with
    ``update(n)`` (``n`` more frames mapped) and ``close()``, like a tqdm bar.

    Raises:
        BagExistsError: outputs exist and ``options.force`` is false.
        BagError / BevMapperError: unreadable bag, unusable calibration, mapper errors. Nothing
            is written then. Damage met *while reading frames* is not raised: it is returned in
            :attr:`ReplayResult.damage` after the outputs of the intact frames were written.
    """
    out = Path(options.out)
    _check_outputs(out, options.force)
    with BagReader(options.bag) as reader:
        rig = reader.rig()
        grid = reader.grid()
        notes: list[str] = []
        if grid is None:
            grid = options.grid or BevGrid()
            notes.append(f"the bag has no GT layers: mapping onto {grid.describe()}, no metrics")
        elif options.grid is not None and not options.grid.isclose(grid):
            raise BagContentError(
                f"the bag's GT grid is {grid.describe()}; grid flags only apply to bags without GT")
        mapper = create_mapper(rig, grid, options.mapper)
        out.mkdir(parents=True, exist_ok=True)
        tmp_frames = partial_name(out / FRAMES_DIR)
        shutil.rmtree(tmp_frames, ignore_errors=True)
        try:
            result = _run(options, reader, rig, grid, mapper, out, tmp_frames, notes, progress)
        finally:
            shutil.rmtree(tmp_frames, ignore_errors=True)
    return result


def _run(options, reader, rig, grid, mapper, out, tmp_frames, notes, progress=None) -> ReplayResult:
    kind = options.mapper.input_kind
    gt_names = reader.gt_classes
    has_ground = T.GROUND_VISIBILITY in reader.topics
    scorer = ReplayScorer(grid, mapper.class_names, gt_names,
                     ground=options.scope == "ground" and has_ground)
    if gt_names and scorer.mapped:
        notes.append("classes scored against GT layers of the same definition: "
                     + ", ".join(f"{c} = {' + '.join(g)}" for c, g in scorer.mapped.items()))
    if gt_names and scorer.unscored:
        notes.append(f"WARNING: NOT SCORED: {scorer.unscored}: the bag has no GT layer of that definition "
                     f"(its GT layers: {list(gt_names)}); mIoU is over {list(scorer.class_map)} only")
    if options.scope == "ground" and gt_names and not has_ground:
        notes.append("scope 'ground' requested but the bag has no /bev/visibility/ground: "
                     "scoring visible cells only")
    image_topic = T.image_topic(rig.names[0], kind)
    total = reader.topics[image_topic].count if image_topic in reader.topics else None
    if options.max_frames is not None:
        total = min(total or options.max_frames, options.max_frames)
    from tqdm import tqdm  # noqa: PLC0415 - only the replay needs it

    bar = progress(total) if progress is not None else tqdm(
        total=total, unit="frame", disable=not options.progress, leave=False, dynamic_ncols=True)
    latencies: list[float] = []
    pictures: list[Path] = []
    gif_frames: list[np.ndarray] = []
    scores = FrameScores()
    mapped = skipped = 0
    damage = None
    frames_dir = out / FRAMES_DIR
    if options.pictures:
        tmp_frames.mkdir()
    ego = reader.ego_frame
    with BagWriter(out / BAG_DIR, storage=options.storage, force=options.force) as bw:
        for c in mapper.class_names:
            bw.add_topic(OUT_PREFIX + c, T.GRID_TYPE)
        bw.add_topic(IMAGE_TOPIC, T.IMAGE_TYPE)
        copier = _InfoCopier(Path(options.bag), reader, bw)
        custom = dict(reader.custom_data)
        custom["bev_mapper.replay"] = json.dumps(
            {"method": options.mapper.method, "input": kind, "label_map": options.mapper.label_map,
             "classes": list(mapper.class_names)})
        for k, v in custom.items():
            bw.set_custom_data(k, v)
        # with a pipeline, the next frames are read and decoded by a thread while this one maps
        frames = reader.frames(rgb=kind == "rgb", labels=kind == "labels",
                               label_map=label_map(options.mapper.label_map))
        if options.pipeline:
            frames = Prefetch(frames, options.pipeline)
        fusion = TemporalFusion(grid, options.temporal) if options.temporal.window > 1 else None
        temporal = {"window": options.temporal.window, "fused_frames": 0, "resets": 0, "frames_without_pose": 0}

        def finish_frame(frame, pred, index: int) -> None:
            """Copy the calibration up to the frame, write its grids, score it, draw it."""
            copier.upto(_frame_time(frame))
            _write_frame(bw, grid, mapper, pred, frame.stamp_ns, ego)
            gt, mask = scorer.update(frame, pred)
            score = None if gt is None else scores.add(
                frame.index, frame.stamp_ns, pred.probs, pred.known, mapper.class_names, gt,
                [c.name for c in scorer.classes], mask, frame.ground_visibility,
                scorer.scope_used, scorer.acc.threshold)
            if options.pictures and index % options.frames_every == 0:
                pic = comparison_picture(
                    grid, pred.probs, pred.known, mapper.classes, gt, mask, scorer.classes,
                    method=options.mapper.method, caption=_caption(frame, score),
                    ious=None if score is None else score.ious)
                name = f"frame_{frame.index:04d}.png"
                write_atomic(tmp_frames / name, encode_png(pic))
                pictures.append(frames_dir / name)
                if options.gif:
                    gif_frames.append(pic)

        finish = InOrder(options.pipeline) if options.pipeline else None
        finished = False
        try:
            for frame in frames:
                images = frame.labels if kind == "labels" else frame.rgb
                if not images:
                    skipped += 1
                    continue
                pose = frame.odom.world_from_ego if frame.odom is not None else None
                t0 = time.perf_counter()
                try:
                    pred = mapper.map(images, ego_pose=pose, stamp_ns=frame.stamp_ns)
                    if fusion is not None:
                        fused = fusion.update(pred, frame.stamp_ns, pose)
                        pred = fused.prediction
                        temporal["fused_frames"] += fused.frames
                        if fused.note:
                            key = "frames_without_pose" if pose is None else "resets"
                            temporal[key] += 1
                except BevMapperError as exc:  # this frame's input: keep the outputs so far
                    damage = f"frame {frame.index} could not be mapped: {exc}"
                    break
                latencies.append((time.perf_counter() - t0) * 1000.0)
                if finish is None:
                    finish_frame(frame, pred, mapped)
                else:  # scored and written by the in-order thread while the next frame maps
                    finish.submit(finish_frame, frame, pred, mapped)
                mapped += 1
                bar.update(1)
                if options.max_frames is not None and mapped >= options.max_frames:
                    break  # before reading further (and maybe meeting damage we don't need)
            finished = True
        except BagCorruptError as exc:
            damage = str(exc)
            finished = True
        finally:
            frames.close()
            if finish is not None:
                finish.close(abandon=not finished)  # the frames mapped so far are scored and written
            bar.close()
            copier.close()
        bag_counts = dict(bw.counts)
    damage = _damage_note(damage, reader)
    # the output bag is in place; now the pictures, the GIF and last the metrics
    if frames_dir.exists():  # stale pictures of an earlier replay (only with --force)
        shutil.rmtree(frames_dir)
    if options.pictures:
        tmp_frames.rename(frames_dir)
    gif_path, gif_note = None, ""
    if options.gif:
        data, gif_note = encode_gif(gif_frames)
        if data is not None:
            gif_path = write_atomic(out / GIF_FILE, data)
        notes.append(gif_note)
    if gif_path is None and (out / GIF_FILE).exists():
        (out / GIF_FILE).unlink()
    metrics = _metrics(options, scorer, grid, mapped, skipped, latencies, damage, bag_counts)
    metrics.update(reader.issues.to_metrics())
    metrics["temporal"] = temporal
    result = ReplayResult(metrics, out, out / BAG_DIR, pictures, gif_path, gif_note, damage, notes,
                          latencies, scores, scoring=scorer.state())
    if metrics["frames_scored"]:
        result.reliability = write_atomic(out / RELIABILITY_FILE, encode_png(
            reliability_picture(metrics["calibration"], title=options.mapper.method)))
    elif (out / RELIABILITY_FILE).exists():  # stale, of an earlier replay (only with --force)
        (out / RELIABILITY_FILE).unlink()
    if options.report:
        result.report = write_atomic(out / REPORT_FILE, render_report(result).encode())
    elif (out / REPORT_FILE).exists():  # stale, of an earlier replay (only with --force)
        (out / REPORT_FILE).unlink()
    write_atomic(out / METRICS_FILE, (json.dumps(metrics, indent=2, allow_nan=False) + "\n").encode())
    return result


def _caption(frame, score) -> str:
    """Picture footer: frame index, stamp and the frame's mIoU over the classes defined in it."""
    text = f"frame {frame.index}  stamp {frame.stamp_ns / 1e9:.3f} s"
    if score is None:
        return text + "  (no GT: not scored)"
    defined = [v for v in score.ious.values() if v is not None]
    miou = "-" if score.miou is None else f"{100 * score.miou:.1f}%"
    return text + f"  mIoU {miou} over {len(defined)} class(es)"


def _damage_note(damage: str | None, reader: BagReader) -> str | None:
    """Everything that makes a replay incomplete, in one sentence (``None``: nothing did):
    the damage the reading met, messages the reader skipped.
    """
    parts = [damage] if damage else []
    issues = reader.issues.summary()
    if issues:
        parts.append(f"{reader.path}: {issues}")
    return "; ".join(parts) or None


def _write_frame(bw: BagWriter, grid: BevGrid, mapper, pred: BevPrediction, stamp: int,
                 ego: str) -> None:
    """``/bev/<class>`` grids and the ``/bev/image`` picture of one frame."""
    for ci, c in enumerate(mapper.class_names):
        bw.write(OUT_PREFIX + c, make_occupancy_grid(bw.factory, grid, pred.probs[ci], pred.known,
                                                     stamp, ego), stamp)
    picture = bev_picture(grid, pred.probs, mapper.classes, pred.known)
    bw.write(IMAGE_TOPIC, make_image(bw.factory, picture, "rgb8", stamp, ego),
             stamp)


def _metrics(options, scorer: "ReplayScorer", grid, mapped, skipped, latencies, damage,
             bag_counts) -> dict:
    """The ``metrics.json`` document."""
    res = scorer.result()
    return {
        "method": options.mapper.method,
        "input": options.mapper.input_kind,
        "label_map": options.mapper.label_map,
        "bag": str(options.bag),
        "frames": mapped,
        "frames_scored": res["frames"],
        "frames_skipped": skipped,
        "scope": options.scope,
        "scope_used": scorer.scope_used,
        "classes": res["classes"],
        "miou": res["miou"],
        "map": res["map"],
        "iou_by_range": res["iou_by_range"],
        "unscored_classes": scorer.unscored,
        "miou_classes": list(scorer.class_map),
        "class_map": scorer.mapped,
        "latency_ms": _percentiles(latencies),
        "grid": grid.to_dict(),
        "output_bag": {"path": BAG_DIR, "storage": options.storage, "messages": bag_counts},
        "complete": damage is None,
        "damage": damage,
        "occlusion": res["occlusion"],
        "calibration": res["calibration"],
    }


class ReplayScorer:
    """Scores a frame's prediction against its GT with the one
    :class:`~bev_mapper_core.metrics.MetricAccumulator`, in the chosen scope.

    The per-class masks come from :func:`~bev_mapper_core.metrics.scope_masks`: ``visible``
    scores the cells whose GT is known (not -1); ``ground`` (with a ground visibility layer)
    scores flat classes only where the ground is seen too, object classes keep the visible
    scope, since an object hides its own ground. Classes the bag has no GT for are not scored.

    Beside it a :class:`~bev_mapper_core.metrics.WholeGridAccumulator` scores the probabilities
    as published (rounded to whole percent, as in the OccupancyGrids) over the whole grid: the
    hidden cells are those ``/bev/visibility/any`` marks unseen (bags without it: the cells
    whose GT is -1), the false claims are counted against ``/bev/truth/<class>`` when the bag
    has it, and the ECE is taken in the same scope masks as the IoU.
    """

    def __init__(self, grid: BevGrid, pred_names, gt_names, ground: bool) -> None:
        #: predicted class -> the GT layers that mean the same (see ``class_cover``)
        self.class_map = {}
        for c in pred_names:
            cover = class_cover(c, tuple(gt_names)) if gt_names else None
            if cover is not None:
                self.class_map[c] = cover
        names = tuple(self.class_map)
        self.classes = resolve_classes(names) if names else ()
        self.unscored = [c for c in pred_names if c not in self.class_map]
        self.scope_used = None if not names else ("ground" if ground else "visible")
        self.acc = MetricAccumulator(grid, names) if names else None
        self.whole = WholeGridAccumulator(grid, names, self.acc.threshold) if names else None
        self._names = names
        self._pred_idx = [list(pred_names).index(c) for c in names]
        self._gt_idx = [[list(gt_names).index(g) for g in self.class_map[c]] for c in names]

    @property
    def mapped(self) -> dict[str, list[str]]:
        """Predicted classes scored against GT layers of other names: ``{class: [gt layers]}``."""
        return {c: list(g) for c, g in self.class_map.items() if g != (c,)}

    def update(self, frame, pred: BevPrediction):
        """Score one frame; returns ``(gt (C', H, W) bool, visible (H, W))`` or ``(None, None)``."""
        if self.acc is None or frame.gt is None:
            return None, None
        # a class covered by several GT layers is their union, known where all of them are
        gt = np.stack([(frame.gt[idx] >= 0.5).any(axis=0) for idx in self._gt_idx])  # (C', H, W)
        visible = np.stack([frame.gt_known[idx].all(axis=0) for idx in self._gt_idx]).all(axis=0)  # (H, W)
        masks = scope_masks(self._names, visible, frame.ground_visibility, self.scope_used)
        probs = pred.probs[self._pred_idx]
        self.acc.update(probs, gt, masks, pred.known)
        truth = None
        if frame.truth is not None:
            truth = np.stack([(frame.truth[idx] >= 0.5).any(axis=0) for idx in self._gt_idx])
        seen = frame.visibility if frame.visibility is not None else visible
        published = np.rint(np.clip(probs, 0.0, 1.0) * 100.0) / 100.0  # as in the OccupancyGrids
        self.whole.update(published, pred.known, seen, gt, truth, masks)
        return gt, visible

    def state(self) -> dict | None:
        """The mergeable state ``{"metrics": MetricAccumulator state, "whole":
        WholeGridAccumulator state}`` (see :mod:`bev_mapper_core.metrics`), ``None`` when no
        class is scored.
        """
        if self.acc is None:
            return None
        return {"metrics": self.acc.state(), "whole": self.whole.state()}

    @staticmethod
    def result_of(state: dict) -> dict:
        """:meth:`result` of a (merged) :meth:`state`."""
        return _scorer_result(MetricAccumulator.from_state(state["metrics"]),
                              WholeGridAccumulator.from_state(state["whole"]))

    def result(self) -> dict:
        """:meth:`MetricAccumulator.result` over the scored classes, in mapper order, plus the
        ``occlusion`` and ``calibration`` parts of :meth:`WholeGridAccumulator.result` (``None``
        when nothing is scored).
        """
        if self.acc is None:
            return {"frames": 0, "classes": {}, "miou": None, "map": None, "iou_by_range": {},
                    "occlusion": None, "calibration": None}
        return _scorer_result(self.acc, self.whole)


def _scorer_result(acc: MetricAccumulator, whole: WholeGridAccumulator) -> dict:
    """The scores of :meth:`ReplayScorer.result` from its two accumulators."""
    w = whole.result()
    w["occlusion"]["frames_with_truth"] = w["frames_with_truth"]
    return {**acc.result(), "occlusion": w["occlusion"], "calibration": w["calibration"]}
