"""Mapping a replay's frames: read them (ahead, in a thread), map each (with temporal fusion when
asked), time the mapper and hand the prediction on, in frame order, to the stage that scores it
and has it written (in threads of their own, see :mod:`bags.replay.pipeline`). Each frame's cameras
are placed with the ego pose of their own stamps first (:mod:`bev_mapper_core.placement`, as the
node does), counted in ``metrics.json``'s ``placement``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.labels.label_maps import label_map
from bev_mapper_core.mapper import BevPrediction
from bev_mapper_core.placement import RigPlacer
from bev_mapper_core.temporal import OdometryCheck, TemporalFusion

from ..errors import BagCorruptError
from .options import ReplayRun
from .pipeline import InOrder, Prefetch

log = logging.getLogger("bags.replay")


@dataclass
class MappingTally:
    """What :func:`map_frames` counted: the mapping latency (ms) of every mapped frame, the frames
    mapped and skipped (no images of the input kind), the damage that ended the reading (or the
    frame the mapper failed on), the temporal fusion's counts (``metrics.json``'s ``temporal``)
    and the time placement's (``placement``: its settings and :data:`PLACEMENT_COUNTS
    <bev_mapper_core.placement.PLACEMENT_COUNTS>`; ``{"mode": "off"}`` when off).
    """

    temporal: dict
    placement: dict = field(default_factory=dict)
    latencies: list[float] = field(default_factory=list)
    mapped: int = 0
    skipped: int = 0
    damage: str | None = None


def map_frames(run: ReplayRun, finish: Callable, bar) -> MappingTally:
    """Map every frame of ``run``'s bag (up to ``max_frames``) and call ``finish(frame, prediction,
    index)`` for each, in order (with a pipeline, in its own thread while the next frame maps);
    ``bar.update(1)`` per mapped frame. Damage met while reading ends the loop and is returned in
    the tally; the frames mapped before it are finished first.
    """
    options, kind = run.options, run.input_kind
    window = options.temporal.window
    tally = MappingTally({"window": window, "fused_frames": 0, "resets": 0, "frames_without_pose": 0})
    uses_pose = window > 1 or run.mapper.uses_ego_pose
    check = OdometryCheck(options.temporal) if uses_pose else None
    if check is not None:  # the odometry as the memories see it (bev_mapper_core.temporal.OdometryCheck)
        tally.temporal["odometry_problems"] = check.counts
    if run.mapper.uses_ego_pose:  # the method's own memory (FocusBEV's bank)
        tally.temporal["method"] = {"fused_frames": 0, "resets": 0, "frames_without_pose": 0}
    # with a pipeline, the next frames are read and decoded by a thread while this one maps
    frames = run.reader.frames(rgb=kind == "rgb", labels=kind == "labels",
                               label_map=label_map(options.mapper.label_map), sync=options.sync,
                               gt_half=True)  # the scorer reads the layers >= 0.5
    if options.pipeline:
        frames = Prefetch(frames, options.pipeline)
    fusion = TemporalFusion(run.grid, options.temporal) if window > 1 else None
    placer = RigPlacer(run.grid, options.placement)
    placer.set_base(run.mapper.rig)
    stage = InOrder(options.pipeline) if options.pipeline else None
    finished = False
    try:
        for frame in frames:
            images = frame.labels if kind == "labels" else frame.rgb
            if not images:
                tally.skipped += 1
                continue
            t0 = time.perf_counter()
            images = _place(run, placer, frame, images)
            try:
                pred = _map_frame(run.mapper, fusion, check, frame, images, tally.temporal)
            except BevMapperError as exc:  # this frame's input: keep the outputs so far
                tally.damage = f"frame {frame.index} could not be mapped: {exc}"
                break
            tally.latencies.append((time.perf_counter() - t0) * 1000.0)
            if stage is None:
                finish(frame, pred, tally.mapped)
            else:  # scored (then written) by the in-order threads while the next frame maps
                stage.submit(finish, frame, pred, tally.mapped)
            tally.mapped += 1
            bar.update(1)
            if options.max_frames is not None and tally.mapped >= options.max_frames:
                break  # before reading further (and maybe meeting damage we don't need)
        finished = True
    except BagCorruptError as exc:
        tally.damage = str(exc)
        finished = True
    finally:
        frames.close()
        if stage is not None:
            stage.close(abandon=not finished)  # the frames mapped so far are scored and written
    cfg = options.placement
    tally.placement = {"mode": cfg.mode} if not cfg.enabled else {
        "mode": cfg.mode, "step_cells": cfg.step_cells, "max_offset_s": cfg.max_offset_s,
        **{k: (round(v, 4) if k == "max_offset_m" else int(v)) for k, v in placer.counts.items()}}
    return tally


def _place(run, placer: RigPlacer, frame, images):
    """Place the frame's cameras at their own times on the mapper (counted by ``placer``); what
    holds for the whole drive goes to the result's notes once, a frame's problems to the log.
    Returns the images to map (a method that keeps its rig: moved cameras' images warped).
    """
    stamps = {c: frame.camera_stamps.get(c) for c in images}
    _, notes = placer.place(run.mapper, stamps, frame.stamp_ns, frame.pose_at)
    for key, text in notes:
        if key.startswith("placement:"):
            run.notes.append(f"time placement: {text}")
        else:
            log.info("frame %d: time placement: %s", frame.index, text)
    return placer.warp(images)


def _map_frame(mapper, fusion: TemporalFusion | None, check: OdometryCheck | None, frame, images,
               temporal: dict) -> BevPrediction:
    """One frame through the mapper and the temporal fusion (counted in ``temporal``); its pose
    vetted by ``check`` first (a problem resets both memories and is counted).
    """
    odom = frame.odom
    pose = odom.world_from_ego if odom is not None else None
    if check is not None:
        verdict = check.check(frame.stamp_ns, pose, None if odom is None else odom.stamp_ns,
                              None if odom is None else (odom.frame_id, odom.child_frame_id),
                              getattr(odom, "pose_covariance", None))
        if verdict.reset and verdict.pose is not None:  # a pose the memories cannot be aligned with
            temporal["resets"] += 1
            if fusion is not None:
                fusion.reset()
            if mapper.uses_ego_pose:
                mapper.reset()
        pose = verdict.pose
    pred = mapper.map(images, ego_pose=pose, stamp_ns=frame.stamp_ns)
    if "method" in temporal:
        method = temporal["method"]
        method["fused_frames"] += pred.frames
        if pred.note:
            method["frames_without_pose" if pose is None else "resets"] += 1
    if fusion is None:
        return pred
    fused = fusion.update(pred, frame.stamp_ns, pose)
    temporal["fused_frames"] += fused.frames
    if fused.note:
        temporal["frames_without_pose" if pose is None else "resets"] += 1
    return fused.prediction
