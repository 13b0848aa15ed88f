"""A replay's outputs: :class:`FrameSink` writes each mapped frame (its grids and picture into
the output bag, the input calibration copied up to it, its score, its PNG picture), and
:func:`write_outputs` completes the rest once the output bag is in place (the pictures' folder,
the GIF, the reliability diagram, ``report.html`` and, last, ``metrics.json``).
"""

from __future__ import annotations

import json
import logging
import shutil
from collections import deque
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from bev_mapper_core.mapper import BevPrediction

from ..errors import BagCorruptError
from ..files import write_atomic
from ..io import topics as T
from ..io.reader import BagReader
from ..io.writer import BagWriter
from ..report.html import render_report
from ..report.pictures import encode_gif, encode_png, save_comparison
from ..report.reliability import reliability_picture
from .frame_messages import prediction_cells, write_frame_messages
from .frame_scores import FrameScores, caption
from .mapping import MappingTally
from .options import (
    BAG_DIR,
    FRAMES_DIR,
    GIF_FILE,
    IMAGE_TOPIC,
    METRICS_FILE,
    OUT_PREFIX,
    RELIABILITY_FILE,
    REPORT_FILE,
    ReplayResult,
    ReplayRun,
)
from .pipeline import InOrder
from .score_process import ScoringProcess
from .scoring import ReplayScorer, percentiles


class InfoCopier:
    """Copies CameraInfo and ``/tf_static`` of the input bag into the output bag, in time order.

    A second reader on the same bag streams those topics lazily, as CDR bytes; :meth:`upto` writes
    what was logged up to a time. Damage on this stream just ends the copy (the frame stream
    reports it). What is written is what deserializing and serializing each message gives (the
    copy is rosbags' rendering of the message); a CameraInfo that equals one already found to
    come back unchanged, but for its header stamp, is written as it is, since the stamp's two
    32-bit integers always come back unchanged.
    """

    def __init__(self, bag: Path, reader: BagReader, writer: BagWriter) -> None:
        self.topics = [t for t in map(reader.camera_info_topic, reader.camera_names) if t in reader.topics]
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
        self._it: Iterator | None = self._reader.messages(self.topics, raw=True)
        self._next = None
        self._same: dict[str, bytes] = {}  # per topic: bytes but the stamp of a message that came back unchanged

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
            data = self._copy(m)
            if data is None:  # does not deserialize: damage, as the stream would have said
                self._it = None
                return
            self._writer.write_raw(m.topic, data, m.log_ns)

    def _copy(self, m) -> bytes | None:
        """The bytes of ``m`` (raw) as written: deserialized and serialized again (see class
        docstring); ``None`` when it does not deserialize.
        """
        raw = m.msg
        rest = raw[:4] + raw[12:]  # all but the header stamp (a CameraInfo's first 8 bytes)
        if self._same.get(m.topic) == rest:
            return raw
        try:
            data = self._writer.serialize(m.topic, self._reader.deserialize(raw, m.msgtype))
        except Exception:  # noqa: BLE001 - rosbags' SerdeError and what its generated code raises
            return None
        if data == raw and m.msgtype == T.CAMERA_INFO_TYPE:
            self._same[m.topic] = rest
        return data

    def close(self) -> None:
        """Release the second reader."""
        self._it = None
        self._reader.close()


class FrameSink:
    """The outputs of each mapped frame, in frame order: :meth:`finish` scores it, then writes its
    messages into the output bag and its picture (with a pipeline, the writing in a thread of its
    own, :class:`~bags.replay.pipeline.InOrder`, while the next frame is scored).

    Opening it declares the output bag's topics (``/bev/<class>``, ``/bev/image``, the copied
    calibration) and its ``custom_data`` (the input's, plus ``bev_mapper.replay``: method, input,
    label map, classes). It keeps the scores, picture paths and GIF frames for the result.
    """

    def __init__(self, run: ReplayRun, bw: BagWriter, scorer: ReplayScorer,
                 remote: ScoringProcess | None = None) -> None:
        self.run, self.bw, self.scorer = run, bw, scorer
        #: the scoring process (None: the frames are scored here); the frames it scores, oldest first
        self._remote, self._waiting = remote, deque()
        #: whether the frames were scored in a process of their own (``metrics.json`` ``score_process``)
        self.scored_apart = remote is not None
        options, mapper = run.options, run.mapper
        for c in mapper.class_names:
            bw.add_topic(OUT_PREFIX + c, T.GRID_TYPE)
        bw.add_topic(IMAGE_TOPIC, T.IMAGE_TYPE)
        self.copier = InfoCopier(Path(options.bag), run.reader, bw)
        custom = dict(run.reader.custom_data)
        custom["bev_mapper.replay"] = json.dumps(
            {"method": options.mapper.method, "input": run.input_kind, "label_map": options.mapper.label_map,
             "classes": list(mapper.class_names)})
        for k, v in custom.items():
            bw.set_custom_data(k, v)
        self.ego = run.reader.ego_frame
        self.scores = FrameScores()
        self.pictures: list[Path] = []
        self.gif_frames: list[np.ndarray] = []
        self.bag_counts: dict[str, int] = {}
        self._writing = InOrder(options.pipeline) if options.pipeline else None

    def finish(self, frame, pred: BevPrediction, index: int) -> None:
        """Score the frame, then copy the calibration up to it, write its grids and draw it (with
        a scoring process: once its score is back, the frames before it first).
        """
        scorer = self.scorer
        if self._remote is None:
            # (C, H*W) int8 OccupancyGrid cells, shared by the grids and the scores
            cells = prediction_cells(pred)
            gt, mask = scorer.update(frame, pred, cells)
            self._scored(frame, pred, index, cells, gt, mask, None if gt is None else scorer.frame_iou)
            return
        layers, picture, cells = scorer.frame_layers(frame), None, None
        if layers is None:  # not scored: the cells are computed here (the scoring process's otherwise)
            cells = prediction_cells(pred)
        else:
            self._release()  # waits for the oldest frame's score while every slot is in use
            # the scoring process draws the picture of a frame it scores (not for a GIF: its
            # pictures are kept here)
            options = self.run.options
            if options.pictures and not options.gif and index % options.frames_every == 0:
                picture = (self._picture_name(frame), frame.index, frame.stamp_ns)
            self._remote.submit(layers, pred, None, picture)
        self._waiting.append((frame, pred, index, cells, layers, picture is not None))
        self._release()

    def _release(self, every: bool = False) -> None:
        """Hand the waiting frames on to be written, oldest first: a frame without GT at once, a
        scored one with its score, waiting for it while the scoring process is full (``every``:
        all of them).
        """
        while self._waiting:
            frame, pred, index, cells, layers, drawn = self._waiting[0]
            iou, image = None, None
            if layers is not None:
                if not (every or self._remote.full):
                    return
                iou, cells, image = self._remote.take()  # its cells and /bev/image from the process
            self._waiting.popleft()
            gt, mask = (None, None) if layers is None else (layers.gt, layers.visible)
            self._scored(frame, pred, index, cells, gt, mask, iou, drawn, image)

    def _scored(self, frame, pred: BevPrediction, index: int, cells, gt, mask, iou, drawn: bool = False,
                image=None) -> None:
        """Keep a scored frame's IoU (``iou``, as the scorer counted it: FrameScores.add would
        score it again alike) and have the frame written (``drawn``: its picture, if it has one,
        was drawn by the scoring process; ``image``: its ``/bev/image`` picture, if drawn there).
        """
        score = None if gt is None else self.scores.add_ious(
            frame.index, frame.stamp_ns, [c.name for c in self.scorer.classes], iou)
        if self._writing is None:
            self._write(frame, pred, index, cells, gt, mask, score, drawn, image)
        else:
            self._writing.submit(self._write, frame, pred, index, cells, gt, mask, score, drawn, image)

    def _write(self, frame, pred: BevPrediction, index: int, cells, gt, mask, score, drawn: bool,
               image=None) -> None:
        """The frame's messages in the output bag (after the calibration logged up to it) and
        its picture (unless ``drawn`` by the scoring process).
        """
        run, mapper = self.run, self.run.mapper
        self.copier.upto(_frame_time(frame))
        write_frame_messages(self.bw, run.grid, mapper, pred, frame.stamp_ns, self.ego, cells, image)
        options = run.options
        if options.pictures and index % options.frames_every == 0:
            name = self._picture_name(frame)
            if not drawn:
                pic = save_comparison(
                    run.tmp_frames / name, run.grid, pred.probs, pred.known, mapper.classes, gt, mask,
                    self.scorer.classes, method=options.mapper.method,
                    caption=caption(frame.index, frame.stamp_ns, score), ious=None if score is None else score.ious)
                if options.gif:
                    self.gif_frames.append(pic)
            self.pictures.append(run.out / FRAMES_DIR / name)

    @staticmethod
    def _picture_name(frame) -> str:
        return f"frame_{frame.index:04d}.png"

    def close(self, abandon: bool = False) -> None:
        """Wait for the frames being scored and written (``abandon``: only the one under way; a
        failure while scoring or writing is raised unless abandoning), stop the scoring process,
        release the calibration copier, keep the output bag's message counts.
        """
        try:
            if self._remote is not None:
                self._finish_scoring(abandon)
        finally:
            try:
                if self._writing is not None:
                    self._writing.close(abandon=abandon)
            finally:
                self.copier.close()
                self.bag_counts = dict(self.bw.counts)

    def _finish_scoring(self, abandon: bool) -> None:
        """Take the scoring process's last scores and its scorer's state (``abandon``: only stop it)."""
        remote = self._remote
        try:
            if abandon:
                remote.close(abandon=True)
                return
            try:
                self._release(every=True)
                state = remote.close()
            except BaseException:
                remote.close(abandon=True)
                raise
            self.scorer.load_state(state)
        finally:
            self._remote = None


def _frame_time(frame) -> int:
    stamps = [s for s in frame.camera_stamps.values() if s is not None]
    return max(stamps + [frame.stamp_ns])


def write_outputs(run: ReplayRun, sink: FrameSink, tally: MappingTally) -> ReplayResult:
    """With the output bag in place: the pictures' folder, the GIF, the metrics, the reliability
    diagram, the report and last ``metrics.json``; stale ones of an earlier replay (``--force``)
    that this one does not write are removed.
    """
    options, out = run.options, run.out
    frames_dir = out / FRAMES_DIR
    if frames_dir.exists():  # stale pictures of an earlier replay (only with --force)
        shutil.rmtree(frames_dir)
    if options.pictures:
        run.tmp_frames.rename(frames_dir)
    gif_path, gif_note = None, ""
    if options.gif:
        data, gif_note = encode_gif(sink.gif_frames)
        if data is not None:
            gif_path = write_atomic(out / GIF_FILE, data)
        run.notes.append(gif_note)
    if gif_path is None:
        _remove_stale(out / GIF_FILE)
    metrics = metrics_document(run, sink.scorer, tally, sink.bag_counts, sink.scored_apart)
    sync_note = run.reader.sync_report.summary()
    if sync_note:
        run.notes.append(sync_note)
    result = ReplayResult(metrics, out, out / BAG_DIR, sink.pictures, gif_path, gif_note, tally.damage, run.notes,
                          tally.latencies, sink.scores, scoring=sink.scorer.state())
    if metrics["frames_scored"]:
        result.reliability = write_atomic(out / RELIABILITY_FILE, encode_png(
            reliability_picture(metrics["calibration"], title=options.mapper.method)))
    else:
        _remove_stale(out / RELIABILITY_FILE)
    if options.report:
        result.report = write_atomic(out / REPORT_FILE, render_report(result).encode())
    else:
        _remove_stale(out / REPORT_FILE)
    write_atomic(out / METRICS_FILE, (json.dumps(metrics, indent=2, allow_nan=False) + "\n").encode())
    return result


def _remove_stale(path: Path) -> None:
    """Remove an output of an earlier replay that this one does not write (only with --force)."""
    if path.exists():
        path.unlink()


def _weights_name(mapper) -> str | None:
    """The file name of the weights a learned mapper runs (e.g. the shipped weights for any rig),
    None for a training-free one.
    """
    for name in ("weights_file", "weights_path"):  # the monocular methods' weights_path is a classmethod
        path = getattr(mapper, name, None)
        if isinstance(path, (str, Path)):
            return Path(path).name
    return None


def metrics_document(run: ReplayRun, scorer: ReplayScorer, tally: MappingTally, bag_counts: dict,
                     scored_apart: bool = False) -> dict:
    """The ``metrics.json`` document: the scores, what was mapped, the reader's input problems,
    the temporal fusion's counts and where the frames were scored (``scored_apart``: in a process
    of their own).
    """
    options, res = run.options, scorer.result()
    doc = {
        "method": options.mapper.method,
        "weights": _weights_name(run.mapper),
        "input": options.mapper.input_kind,
        "label_map": options.mapper.label_map,
        "bag": str(options.bag),
        "frames": tally.mapped,
        "frames_scored": res["frames"],
        "frames_skipped": tally.skipped,
        "scope": options.scope,
        "scope_used": scorer.scope_used,
        "classes": res["classes"],
        "miou": res["miou"],
        "map": res["map"],
        "iou_by_range": res["iou_by_range"],
        "unscored_classes": scorer.unscored,
        "miou_classes": list(scorer.class_map),
        "class_map": scorer.mapped,
        "latency_ms": percentiles(tally.latencies),
        "grid": run.grid.to_dict(),
        "output_bag": {"path": BAG_DIR, "storage": options.storage, "messages": bag_counts},
        "complete": tally.damage is None,
        "damage": tally.damage,
        "occlusion": res["occlusion"],
        "calibration": res["calibration"],
    }
    doc.update(run.reader.issues.to_metrics())
    doc["skipped_gt_layers"] = [T.gt_topic(c) for c in run.reader.unknown_gt_classes]  # unknown classes
    doc["sync"] = run.reader.sync_report.to_metrics()
    doc["rig"] = {"name": run.rig.name, "cameras": list(run.rig.names)}
    doc["temporal"] = tally.temporal
    doc["placement"] = tally.placement
    spare = run.spare_cores
    doc["score_process"] = {"setting": options.score_process, "ran": "process" if scored_apart else "replay",
                            "spare_cores": None if spare is None else round(spare, 2)}
    return doc
