"""SIGTERM during ``bev-bag replay`` (issue #10, defect 8): it cleans up like Ctrl-C.

A real subprocess replays a bag long enough to still be running when its temporary output
directories appear (the readiness signal); SIGTERM then must end it with a non-zero status,
an ``error:`` line, no traceback and no ``.partial-<pid>`` directory left behind (SIGTERM's
default action killed the process and left both directories).
"""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys
import time
from pathlib import Path

import bag_damage as D
import pytest

from bags.io import topics as T
from bags.io.writer import BagWriter

pytestmark = [pytest.mark.slow]

pytest.importorskip("bev_mapper_core.synth")

REPEATS = 20  # 20 x 12 frames: seconds of replay with a picture per frame


def _shifted(msg, dt_ns: int):
    s = msg.header.stamp
    ns = s.sec * 1_000_000_000 + s.nanosec + dt_ns
    stamp = dataclasses.replace(s, sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    return dataclasses.replace(msg, header=dataclasses.replace(msg.header, stamp=stamp))


def long_bag(base: D.Base, dst: Path) -> Path:
    """The base drive played ``REPEATS`` times in a row, as one bag."""
    times = [ns for _, _, ns, _ in base.messages]
    period = max(times) - min(times) + 100_000_000
    with BagWriter(dst) as w:
        for topic, msgtype in base.types.items():
            w.add_topic(topic, msgtype, latched=topic in base.latched)
        for k in range(REPEATS):
            for topic, _, ns, msg in base.messages:
                if topic == T.TF_STATIC:
                    if k == 0:
                        w.write(topic, msg, ns)
                    continue
                w.write(topic, _shifted(msg, k * period), ns + k * period)
    return dst


def writing(out: Path) -> bool:
    """Readiness: both temporary output directories exist and frames are being written."""
    frames = list(out.glob(".frames.partial-*"))
    return bool(list(out.glob(".bev_bag.partial-*")) and frames
                and len(list(frames[0].glob("*.png"))) >= 2)


def test_sigterm_cleans_up_like_sigint(tmp_path):
    base = D.make_base(tmp_path / "base")
    bag = long_bag(base, tmp_path / "long")
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "bags.cli.main", "replay", str(bag), "--out", str(out), "--quiet",
         "--method", "ipm", "--picture-every", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not writing(out):
            assert proc.poll() is None, f"replay ended before writing: {proc.stderr.read()}"
            assert time.monotonic() < deadline, "replay never started writing"
            time.sleep(0.002)
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = proc.stderr.read()
    assert rc == 128 + signal.SIGTERM, err  # exited through main's handler, not killed
    assert "error: terminated" in err and "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == []  # no partials, no half outputs
