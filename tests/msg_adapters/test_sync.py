"""msg_adapters.sync: scripted arrival orders, no threads or clocks needed."""

from __future__ import annotations

import threading

import pytest

from msg_adapters import FrameSynchronizer, SyncConfig, SyncConfigError
from msg_adapters.errors import AdapterError

MS = 1_000_000
CAMS = ("front", "left", "right")
CFG = SyncConfig(slop_ns=10 * MS, timeout_ns=150 * MS, queue_size=4, jump_back_ns=500 * MS)


def feed(sync, script):
    """script: (camera, stamp_ms[, now_ms]) tuples; returns every emitted set in order."""
    out = []
    for item in script:
        cam, stamp = item[0], item[1] * MS
        now = item[2] * MS if len(item) > 2 else None
        out += sync.add(cam, stamp, f"{cam}@{item[1]}", now_ns=now)
    return out


def frames(start_ms, n, period_ms=100, cams=CAMS, jitter=None):
    script = []
    for i in range(n):
        for j, c in enumerate(cams):
            script.append((c, start_ms + i * period_ms + (jitter[j] if jitter else 0)))
    return script


def test_in_order_complete_sets():
    got = []
    sync = FrameSynchronizer(CAMS, CFG, callback=got.append)
    out = feed(sync, frames(1000, 3))
    assert [s.stamp_ns for s in out] == [1000 * MS, 1100 * MS, 1200 * MS]
    assert all(s.complete and s.reason == "complete" for s in out)
    assert got == out
    assert out[1].messages == {"front": "front@1100", "left": "left@1100", "right": "right@1100"}
    assert sync.stats.complete == 3 and sync.pending == 0


def test_out_of_order_arrival():
    script = [("left", 1100), ("front", 1000), ("right", 1000), ("front", 1100), ("left", 1000),
              ("right", 1100)]
    out = feed(FrameSynchronizer(CAMS, CFG), script)
    assert [s.stamp_ns // MS for s in out] == [1000, 1100]
    assert all(s.complete for s in out)
    assert out[0].messages["left"] == "left@1000"


def test_jitter_within_slop_groups_and_beyond_slop_splits():
    out = feed(FrameSynchronizer(CAMS, CFG), frames(1000, 2, jitter=[0, 4, -5]))
    assert [s.complete for s in out] == [True, True]
    assert out[0].stamps == {"front": 1000 * MS, "left": 1004 * MS, "right": 995 * MS}
    # 12 ms spread > 10 ms slop: the late-jittered camera cannot join
    sync = FrameSynchronizer(CAMS, CFG)
    out = feed(sync, [("front", 1000), ("left", 1004), ("right", 1012)])
    assert out == [] and sync.pending == 2


def test_missing_camera_times_out_as_partial_set():
    sync = FrameSynchronizer(CAMS, CFG)
    script = [c for c in frames(1000, 4) if c[0] != "right"]
    out = feed(sync, script)
    # deadline of the 1000 ms set is 1150 ms: passed once the 1200 ms messages arrive
    assert [s.stamp_ns // MS for s in out] == [1000, 1100]
    s = out[0]
    assert s.valid == (True, True, False) and not s.complete and s.reason == "timeout"
    assert s.messages["right"] is None and s.stamps["right"] is None
    assert s.valid_names == ("front", "left")
    assert sync.poll(1450 * MS)[-1].stamp_ns == 1300 * MS
    assert sync.stats.partial == 4


def test_poll_uses_explicit_now():
    sync = FrameSynchronizer(CAMS, CFG)
    feed(sync, [("front", 1000, 5000), ("left", 1000, 5001)])
    assert sync.poll(5149 * MS) == []
    (s,) = sync.poll(5150 * MS)
    assert s.valid == (True, True, False)


def test_late_message_is_dropped_and_counted():
    sync = FrameSynchronizer(CAMS, CFG)
    out = feed(sync, [c for c in frames(1000, 3) if c != ("right", 1000)])
    assert out[0].valid == (True, True, False)
    assert feed(sync, [("right", 1000)]) == []
    assert sync.stats.late == 1
    # the next frame is unaffected
    assert feed(sync, [("right", 1300), ("front", 1300), ("left", 1300)])[-1].complete


def test_superseded_older_set_emitted_first():
    sync = FrameSynchronizer(CAMS, CFG)
    out = feed(sync, [("front", 1000), ("front", 1100), ("left", 1100), ("right", 1100)])
    assert [(s.stamp_ns // MS, s.reason) for s in out] == [(1000, "superseded"), (1100, "complete")]


def test_queue_bound_overflow():
    sync = FrameSynchronizer(CAMS, SyncConfig(slop_ns=MS, timeout_ns=10**12, queue_size=2))
    out = feed(sync, [("front", 1000), ("front", 1100), ("front", 1200)])
    assert [(s.stamp_ns // MS, s.reason) for s in out] == [(1000, "overflow")]
    assert sync.stats.overflow == 1 and sync.pending == 2


def test_backwards_jump_resets():
    sync = FrameSynchronizer(CAMS, CFG)
    feed(sync, frames(5000, 2))
    feed(sync, [("front", 5200)])
    assert sync.pending == 1
    out = feed(sync, frames(1000, 2))  # bag loop: back to t = 1 s
    assert sync.stats.resets == 1 and sync.stats.dropped_on_reset == 1
    assert [s.stamp_ns // MS for s in out] == [1000, 1100] and all(s.complete for s in out)
    assert sync.stats.late == 0


def test_min_valid_drops_sparse_sets():
    sync = FrameSynchronizer(CAMS, SyncConfig(slop_ns=MS, timeout_ns=50 * MS, min_valid=2))
    out = feed(sync, [("front", 1000), ("front", 1100), ("left", 1100), ("front", 1200),
                      ("left", 1200), ("right", 1200)])
    assert [(s.stamp_ns // MS, s.valid) for s in out] == [(1100, (True, True, False)),
                                                          (1200, (True, True, True))]
    assert sync.stats.sparse == 1


def test_flush_and_duplicates():
    sync = FrameSynchronizer(CAMS, CFG)
    feed(sync, [("front", 1000), ("front", 1002)])  # same camera twice within slop: two sets
    assert sync.pending == 2
    out = sync.flush()
    assert [s.reason for s in out] == ["superseded", "flush"] or [s.reason for s in out] == [
        "flush", "flush"]
    assert sync.pending == 0


def test_bad_config_and_names():
    with pytest.raises(SyncConfigError):
        SyncConfig(slop_ns=-1)
    with pytest.raises(SyncConfigError):
        SyncConfig(queue_size=0)
    with pytest.raises(SyncConfigError):
        FrameSynchronizer(("a", "a"))
    with pytest.raises(AdapterError, match="unknown stream"):
        FrameSynchronizer(CAMS).add("rear", 0, None)


def test_callback_outside_lock_and_threads():
    """The callback may call back into the synchronizer (would deadlock under the lock)."""
    seen = []

    def cb(s):
        seen.append(s.stamp_ns)
        assert sync.pending >= 0  # takes the lock

    sync = FrameSynchronizer(CAMS, SyncConfig(slop_ns=MS, timeout_ns=10**12, queue_size=10**6),
                             callback=cb)
    n = 300

    def run(cam):
        for i in range(n):
            sync.add(cam, (1000 + 100 * i) * MS, i)

    threads = [threading.Thread(target=run, args=(c,)) for c in CAMS]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    sync.flush()
    assert seen == sorted(seen) and len(seen) == n
    assert sync.stats.complete == n


SIX = ("front", "front_right", "back_right", "back", "back_left", "front_left")


def test_default_window_takes_a_43_ms_rolling_trigger_as_one_set():
    """nuScenes' six cameras fire over ~43 ms: with the defaults, one set per frame at 10 Hz."""
    sync = FrameSynchronizer(SIX, SyncConfig())
    out = feed(sync, frames(0, 10, cams=SIX, jitter=[round(j * 43 / 5) for j in range(6)]))
    out += sync.flush()
    assert [s.reason for s in out] == ["complete"] * 10
    assert sync.stats.split == 0 and sync.window_ns == 50 * MS and sync.period_ns == 100 * MS


def test_window_narrows_to_half_the_frame_period():
    """At 20 Hz a 50 ms window could join one camera's image to the next frame: it narrows to
    25 ms once the period is measured, and consecutive frames are never merged."""
    sync = FrameSynchronizer(SIX, SyncConfig())
    out = feed(sync, frames(0, 12, period_ms=50, cams=SIX, jitter=[0, 4, 8, 12, 16, 20]))
    out += sync.flush()
    assert sync.period_ns == 50 * MS and sync.window_ns == 25 * MS
    assert [s.reason for s in out] == ["complete"] * 12
    assert [s.stamps["front"] // MS for s in out] == [50 * i for i in range(12)]


def test_a_set_split_by_a_narrow_window_is_counted():
    sync = FrameSynchronizer(SIX, SyncConfig(slop_ns=20 * MS, timeout_ns=300 * MS))
    out = feed(sync, frames(0, 5, cams=SIX, jitter=[round(j * 43 / 5) for j in range(6)]))
    out += sync.flush()
    assert len(out) == 10 and not any(s.complete for s in out)
    assert sync.stats.split == 5 and sync.stats.partial == 10
    # a camera that is merely absent is no split
    sync = FrameSynchronizer(CAMS, SyncConfig())
    out = feed(sync, [(c, t) for c, t in frames(0, 5) if c != "right"]) + sync.flush()
    assert sync.stats.split == 0 and sync.stats.partial == 5


def test_max_slop_fraction_is_checked():
    with pytest.raises(SyncConfigError, match="max_slop_fraction"):
        SyncConfig(max_slop_fraction=1.5)
