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

The stages live beside this module: :mod:`~bags.replay.options` (options, result, output names,
the run's state), :mod:`~bags.replay.mapping` (reading and mapping the frames),
:mod:`~bags.replay.scoring` (the scorer), :mod:`~bags.replay.outputs` (writing each frame, then
the rest; the frame's messages in :mod:`~bags.replay.frame_messages`) and
:mod:`~bags.replay.pipeline` (the threads between them).

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

import shutil
from collections.abc import Callable
from pathlib import Path

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.ego_mask import load_ego_mask, mask_notes, with_ego_masks
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import PRESETS
from bev_mapper_core.labels.classes import known_class_names
from bev_mapper_core.mapper import create_mapper

from ..errors import BagContentError
from ..files import partial_name
from ..io import topics as T
from ..io.reader import BagReader
from ..io.rig_source import RIG_FLAGS_HINT
from ..io.writer import BagWriter
from .mapping import map_frames
from .options import BAG_DIR, FRAMES_DIR, ReplayOptions, ReplayResult, ReplayRun, check_outputs
from .outputs import FrameSink, write_outputs
from .score_process import Pictures, ScoringError, ScoringProcess, start_child, stop_child, use_process
from .scoring import scorer_for
from .spare_cpu import CpuWatch


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
    watch = CpuWatch()  # the other jobs' load while the bag opens: does a scoring process pay?
    out = Path(options.out)
    check_outputs(out, options.force)
    hints = options.rig.hints()
    # ego-body masks: read (and checked) before the bag; a bad one is refused, never ignored
    mask_paths = {**(hints.ego_masks if hints is not None else {}), **dict(options.ego_masks)}
    masks = {cam: load_ego_mask(path) for cam, path in mask_paths.items()}
    with BagReader(options.bag, hints=hints) as reader:
        rig = with_ego_masks(reader.rig(), masks)
        # a scoring process this replay will want starts now: its start overlaps the mapper's
        spare = watch.spare_cores()
        wanted = use_process(options.score_process, _expected_frames(options, reader, rig), spare)
        child, failed = None, None
        if wanted:
            try:
                child = start_child()
            except OSError as exc:  # no interpreter to run (an embedded Python): scored here, said
                failed = exc
        try:
            return _replay(options, progress, reader, rig, out, child, spare, failed)
        finally:
            stop_child(child)  # unless taken over (then already stopped): e.g. the mapper failed


def _replay(options: ReplayOptions, progress: Callable | None, reader: BagReader, rig, out: Path,
            child, spare: float | None, failed: OSError | None = None) -> ReplayResult:
    """:func:`replay` with the bag open (``child``: the scoring process started for it, or
    ``None``; ``spare``: the cores the other jobs left free while the bag opened; ``failed``:
    why a scoring process asked for did not start).
    """
    hints = options.rig.hints()
    grid = reader.grid()
    notes: list[str] = mask_notes(rig)
    if failed is not None:
        notes.append(f"scored in the replay's own process: the scoring process did not start ({failed})")
    if reader.unknown_gt_classes:
        notes.append(f"GT layers of unknown classes skipped (not scored): "
                     f"{', '.join(T.gt_topic(c) for c in reader.unknown_gt_classes)} (known classes: "
                     f"{', '.join(known_class_names())})")
    if grid is None:
        grid = options.grid or (hints and hints.grid) or BevGrid()
        notes.append(f"the bag has no GT layers: mapping onto {grid.describe()}, no metrics")
    elif options.grid is not None and not options.grid.isclose(grid):
        raise BagContentError(
            f"the bag's GT grid is {grid.describe()}; grid flags only apply to bags without GT")
    try:
        mapper = create_mapper(rig, grid, options.mapper)
    except BevMapperError as exc:
        if "rig" not in str(exc) or hints is not None or rig.name in PRESETS:  # a preset is no guess
            raise
        raise type(exc)(f"{exc} (the bag's rig was taken as {rig.name!r}: {RIG_FLAGS_HINT})") from None
    notes += list(mapper.notes)  # e.g. the weights for any rig chosen for a rig its own do not fit
    out.mkdir(parents=True, exist_ok=True)
    run = ReplayRun(options, reader, rig, grid, mapper, out, partial_name(out / FRAMES_DIR), notes, spare)
    shutil.rmtree(run.tmp_frames, ignore_errors=True)
    try:
        result = _run(run, progress, child)
    finally:
        shutil.rmtree(run.tmp_frames, ignore_errors=True)
    return result


def _run(run: ReplayRun, progress: Callable | None, child) -> ReplayResult:
    """Map, score and write every frame into the output bag, then the other outputs."""
    options = run.options
    scorer = scorer_for(run)
    total = _expected_frames(options, run.reader, run.rig)
    bar = progress(total) if progress is not None else _tqdm_bar(run, total)
    if options.pictures:
        run.tmp_frames.mkdir()
    with BagWriter(run.out / BAG_DIR, storage=options.storage, force=options.force) as bw:
        remote = _scoring_process(run, scorer, child)
        try:
            sink = FrameSink(run, bw, scorer, remote)
        except BaseException:
            if remote is not None:
                remote.close(abandon=True)
            raise
        done = False
        try:
            tally = map_frames(run, sink.finish, bar)
            done = True
        finally:
            bar.close()
            sink.close(abandon=not done)
    tally.damage = _damage_note(tally.damage, run.reader)
    # the output bag is in place; now the pictures, the GIF and last the metrics
    return write_outputs(run, sink, tally)


def _scoring_process(run: ReplayRun, scorer, child) -> ScoringProcess | None:
    """The scoring process ``options.score_process`` asked for (``child``: its interpreter,
    started by :func:`replay`; ``None``: score here). One that does not start (no shared memory,
    no interpreter to run) leaves the scoring here, with a note: the outputs are the same either way.
    """
    options = run.options
    if scorer.acc is None or child is None:
        return None
    try:
        pictures = Pictures(options.mapper.method, tuple(run.mapper.classes), str(run.tmp_frames))
        return ScoringProcess(scorer, len(run.mapper.class_names), run.grid.shape, pictures=pictures,
                              published=tuple(run.mapper.classes), child=child)
    except (OSError, ScoringError) as exc:
        run.notes.append(f"scored in the replay's own process: the scoring process did not start ({exc})")
        return None


def _expected_frames(options: ReplayOptions, reader: BagReader, rig) -> int | None:
    """The frames the replay expects to map (``None``: unknown): the first camera's images,
    at most ``max_frames``.
    """
    image_topic = reader.image_topic(rig.names[0], options.mapper.input_kind)
    total = reader.topics[image_topic].count if image_topic in reader.topics else None
    if options.max_frames is not None:
        total = min(total or options.max_frames, options.max_frames)
    return total


def _tqdm_bar(run: ReplayRun, total: int | None):
    """A tqdm bar of ``total`` frames (hidden unless ``options.progress``)."""
    from tqdm import tqdm  # noqa: PLC0415 - only the replay needs it

    return tqdm(total=total, unit="frame", disable=not run.options.progress, leave=False, dynamic_ncols=True)


def _damage_note(damage: str | None, reader: BagReader) -> str | None:
    """Everything that makes a replay incomplete, in one sentence (``None``: nothing did):
    the damage the reading met, messages the reader skipped.
    """
    parts = [damage] if damage else []
    issues = reader.issues.summary()
    if issues:
        parts.append(f"{reader.path}: {issues}")
    return "; ".join(parts) or None
