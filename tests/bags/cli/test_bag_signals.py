"""SIGTERM during ``bev-bag replay`` (issue #10, defect 8): it cleans up like Ctrl-C.

A real subprocess replays a bag long enough to still be running when its temporary output
directories appear (the readiness signal); SIGTERM then must end it with a non-zero status,
an ``error:`` line, no traceback and no ``.partial-<pid>`` directory left behind (SIGTERM's
default action killed the process and left both directories). ``bev-train`` shares that
handling (:mod:`bags.cli.dispatch`): SIGTERM while it renders its drives ends it the same way.
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
    """``msg`` with its header stamp (a TFMessage: each transform's) ``dt_ns`` later."""
    if not hasattr(msg, "header"):  # tf2_msgs/TFMessage (/tf)
        return dataclasses.replace(msg, transforms=[_shifted(t, dt_ns) for t in msg.transforms])
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


def sigterm_when_ready(argv: list[str], ready, what: str) -> str:
    """Run ``python -m ARGV``, send SIGTERM once ``ready()`` holds, and check that it ended
    through the command line's handler (status 143, ``error: terminated``, no traceback);
    returns its stderr. ``what`` names the readiness in the failure messages.
    """
    proc = subprocess.Popen([sys.executable, "-m", *argv], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not ready():
            assert proc.poll() is None, f"{argv[0]} ended before {what}: {proc.stderr.read()}"
            assert time.monotonic() < deadline, f"{argv[0]} never started {what}"
            time.sleep(0.002)
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    err = proc.stderr.read()
    assert rc == 128 + signal.SIGTERM, err  # exited through main's handler, not killed
    assert "error: terminated" in err and "Traceback" not in err
    return err


def test_sigterm_cleans_up_like_sigint(tmp_path):
    base = D.make_base(tmp_path / "base")
    bag = long_bag(base, tmp_path / "long")
    out = tmp_path / "out"
    sigterm_when_ready(["bags.cli.main", "replay", str(bag), "--out", str(out), "--quiet", "--method", "ipm",
                        "--picture-every", "1"], lambda: writing(out), "writing")
    assert sorted(p.name for p in out.iterdir()) == []  # no partials, no half outputs


def test_bev_train_ends_on_sigterm_like_bev_bag(tmp_path):
    """SIGTERM while ``bev-train`` renders its training drives: status 143, ``error: terminated``,
    no traceback, no half-written drive in the cache (the readiness signal: the first drive there).
    """
    pytest.importorskip("torch")
    cache = tmp_path / "cache"
    sigterm_when_ready(["bags.cli.train", "--rig", "cam2bev4", "--classes", "cam2bev", "--train-drives", "200",
                        "--frames-per-drive", "4", "--cache", str(cache), "--out", str(tmp_path / "run"),
                        "--threads", "1", "--no-progress"],
                       lambda: bool(list(cache.glob("*/drive_*.npz"))), "rendering drives")
    assert not list(cache.glob("*/*.tmp.npz"))  # the drive being written was removed
