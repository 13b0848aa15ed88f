"""Approximate-time synchronizer for N camera streams, with partial sets on timeout.

Pure logic, no threads or timers of its own: time advances only through message stamps and the
``now_ns`` arguments of :meth:`FrameSynchronizer.add` / :meth:`FrameSynchronizer.poll`, so the
behaviour is reproducible in unit tests and in offline bag replay.

Rules:

* A message joins the pending set where its stream is still free and the set's stamp spread
  (max - min) stays within the window; the closest such set wins. Otherwise it opens a new set
  whose deadline is ``now + timeout_ns``. The window is ``slop_ns`` (50 ms: real rigs trigger
  their cameras over tens of milliseconds, nuScenes' six over ~43 ms), but at most
  ``max_slop_fraction`` of the cameras' frame period as measured from the stamps (the median
  interval of each stream's last messages, the median over the streams), so that two
  consecutive frames are never merged into one set (at 20 Hz the window is 25 ms).
* A set is emitted as soon as every stream is filled. Older pending sets are emitted first
  (partial, reason ``'superseded'``), so output stamps are monotonic.
* At ``now >= deadline`` a set is emitted partial (reason ``'timeout'``): the missing streams
  are masked out in :attr:`SyncedSet.valid`, the frame is not dropped.
* More than ``queue_size`` pending sets: the oldest is emitted partial (``'overflow'``), which
  bounds each stream's queue to ``queue_size`` messages.
* A message that joins no pending set and is not newer than the last emitted set (+ window)
  belongs to a set already emitted: it is dropped and counted as ``late``; unless its stream
  was in that set with an older stamp (then it is the next frame's).
* A stamp more than ``jump_back_ns`` behind the newest stamp of the *same* stream, or a
  ``now`` that far behind the newest ``now`` (a bag loop, a simulator restart), resets the
  synchronizer; pending sets are dropped and counted. A camera that merely lags behind the
  others does not trigger a reset (its messages end up late or in partial sets).

Thread safety: state is guarded by a lock; the callback runs after the lock is released. Sets
are delivered in emission order even when :meth:`add` is called from several threads (one
caller drains the output queue while the others only enqueue).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

from .errors import AdapterError, SyncConfigError

#: Intervals per stream kept to measure the frame period.
_INTERVALS = 9

#: Offline bag replay widens the live timeout by this factor (see :meth:`SyncConfig.replay`).
REPLAY_WIDENING = 1.5


@dataclass(frozen=True)
class SyncConfig:
    """Synchronizer settings (all times in integer nanoseconds).

    The defaults are the live ones: the node's ``sync_slop_s`` / ``sync_timeout_s`` parameters
    default to ``slop_ns`` / ``timeout_ns``. Offline replay uses :meth:`replay`.
    """

    slop_ns: int = 50_000_000
    timeout_ns: int = 200_000_000
    queue_size: int = 8
    jump_back_ns: int = 1_000_000_000
    #: Partial sets with fewer valid streams are dropped (counted in ``sparse``).
    min_valid: int = 1
    #: The window never exceeds this fraction of the measured frame period (0 = no limit).
    max_slop_fraction: float = 0.5

    def __post_init__(self) -> None:
        if self.slop_ns < 0 or self.timeout_ns < 0:
            raise SyncConfigError(f"slop and timeout must be >= 0, got {self.slop_ns}, {self.timeout_ns}")
        if self.queue_size < 1:
            raise SyncConfigError(f"queue_size must be >= 1, got {self.queue_size}")
        if self.jump_back_ns <= 0:
            raise SyncConfigError(f"jump_back_ns must be > 0, got {self.jump_back_ns}")
        if self.min_valid < 1:
            raise SyncConfigError(f"min_valid must be >= 1, got {self.min_valid}")
        if not 0.0 <= self.max_slop_fraction <= 1.0:
            raise SyncConfigError(f"max_slop_fraction must be in [0, 1], got {self.max_slop_fraction}")

    @classmethod
    def replay(cls, slop_ns: int | None = None, timeout_ns: int | None = None) -> "SyncConfig":
        """Settings for reading bags offline: the live window (``slop_ns``), the timeout
        :data:`REPLAY_WIDENING` times the live one (300 ms), twice the queue; ``slop_ns`` /
        ``timeout_ns`` replace them (``bev-bag replay --sync-slop-ms / --sync-timeout-ms``).

        Offline nothing waits for a late camera, so a longer timeout costs nothing; the window
        is the live one, so that a bag replays into the sets the node maps.
        """
        return cls(slop_ns=cls.slop_ns if slop_ns is None else int(slop_ns),
                   timeout_ns=round(cls.timeout_ns * REPLAY_WIDENING) if timeout_ns is None else int(timeout_ns),
                   queue_size=2 * cls.queue_size)


@dataclass(frozen=True)
class SyncedSet:
    """One synchronized frame.

    Attributes:
        names: stream names, in synchronizer order.
        messages: per stream, the message or ``None`` where the stream is missing.
        stamps: per stream, the stamp (ns) or ``None``.
        valid: per stream, True where a message is present (aligned with ``names``).
        reason: ``'complete'``, ``'superseded'``, ``'timeout'``, ``'overflow'`` or ``'flush'``.
    """

    names: tuple[str, ...]
    messages: dict[str, Any]
    stamps: dict[str, int | None]
    valid: tuple[bool, ...]
    reason: str

    @property
    def complete(self) -> bool:
        """True when every stream is present."""
        return all(self.valid)

    @property
    def stamp_ns(self) -> int:
        """Earliest stamp of the set."""
        return min(s for s in self.stamps.values() if s is not None)

    @property
    def mean_stamp_ns(self) -> int:
        """Mean of the present stamps (rounded down)."""
        present = [s for s in self.stamps.values() if s is not None]
        return sum(present) // len(present)

    @property
    def valid_names(self) -> tuple[str, ...]:
        """Names of the present streams."""
        return tuple(n for n, v in zip(self.names, self.valid) if v)


@dataclass(frozen=True)
class SyncStats:
    """Counters since construction (resets do not clear them)."""

    complete: int = 0
    partial: int = 0
    #: partial sets whose missing streams came in the next set, less than half a frame period
    #: later: one frame whose cameras spread wider than the window (see :attr:`SyncConfig.slop_ns`)
    split: int = 0
    late: int = 0
    overflow: int = 0
    sparse: int = 0
    resets: int = 0
    dropped_on_reset: int = 0


@dataclass
class _Open:
    deadline_ns: int
    msgs: dict[str, tuple[int, Any]] = field(default_factory=dict)

    @property
    def lo(self) -> int:
        return min(s for s, _ in self.msgs.values())

    @property
    def hi(self) -> int:
        return max(s for s, _ in self.msgs.values())


class FrameSynchronizer:
    """Groups messages of N named streams into :class:`SyncedSet` s (see module docstring)."""

    def __init__(
        self,
        names: Sequence[str],
        config: SyncConfig = SyncConfig(),
        callback: Callable[[SyncedSet], None] | None = None,
    ) -> None:
        names = tuple(names)
        if not names or len(set(names)) != len(names):
            raise SyncConfigError(f"need distinct stream names, got {names}")
        self.names = names
        self.config = config
        self.callback = callback
        self._lock = threading.Lock()
        self._pending: list[_Open] = []
        self._newest_now: int | None = None
        self._newest_stamp: dict[str, int] = {}  # per stream
        self._last_emitted_lo: int | None = None
        self._last_emitted: dict[str, int] = {}  # stream -> its stamp in the last emitted set
        self._intervals: dict[str, deque[int]] = {n: deque(maxlen=_INTERVALS) for n in names}
        self._last_partial: tuple[frozenset[str], int, int] | None = None  # (streams, lo, hi)
        self._stats = SyncStats()
        self._out: deque[SyncedSet] = deque()
        self._draining = False

    # ----------------------------------------------------------------- public
    @property
    def stats(self) -> SyncStats:
        """A snapshot of the counters."""
        with self._lock:
            return self._stats

    @property
    def window_ns(self) -> int:
        """The stamp spread a set may have now: ``slop_ns``, at most ``max_slop_fraction`` of the
        measured frame period (see the module docstring).
        """
        with self._lock:
            return self._window()

    @property
    def period_ns(self) -> int | None:
        """The cameras' frame period measured from the stamps (``None`` until measured)."""
        with self._lock:
            return self._period()

    @property
    def pending(self) -> int:
        """Number of sets waiting for messages."""
        with self._lock:
            return len(self._pending)

    def add(self, name: str, stamp_ns: int, msg: Any, now_ns: int | None = None) -> list[SyncedSet]:
        """Feed one message; returns the sets this call emitted (also passed to the callback).

        Args:
            name: stream name (one of ``names``).
            stamp_ns: the message's header stamp.
            msg: anything; handed back in :attr:`SyncedSet.messages`.
            now_ns: current time (e.g. the node clock); ``None`` = stamp-driven time, the
                newest stamp seen on any stream. Only an explicit ``now_ns`` can jump back.
        """
        if name not in self.names:
            raise AdapterError(f"unknown stream {name!r}; expected one of {list(self.names)}")
        stamp_ns = int(stamp_ns)
        with self._lock:
            out = self._add_locked(name, stamp_ns, msg, None if now_ns is None else int(now_ns))
            self._enqueue(out)
        self._drain()
        return out

    def poll(self, now_ns: int) -> list[SyncedSet]:
        """Advance time to ``now_ns`` and emit the sets whose timeout has passed."""
        now = int(now_ns)
        with self._lock:
            self._advance_now(now)
            out = self._expire(now)
            self._enqueue(out)
        self._drain()
        return out

    def flush(self) -> list[SyncedSet]:
        """Emit every pending set now (end of a bag)."""
        with self._lock:
            out = self._emit_upto(len(self._pending) - 1, "flush")
            self._enqueue(out)
        self._drain()
        return out

    def reset(self) -> None:
        """Drop pending sets and forget the time history."""
        with self._lock:
            self._reset_locked()

    # --------------------------------------------------------------- internals
    def _period(self) -> int | None:
        """Median over the streams of each stream's median interval (streams with 2+ intervals)."""
        per_stream = sorted(sorted(d)[len(d) // 2] for d in self._intervals.values() if len(d) >= 2)
        return per_stream[len(per_stream) // 2] if per_stream else None

    def _window(self) -> int:
        cfg = self.config
        period = self._period()
        if period is None or cfg.max_slop_fraction <= 0:
            return cfg.slop_ns
        return min(cfg.slop_ns, int(period * cfg.max_slop_fraction))

    def _reset_locked(self) -> None:
        self._stats = replace(
            self._stats,
            resets=self._stats.resets + 1,
            dropped_on_reset=self._stats.dropped_on_reset + len(self._pending),
        )
        self._pending.clear()
        self._newest_now = None
        self._newest_stamp.clear()
        self._last_emitted_lo = None
        self._last_emitted = {}
        self._last_partial = None
        for d in self._intervals.values():
            d.clear()

    def _advance_now(self, now: int) -> None:
        """Track ``now``; reset on a backwards jump."""
        if self._newest_now is not None and now < self._newest_now - self.config.jump_back_ns:
            self._reset_locked()
        self._newest_now = now if self._newest_now is None else max(self._newest_now, now)

    def _add_locked(self, name: str, stamp: int, msg: Any, now: int | None) -> list[SyncedSet]:
        cfg = self.config
        last = self._newest_stamp.get(name)
        if last is not None and stamp < last - cfg.jump_back_ns:
            self._reset_locked()
        if now is None:  # stamp-driven time: the newest stamp of any stream
            now = stamp if self._newest_now is None else max(self._newest_now, stamp)
        self._advance_now(now)
        if last is not None and stamp > last:
            self._intervals[name].append(stamp - last)
        self._newest_stamp[name] = max(self._newest_stamp.get(name, stamp), stamp)

        window = self._window()
        best, best_cost = None, None
        for i, s in enumerate(self._pending):
            if name in s.msgs:
                continue
            lo, hi = min(s.lo, stamp), max(s.hi, stamp)
            if hi - lo > window:
                continue
            cost = abs(stamp - (s.lo + s.hi) / 2)
            if best_cost is None or cost < best_cost:
                best, best_cost = i, cost

        out: list[SyncedSet] = []
        if best is None:
            if (self._last_emitted_lo is not None and stamp <= self._last_emitted_lo + window
                    and stamp <= self._last_emitted.get(name, stamp)):  # newer than its last: the next frame
                self._stats = replace(self._stats, late=self._stats.late + 1)
                return self._expire(now)
            new = _Open(deadline_ns=now + cfg.timeout_ns, msgs={name: (stamp, msg)})
            best = sum(1 for s in self._pending if s.lo <= stamp)
            self._pending.insert(best, new)
        else:
            self._pending[best].msgs[name] = (stamp, msg)

        if len(self._pending[best].msgs) == len(self.names):
            out += self._emit_upto(best, "superseded")
        while len(self._pending) > cfg.queue_size:
            self._stats = replace(self._stats, overflow=self._stats.overflow + 1)
            out += self._emit_upto(0, "overflow")
        out += self._expire(now)
        return out

    def _expire(self, now: int) -> list[SyncedSet]:
        last = -1
        for i, s in enumerate(self._pending):
            if now >= s.deadline_ns:
                last = i
        return self._emit_upto(last, "timeout") if last >= 0 else []

    def _emit_upto(self, last: int, reason: str) -> list[SyncedSet]:
        """Emit pending sets ``0..last`` (the last with ``reason`` unless complete)."""
        out = []
        for i in range(last + 1):
            s = self._pending.pop(0)
            r = reason if i == last else ("flush" if reason == "flush" else "superseded")
            built = self._build(s, r)
            self._last_emitted_lo = s.lo
            self._last_emitted = {n: t for n, (t, _) in s.msgs.items()}
            if built is not None:
                out.append(built)
        return out

    def _build(self, s: _Open, reason: str) -> SyncedSet | None:
        valid = tuple(n in s.msgs for n in self.names)
        complete = all(valid)
        if not complete and sum(valid) < self.config.min_valid:
            self._stats = replace(self._stats, sparse=self._stats.sparse + 1)
            return None
        if complete:
            self._stats = replace(self._stats, complete=self._stats.complete + 1)
            self._last_partial = None
        else:
            self._stats = replace(self._stats, partial=self._stats.partial + 1)
            self._count_split(s)
        return SyncedSet(
            names=self.names,
            messages={n: s.msgs[n][1] if n in s.msgs else None for n in self.names},
            stamps={n: s.msgs[n][0] if n in s.msgs else None for n in self.names},
            valid=valid,
            reason="complete" if complete else reason,
        )

    def _count_split(self, s: _Open) -> None:
        """Count ``s`` as the second half of a split frame when it holds only streams that the
        partial set emitted just before it lacked, within half a frame period of it.
        """
        streams, prev = frozenset(s.msgs), self._last_partial
        self._last_partial = (streams, s.lo, s.hi)
        if prev is None or streams & prev[0]:
            return
        period = self._period()
        reach = period // 2 if period is not None else 4 * self.config.slop_ns
        if max(s.hi, prev[2]) - min(s.lo, prev[1]) < reach:
            self._stats = replace(self._stats, split=self._stats.split + 1)
            self._last_partial = None

    def _enqueue(self, sets: list[SyncedSet]) -> None:
        """Queue emitted sets for the callback (called with the lock held, in emission order)."""
        if self.callback is not None:
            self._out.extend(sets)

    def _drain(self) -> None:
        """Hand queued sets to the callback in order, outside the lock; one thread at a time."""
        if self.callback is None:
            return
        with self._lock:
            if self._draining or not self._out:
                return
            self._draining = True
        try:
            while True:
                with self._lock:
                    if not self._out:
                        self._draining = False
                        return
                    item = self._out.popleft()
                self.callback(item)
        except BaseException:
            with self._lock:
                self._draining = False
            raise
