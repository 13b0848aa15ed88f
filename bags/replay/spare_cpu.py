"""How much CPU the other jobs on the machine leave free, measured over an interval:
:class:`CpuWatch`.

``bev-bag replay --score-process auto`` scores a long drive in a process of its own only when a
core is free for it beside the replay's own (``bench/bench_replay_e2e.py``: with another
replay on the 2 cores, a scoring process makes the command slower, on a quiet machine faster).

The watch reads the CPUs this process may run on from ``/proc/stat`` (busy and total ticks) and
its own CPU time (``os.times``) at its start and when asked; the other jobs' load is the busy
time of those CPUs less this process's own, per second of the interval. Where ``/proc/stat``
cannot be read (not Linux), nothing is known (``None``).
"""

from __future__ import annotations

import os
import time

#: ``/proc/stat`` columns counted as not busy: idle and iowait
_IDLE_COLUMNS = (3, 4)


def usable_cpus() -> set[int]:
    """The CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return set(os.sched_getaffinity(0))
    return set(range(os.cpu_count() or 1))


def _busy_seconds(cpus: set[int], stat: str = "/proc/stat") -> float | None:
    """Busy CPU seconds of ``cpus`` since boot (``None``: not readable)."""
    try:
        with open(stat) as f:
            lines = f.read().splitlines()
        tick = os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError):
        return None
    busy = 0
    seen = 0
    for line in lines:
        name, _, rest = line.partition(" ")
        if not (name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cpus):
            continue
        values = [int(v) for v in rest.split()[:8]]
        busy += sum(v for i, v in enumerate(values) if i not in _IDLE_COLUMNS)
        seen += 1
    return busy / tick if seen else None


def _own_seconds() -> float:
    t = os.times()
    return t.user + t.system


class CpuWatch:
    """Started at construction; :meth:`spare_cores` says how many of this process's CPUs the other
    jobs left free since then, beside ``keep`` cores this process uses itself.
    """

    def __init__(self, stat: str = "/proc/stat") -> None:
        self._stat = stat
        self.cpus = usable_cpus()
        self._wall = time.monotonic()
        self._busy = _busy_seconds(self.cpus, stat)
        self._own = _own_seconds()

    def others_cores(self) -> float | None:
        """Cores the other jobs kept busy since the start, on average (``None``: unknown, or
        under 0.2 s since the start: too few ticks to tell).
        """
        wall = time.monotonic() - self._wall
        busy = _busy_seconds(self.cpus, self._stat)
        if busy is None or self._busy is None or wall < 0.2:
            return None
        return max(0.0, (busy - self._busy - (_own_seconds() - self._own)) / wall)

    def spare_cores(self, keep: float = 1.0) -> float | None:
        """Cores left free beside the other jobs and ``keep`` cores of this process's own
        (``None``: unknown, see :meth:`others_cores`).
        """
        others = self.others_cores()
        return None if others is None else len(self.cpus) - keep - others


__all__ = ["CpuWatch", "usable_cpus"]
