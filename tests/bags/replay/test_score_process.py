"""Issue #28: scoring a replay in a process of its own (``--score-process``) gives every output of
scoring in the replay's process; a failure there is an error of the replay, never a hang, and
leaves no process behind."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest
from bag_helpers import replay_ipm, replay_outputs, synth_small

from bags.replay import ReplayOptions, replay
from bags.replay.frame_messages import prediction_cells
from bags.replay.score_process import AUTO_MIN_FRAMES, AUTO_MIN_SPARE, ScoringError, ScoringProcess, start_child, stop_child, use_process
from bags.replay.scoring import FrameLayers, ReplayScorer
from bev_mapper_core.errors import InputError
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.mapper import BevPrediction, MapperConfig

pytest.importorskip("bev_mapper_core.synth")


def _children() -> list[int]:
    """Pids of this process's live children (from /proc)."""
    me, out = os.getpid(), []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2:].split()  # after "pid (comm) "
            if int(fields[1]) == me and fields[0] != "Z":
                out.append(int(entry.name))
    return out


@pytest.mark.slow
def test_outputs_equal_scoring_in_the_replays_process(tmp_path):
    bag = synth_small(tmp_path / "drive", frames=6, seed=33)
    assert replay_ipm(bag, tmp_path / "here", "--frames-every", "2", "--score-process", "off") == 0
    here = replay_outputs(tmp_path / "here")
    assert here[0]["frames_scored"] == 6 and here[0]["classes"]["drivable"]["cd"] is not None
    for pipeline in ("0", "4"):
        out = tmp_path / f"process-{pipeline}"
        assert replay_ipm(bag, out, "--frames-every", "2", "--score-process", "on", "--pipeline", pipeline) == 0
        there = replay_outputs(out)
        assert there[0] == here[0]
        assert there[1] == here[1] and len(there[1]) == 3
        assert there[2] == here[2]
        assert there[3] == here[3]
    assert not _children()


def test_a_scoring_process_that_dies_is_an_error_of_the_replay(tmp_path):
    bag = synth_small(tmp_path / "drive", frames=8, seed=34)
    killed = []

    class KillAtFrame3:
        def __init__(self, total) -> None:
            self.n = 0

        def update(self, n: int) -> None:
            self.n += n
            if self.n == 3 and not killed:
                for pid in _children():
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)

        def close(self) -> None:
            pass

    options = ReplayOptions(bag=bag, out=tmp_path / "out", mapper=MapperConfig(method="ipm"), score_process="on")
    with pytest.raises(ScoringError, match="exited unexpectedly.*--score-process off"):
        replay(options, progress=KillAtFrame3)
    assert killed
    assert not _children()
    assert not (tmp_path / "out" / "metrics.json").exists()


def test_the_scorers_error_in_the_process_is_raised_in_the_replay():
    grid = BevGrid(x_min=-5.0, x_max=5.0, y_min=-2.5, y_max=2.5, resolution=0.25)
    names = ("drivable", "vehicle")
    scorer = ReplayScorer(grid, names, names, ground=False)
    local = ReplayScorer(grid, names, names, ground=False)
    remote = ScoringProcess(scorer, len(names), grid.shape)
    try:
        rng = np.random.default_rng(28)
        for _ in range(4):  # more frames than slots: each answer taken before its slot is reused
            gt = rng.random((2,) + grid.shape) < 0.3
            layers = FrameLayers(gt, rng.random(grid.shape) < 0.9, None, np.ones(grid.shape, bool), None)
            pred = BevPrediction(names, rng.random((2,) + grid.shape).astype(np.float32),
                                 rng.random(grid.shape) < 0.8)
            if remote.full:
                remote.take()
            remote.submit(layers, pred, prediction_cells(pred))
            local.add(layers, pred)  # the published bytes computed here: the same scores
        while remote.pending:
            remote.take()
        probs = pred.probs.copy()
        probs[0, 0, 0] = np.nan
        remote.submit(layers, BevPrediction(names, probs, np.ones(grid.shape, bool)),
                      prediction_cells(BevPrediction(names, probs, None)))
        with pytest.raises(InputError, match="NaN"):
            remote.take()
        state = remote.close()
    finally:
        remote.close(abandon=True)
    assert state == local.state()  # the frame that failed added nothing
    assert not _children()


def test_auto_scores_in_a_process_only_long_drives_on_two_cores_with_a_core_free():
    cores = len(os.sched_getaffinity(0))
    assert use_process("on", 1) and not use_process("off", 10 ** 6)
    assert use_process("on", 1, spare=-3.0)  # asked for: the load does not matter
    assert not use_process("auto", None) and not use_process("auto", AUTO_MIN_FRAMES - 1)
    assert use_process("auto", AUTO_MIN_FRAMES) == (cores >= 2)  # the load unknown: taken as free
    assert use_process("auto", AUTO_MIN_FRAMES, spare=AUTO_MIN_SPARE) == (cores >= 2)
    assert not use_process("auto", AUTO_MIN_FRAMES, spare=AUTO_MIN_SPARE - 0.01)  # the cores are busy


def test_metrics_say_where_the_frames_were_scored(tmp_path):
    bag = synth_small(tmp_path / "drive", frames=3, seed=36)
    for setting, ran in (("on", "process"), ("off", "replay"), ("auto", "replay")):  # auto: 3 frames
        result = replay(ReplayOptions(bag=bag, out=tmp_path / setting, mapper=MapperConfig(method="ipm"),
                                      score_process=setting, pictures=False, report=False))
        doc = result.metrics["score_process"]
        assert doc["setting"] == setting and doc["ran"] == ran
        assert doc["spare_cores"] is None or doc["spare_cores"] <= len(os.sched_getaffinity(0))
    assert not _children()


def test_a_child_started_early_and_never_used_exits_quietly():
    """The replay starts its scoring process before it knows it needs it (the mapper may fail):
    stopped unused, it exits 0 at once; stopping it twice, or ``None``, is harmless."""
    child = start_child()
    stop_child(child)
    assert child.returncode == 0
    stop_child(child)
    stop_child(None)
    assert not _children()


def test_a_replay_whose_mapper_fails_leaves_no_scoring_process(tmp_path):
    bag = synth_small(tmp_path / "drive", frames=3, seed=37)
    with pytest.raises(Exception, match="weights"):
        replay(ReplayOptions(bag=bag, out=tmp_path / "out", score_process="on",
                             mapper=MapperConfig(method="bimapper", weights=str(tmp_path / "missing.safetensors"))))
    assert not _children()


def test_a_scoring_process_that_cannot_start_leaves_the_scoring_here(tmp_path, monkeypatch):
    """No interpreter to run (an embedded Python): the replay scores in its own process and says so."""
    bag = synth_small(tmp_path / "drive", frames=3, seed=35)
    monkeypatch.setattr("sys.executable", str(tmp_path / "no-python"))
    result = replay(ReplayOptions(bag=bag, out=tmp_path / "out", mapper=MapperConfig(method="ipm"),
                                  score_process="on"))
    assert result.metrics["frames_scored"] == 3 and result.damage is None
    assert any("scoring process did not start" in n for n in result.notes)
    assert not _children()


def test_the_process_computes_the_published_cells_and_picture_as_the_replay_does():
    """With the mapper's classes the child also computes each frame's OccupancyGrid cells and,
    while the replay does not wait for its answers, the ``/bev/image`` picture (taken off the
    replay's process): the same bytes as computed here, the unknown cells included. When the
    replay waits it draws the picture itself; without the classes the child computes neither."""
    from bev_mapper_core.labels.classes import bev_picture, resolve_classes

    grid = BevGrid(x_min=-5.0, x_max=5.0, y_min=-2.5, y_max=2.5, resolution=0.25)
    names = ("drivable", "vehicle")
    classes = resolve_classes(names)
    rng = np.random.default_rng(3)
    frames = []
    for _ in range(4):
        known = rng.random(grid.shape) < 0.8
        probs = rng.random((2,) + grid.shape).astype(np.float32)
        probs[:, ~known] = np.nan  # as IPM leaves them
        layers = FrameLayers(rng.random((2,) + grid.shape) < 0.3, rng.random(grid.shape) < 0.9, None,
                             np.ones(grid.shape, bool), None)
        frames.append((layers, BevPrediction(names, probs, known)))
    for published, waited in ((classes, 0.0), (classes, 1.0), (None, 0.0)):
        remote = ScoringProcess(ReplayScorer(grid, names, names, ground=False), 2, grid.shape,
                                published=published)
        try:
            got = []  # every frame's answer, in order
            for layers, pred in frames:
                remote.waited_s = waited  # 1 s: the replay is waiting for the child
                remote.submit(layers, pred)
                got.append(remote.take())
            remote.close()
        finally:
            remote.close(abandon=True)
        for (_, pred), (_, cells, image) in zip(frames, got):
            if published is None:
                assert cells is None and image is None
                continue
            np.testing.assert_array_equal(cells, prediction_cells(pred))
            assert (cells == -1).any()
            if waited:
                assert image is None
            else:
                np.testing.assert_array_equal(image, bev_picture(grid, pred.probs, classes, pred.known))
    assert not _children()
