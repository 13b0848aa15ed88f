"""The replay pipeline (bags/replay/pipeline.py): read-ahead items and the source's exception arrive in order, closing
stops the thread and runs the source's ``finally``, in-order calls run in order and hand back the first error; a replay through the pipeline
equals one in a single thread."""

from __future__ import annotations

import json
import threading

import pytest

from bags.replay import ReplayOptions, replay
from bags.replay.pipeline import InOrder, Prefetch
from bev_mapper_core.mapper import MapperConfig


def test_items_then_the_sources_exception_in_order():
    def source():
        yield from range(10)
        raise ValueError("damaged at 10")

    got = []
    with pytest.raises(ValueError, match="damaged at 10"):
        for x in Prefetch(source(), depth=2):
            got.append(x)
    assert got == list(range(10))


def test_close_stops_reading_and_runs_the_sources_finally():
    read, closed = [], threading.Event()

    def source():
        try:
            for i in range(1000):
                read.append(i)
                yield i
        finally:
            closed.set()

    p = Prefetch(source(), depth=3)
    it = iter(p)
    assert [next(it) for _ in range(5)] == [0, 1, 2, 3, 4]
    p.close()
    assert closed.is_set()
    assert len(read) <= 5 + 3 + 1  # taken + queued + the one waiting for room
    with pytest.raises(ValueError):
        Prefetch(iter(()), depth=0)


@pytest.mark.slow
def test_replay_through_the_pipeline_equals_one_thread(small_drive_mcap, tmp_path):
    docs = []
    for n in (0, 4):
        out = tmp_path / f"pipeline{n}"
        replay(ReplayOptions(bag=small_drive_mcap[0], out=out, mapper=MapperConfig(method="ipm"), pipeline=n,
                             pictures=False, report=False))
        docs.append(json.loads((out / "metrics.json").read_text()))
    for d in docs:
        d.pop("latency_ms")
        d.pop("score_process")
    assert docs[0] == docs[1] and docs[0]["frames"] > 0


def test_in_order_runs_calls_in_order_and_hands_back_the_first_error():
    done = []
    w = InOrder(depth=2)
    for i in range(20):
        w.submit(done.append, i)
    w.close()
    assert done == list(range(20))

    def fail(i):
        if i == 3:
            raise OSError("disk full at 3")
        done.append(i)

    done.clear()
    w = InOrder(depth=1)
    with pytest.raises(OSError, match="disk full at 3"):
        for i in range(50):
            w.submit(fail, i)
        w.close()
    assert done == [0, 1, 2]  # nothing after the failed call ran
    w.close(abandon=True)
