"""The other jobs' load, as ``--score-process auto`` measures it (bags/replay/spare_cpu.py)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from bags.replay.spare_cpu import CpuWatch, usable_cpus


def _stat(path, busy_s: dict[int, float], idle_s: float = 100.0) -> None:
    """A /proc/stat of the usable CPUs: user ticks = busy seconds, the rest idle."""
    tick = os.sysconf("SC_CLK_TCK")
    lines = ["cpu  0 0 0 0 0 0 0 0 0 0"]
    lines += [f"cpu{c} {int(busy_s.get(c, 0.0) * tick)} 0 0 {int(idle_s * tick)} 0 0 0 0 0 0"
              for c in sorted(usable_cpus())]
    path.write_text("\n".join(lines + ["intr 0", "ctxt 0"]) + "\n")


def test_the_other_jobs_busy_time_per_second_is_their_load(tmp_path):
    stat = tmp_path / "stat"
    cpus = sorted(usable_cpus())
    _stat(stat, {c: 10.0 for c in cpus})
    watch = CpuWatch(str(stat))
    assert watch.others_cores() is None  # too soon to tell
    time.sleep(0.3)
    _stat(stat, {**{c: 10.0 for c in cpus}, cpus[0]: 10.0 + 0.3})  # one CPU busy the whole time
    others = watch.others_cores()
    assert others == pytest.approx(1.0, abs=0.35)  # this process's own time (the sleep: ~0) is not theirs
    # spare cores are the CPUs less ``keep`` less that load (the load read once: a second reading a
    # moment later differs by this process's own time in between, 0.054 cores once in a suite run)
    watch.others_cores = lambda: others
    assert watch.spare_cores() == pytest.approx(len(cpus) - 1 - others)
    assert watch.spare_cores(keep=0.0) == pytest.approx(len(cpus) - others)


def test_an_unreadable_stat_is_unknown(tmp_path):
    watch = CpuWatch(str(tmp_path / "missing"))
    time.sleep(0.25)
    assert watch.others_cores() is None and watch.spare_cores() is None


@pytest.mark.skipif(not os.path.exists("/proc/stat"), reason="Linux /proc")
def test_a_busy_process_beside_is_seen_and_this_process_own_work_is_not():
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.2)
        watch = CpuWatch()
        end = time.monotonic() + 0.6
        while time.monotonic() < end:  # this process busy too: its own time is not the others'
            sum(range(10000))
        others = watch.others_cores()
    finally:
        busy.kill()
        busy.wait()
    assert others is not None and others >= 0.5
