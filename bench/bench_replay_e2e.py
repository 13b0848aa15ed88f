"""Benchmark: the whole ``bev-bag replay`` command, end to end, against real time (issue #41).

What a user waits for: the wall time of the command, from its start to its exit, with every
default output written (the output bag, the pictures, ``report.html``, ``reliability.png``,
``metrics.json``). Two drives of the same seed, a long one and a short one (default 300 and 30
frames of surround6 at 10 Hz, IPM); the **marginal** cost of a frame is

    (wall of the long drive - wall of the short drive) / (frames of the long - of the short)

so the interpreter's start, the imports and the tables enter neither side, while everything that
grows with the drive does (reading and checking the bag, mapping, scoring, writing, the report).
``x real time`` = the drive's frame period over that cost.

Each ``--score-process`` setting (``auto``, ``on``, ``off``) runs under each load (``--loads``:
``0`` = a quiet machine, ``K`` = K busy-looping processes beside it, i.e. other jobs on the
cores), interleaved: for every repeat, every load, every setting, the short drive then the long
one. The best of the repeats of each is reported, and what ``auto`` chose (its note in
``metrics.json``). ``auto`` should never be slower than one process (``off``) under any load.

    .venv/bin/python bench/bench_replay_e2e.py [--frames 300] [--short 30] [--repeat 2] [--loads 0 1 2]
    .venv/bin/python bench/bench_replay_e2e.py --bag LONG --short-bag SHORT   # your own drives

The per-stage table (where a frame's time goes, on one thread) is ``bench/bench_replay_rate.py --stages``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_replay import frame_rate  # noqa: E402
from bench_rows import machine, row, write_rows  # noqa: E402

from bags.cli.synth import SynthBagOptions, synth_bag  # noqa: E402
from bev_mapper_core.synth.config import SynthConfig  # noqa: E402

SETTINGS = ("auto", "on", "off")
#: the command, as a user runs it (the console script beside this interpreter)
BEV_BAG = [str(Path(sys.executable).with_name("bev-bag"))]


def timed_command(bag: Path, out: Path, setting: str, method: str) -> tuple[float, dict]:
    """Wall seconds of one whole ``bev-bag replay`` command and its ``metrics.json``."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [*BEV_BAG, "replay", str(bag), "--out", str(out), "--method", method, "--quiet",
           "--score-process", setting]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise SystemExit(f"error: {' '.join(cmd)} exited {done.returncode}: {done.stderr[-2000:]}")
    return wall, json.loads((out / "metrics.json").read_text())


class Load:
    """``k`` other jobs on the machine while in a ``with`` block: ``busy`` = processes that keep a
    core busy each; ``replay`` = ``bev-bag replay`` commands of ``bag`` (the long drive) in a loop, each with
    ``--score-process setting`` (a fleet evaluation running several replays at once).
    """

    def __init__(self, k: int, kind: str = "busy", bag: Path | None = None, setting: str = "auto",
                 method: str = "ipm", out: Path | None = None) -> None:
        self.k, self.kind, self.bag, self.setting, self.method, self.out = k, kind, bag, setting, method, out
        self.procs: list[subprocess.Popen] = []

    def __enter__(self) -> Load:
        for i in range(self.k):
            if self.kind == "busy":
                cmd = [sys.executable, "-c", "while True: pass"]
            else:
                out = self.out / f"load{i}"
                replay = " ".join([*BEV_BAG, "replay", str(self.bag), "--out", str(out), "--method", self.method,
                                   "--quiet", "--force", "--score-process", self.setting])
                cmd = ["bash", "-c", f"while true; do {replay} >/dev/null 2>&1; done"]
            self.procs.append(subprocess.Popen(cmd, start_new_session=True))
        time.sleep(1.0 if self.k else 0.0)
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            os.killpg(p.pid, signal.SIGKILL)  # the loop and the replay it runs
            p.wait()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bag", type=Path, default=None, help="the long drive (default: a synthetic one)")
    ap.add_argument("--short-bag", type=Path, default=None, help="the short drive (with --bag)")
    ap.add_argument("--frames", type=int, default=300, help="frames of the synthetic long drive")
    ap.add_argument("--short", type=int, default=30, help="frames of the synthetic short drive")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--method", default="ipm")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--loads", type=int, nargs="+", default=[0, 1, 2],
                    help="busy processes beside the replay (0 = quiet)")
    ap.add_argument("--load-kind", choices=("busy", "replay"), default="busy",
                    help="the other jobs: busy loops, or replays of the short drive in a loop with the same "
                         "--score-process (a fleet evaluation)")
    ap.add_argument("--settings", nargs="+", default=list(SETTINGS), choices=SETTINGS)
    ap.add_argument("--keep", type=Path, default=None, help="write the synthetic drives here and keep them")
    ap.add_argument("--json", default=None, help="also write the rows for bench/bench_table.py here")
    args = ap.parse_args()
    if (args.bag is None) != (args.short_bag is None):
        raise SystemExit("error: --bag and --short-bag go together")
    tmp = Path(tempfile.mkdtemp(prefix="bench_replay_e2e_"))
    try:
        long_bag, short_bag = args.bag, args.short_bag
        if long_bag is None:
            where = args.keep or tmp
            long_bag, short_bag = where / f"drive{args.frames}", where / f"drive{args.short}"
            for bag, n in ((long_bag, args.frames), (short_bag, args.short)):
                if not (bag / "metadata.yaml").exists():
                    shutil.rmtree(bag, ignore_errors=True)
                    synth_bag(SynthBagOptions(out=bag, synth=SynthConfig(frames=n, seed=args.seed)))
        rate = frame_rate(long_bag)[1]
        timed_command(short_bag, tmp / "warm", "off", args.method)  # the page cache, compiled bytecode
        best: dict[tuple[int, str], dict[str, float]] = {}
        frames: dict[str, int] = {}
        chose: dict[tuple[int, str], set] = {}
        for _ in range(args.repeat):
            for load in args.loads:
                for setting in args.settings:
                    with Load(load, args.load_kind, long_bag, setting, args.method, tmp):
                        for part, bag in (("short", short_bag), ("long", long_bag)):
                            wall, metrics = timed_command(bag, tmp / "out", setting, args.method)
                            key = (load, setting)
                            best.setdefault(key, {})[part] = min(best.get(key, {}).get(part, float("inf")), wall)
                            frames[part] = metrics["frames"]
                            if part == "long":
                                chose.setdefault(key, set()).add(metrics["score_process"]["ran"])
        n = frames["long"] - frames["short"]
        print(f"{machine()}; {args.method}, {frames['long']} - {frames['short']} frames at {rate:.1f} Hz, "
              f"best of {args.repeat}, interleaved; marginal = (wall long - wall short) / {n} frames")
        print(f"{'load':>4s}  {'--score-process':15s} {'short s':>8s} {'long s':>8s} {'ms/frame':>9s} "
              f"{'x real time':>11s}  ran as")
        rows = []
        for load in args.loads:
            ms = {}
            for setting in args.settings:
                b = best[(load, setting)]
                ms[setting] = 1000.0 * (b["long"] - b["short"]) / n
                print(f"{load:4d}  {setting:15s} {b['short']:8.2f} {b['long']:8.2f} {ms[setting]:9.2f} "
                      f"{1000.0 / ms[setting] / rate:10.1f}x  {'/'.join(sorted(chose[(load, setting)]))}")
            if "auto" in ms and "off" in ms:
                beside = "a quiet machine" if load == 0 else f"{load} {args.load_kind} job(s) beside"
                rows.append(row(
                    f"bev-bag replay, the whole command, {args.method}, surround6 at {rate:.0f} Hz, {beside}",
                    f"{1000.0 / ms['auto'] / rate:.1f}x real time ({ms['auto']:.1f} ms/frame, --score-process auto)",
                    f"{1000.0 / ms['off'] / rate:.1f}x real time ({ms['off']:.1f} ms/frame, one process)",
                    ms["off"] / ms["auto"],
                    f"marginal: (wall of {frames['long']} frames - of {frames['short']}) / {n}, best of {args.repeat}, "
                    "interleaved, every default output"))
        write_rows(args.json, "bench_replay_e2e", rows)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
