"""The replay as it was before issue #28, for ``bench_replay_rate.py``'s references.

:func:`reference_scoring`: the scoring before #28: one distance transform of the whole grid per
class and side for the Chamfer distances, the calibration counts summed cell by cell, and each
frame's IoU for the captions scored a second time by ``FrameScores.add``.

:func:`reference_io`: the reading and writing before #28's second part: every message read by
``rosbags`` (whole chunks, CRC-checked, deserialized into rosbags messages), every GT layer through
``occupancy_grid_to_layer``, every grid and CameraInfo of the output bag serialized by rosbags.

The outputs are the same (``tests/bags/replay/test_replay_scoring_unchanged.py``,
``tests/bags/replay/test_replay_io_unchanged.py``); each swaps its path in for a block.
"""

from __future__ import annotations

import contextlib

import cv2
import numpy as np

import bags.io.reader.bag_reader as bag_reader
import bags.io.reader.layers as layers
import bags.io.sources as sources
import bags.replay.outputs as outputs
import bev_mapper_core.metrics.accumulator as accumulator
import bev_mapper_core.metrics.whole_grid as whole_grid
from bags.replay import FRAMES_DIR, IMAGE_TOPIC
from bags.replay.frame_scores import caption
from bags.replay.options import OUT_PREFIX
from bags.report.pictures import comparison_picture
from bev_mapper_core.labels.classes import bev_picture
from bev_mapper_core.metrics._packed import unpack
from msg_adapters import make_image, make_occupancy_grid


def reference_chamfer_terms(pred, gt, resolution, clip):
    """The Chamfer terms as computed before #28: a whole-grid transform per side."""
    def distance_to(cells, at):
        d = cv2.distanceTransform(np.where(cells, 0, 1).astype(np.uint8), cv2.DIST_L2,
                                  cv2.DIST_MASK_PRECISE)[at]
        return np.sqrt(np.rint(d.astype(np.float64) ** 2))

    n_p, n_g = int(np.count_nonzero(pred)), int(np.count_nonzero(gt))
    d_p = np.full(n_p, clip) if n_g == 0 else np.minimum(distance_to(gt, pred) * resolution, clip)
    d_g = np.full(n_g, clip) if n_p == 0 else np.minimum(distance_to(pred, gt) * resolution, clip)
    return d_p, d_g


def reference_packed_chamfer_terms(pred, gt, c, shape, resolution, clip):
    """:func:`reference_chamfer_terms` of class ``c`` of the accumulator's packed layers."""
    return reference_chamfer_terms(unpack(pred, c).reshape(shape), unpack(gt, c).reshape(shape), resolution, clip)


def reference_finish(self, frame, pred, index):
    """``FrameSink.finish`` as before #28: ``FrameScores.add`` scores the frame a second time."""
    run, mapper, scorer = self.run, self.run.mapper, self.scorer
    self.copier.upto(outputs._frame_time(frame))
    outputs.write_frame_messages(self.bw, run.grid, mapper, pred, frame.stamp_ns, self.ego)
    gt, mask = scorer.update(frame, pred)
    score = None if gt is None else self.scores.add(
        frame.index, frame.stamp_ns, pred.probs, pred.known, mapper.class_names, gt,
        [c.name for c in scorer.classes], mask, frame.ground_visibility, scorer.scope_used,
        scorer.acc.threshold)
    options = run.options
    if options.pictures and index % options.frames_every == 0:
        pic = comparison_picture(
            run.grid, pred.probs, pred.known, mapper.classes, gt, mask, scorer.classes,
            method=options.mapper.method, caption=caption(frame.index, frame.stamp_ns, score),
            ious=None if score is None else score.ious)
        name = f"frame_{frame.index:04d}.png"
        outputs.write_atomic(run.tmp_frames / name, outputs.encode_png(pic))
        self.pictures.append(run.out / FRAMES_DIR / name)
        if options.gif:
            self.gif_frames.append(pic)


@contextlib.contextmanager
def reference_scoring():
    """Within the block, replays score as before #28."""
    saved = (accumulator._packed_chamfer_terms, whole_grid._EXACT_PERCENT_CELLS, outputs.FrameSink.finish)
    accumulator._packed_chamfer_terms = reference_packed_chamfer_terms
    whole_grid._EXACT_PERCENT_CELLS = 0  # the per-cell calibration sums
    outputs.FrameSink.finish = reference_finish
    try:
        yield
    finally:
        accumulator._packed_chamfer_terms, whole_grid._EXACT_PERCENT_CELLS, outputs.FrameSink.finish = saved


def reference_write_frame_messages(bw, grid, mapper, pred, stamp, ego, cells=None, picture=None):
    """``/bev/<class>`` grids and the ``/bev/image`` picture, each message built and serialized
    by rosbags (as before #28's second part)."""
    del cells, picture
    for ci, c in enumerate(mapper.class_names):
        bw.write(OUT_PREFIX + c, make_occupancy_grid(bw.factory, grid, pred.probs[ci], pred.known, stamp, ego),
                 stamp)
    picture = bev_picture(grid, pred.probs, mapper.classes, pred.known)
    bw.write(IMAGE_TOPIC, make_image(bw.factory, picture, "rgb8", stamp, ego), stamp)


def _reference_copy(self, m):
    """Every copied message deserialized and serialized again by rosbags."""
    try:
        return self._writer.serialize(m.topic, self._reader.deserialize(m.msg, m.msgtype))
    except Exception:  # noqa: BLE001 - as InfoCopier._copy
        return None


@contextlib.contextmanager
def reference_io():
    """Within the block, replays read and write as before #28's second part (see module docstring)."""
    saved = (sources.IndexedMcap.__dict__["open"], bag_reader.fast_deserializer, layers.LayerDecoder.cells,
             outputs.write_frame_messages, outputs.InfoCopier._copy)
    sources.IndexedMcap.open = classmethod(lambda cls, path, verified: None)  # rosbags reads every file
    bag_reader.fast_deserializer = lambda deserialize: deserialize
    layers.LayerDecoder.cells = lambda self, msg: None
    outputs.write_frame_messages = reference_write_frame_messages
    outputs.InfoCopier._copy = _reference_copy
    try:
        yield
    finally:
        (sources.IndexedMcap.open, bag_reader.fast_deserializer, layers.LayerDecoder.cells,
         outputs.write_frame_messages, outputs.InfoCopier._copy) = saved
