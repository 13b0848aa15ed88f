"""Benchmark: ``bev-bag replay`` throughput with IPM on a surround6 drive, vs real time.

Writes a synthetic surround6 drive (full-size 400x225 cameras, the standard 400x200 grid at
0.15 m, 10 Hz) unless ``--bag`` is given, then replays it end to end (read + synchronize +
decode + map + score + write the output bag, pictures and metrics) and prints frames/s and
the factor over the drive's own frame rate ("x real time").

    .venv/bin/python bench/bench_replay.py [--frames 30] [--bag BAG] [--no-pictures] [--keep DIR]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

from bench_rows import row, write_rows  # noqa: E402

from bags.cli.synth import SynthBagOptions, synth_bag  # noqa: E402
from bags.io.reader import BagReader  # noqa: E402
from bags.memory import keep_freed_memory  # noqa: E402
from bags.replay import ReplayOptions, replay  # noqa: E402
from bev_mapper_core.mapper import MapperConfig  # noqa: E402
from bev_mapper_core.synth.config import SynthConfig  # noqa: E402


def frame_rate(bag: Path) -> tuple[int, float]:
    """Frames (messages on the first camera's label topic) and their rate in Hz."""
    with BagReader(bag) as r:
        topic = f"/cameras/{r.camera_names[0]}/labels"
        stamps = [m.log_ns for m in r.messages([topic])]
    rate = (len(stamps) - 1) * 1e9 / (stamps[-1] - stamps[0]) if len(stamps) > 1 else float("nan")
    return len(stamps), rate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bag", type=Path, default=None, help="replay this bag instead of a synth one")
    ap.add_argument("--frames", type=int, default=30, help="frames of the synthetic drive")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--no-pictures", action="store_true")
    ap.add_argument("--frames-every", type=int, default=ReplayOptions.frames_every)
    ap.add_argument("--repeat", type=int, default=2, help="replays; the best is reported")
    ap.add_argument("--keep", type=Path, default=None, help="keep the outputs here")
    ap.add_argument("--json", default=None, help="also write the rows for bench/bench_table.py here")
    args = ap.parse_args()
    keep_freed_memory()  # as bev-bag replay does (bags/memory.py)
    tmp = Path(tempfile.mkdtemp(prefix="bench_replay_"))
    try:
        bag = args.bag
        if bag is None:
            bag = tmp / "drive"
            t0 = time.perf_counter()
            synth_bag(SynthBagOptions(out=bag, synth=SynthConfig(frames=args.frames, seed=args.seed)))
            print(f"synthetic surround6 drive: {args.frames} frames in {time.perf_counter() - t0:.1f} s")
        n, rate = frame_rate(bag)
        size = sum(p.stat().st_size for p in ([bag] if bag.is_file() else bag.rglob("*")))
        walls = []
        for i in range(args.repeat):
            out = tmp / f"out{i}"
            t0 = time.perf_counter()
            result = replay(ReplayOptions(bag=bag, out=out, mapper=MapperConfig(method="ipm"),
                                          pictures=not args.no_pictures,
                                          frames_every=args.frames_every))
            walls.append(time.perf_counter() - t0)
        m = result.metrics
        wall = min(walls)
        # marginal cost per frame: the same replay cut at a third, fixed costs cancel out
        few = max(1, m["frames"] // 3)
        t0 = time.perf_counter()
        replay(ReplayOptions(bag=bag, out=tmp / "few", max_frames=few, mapper=MapperConfig(method="ipm"),
                             pictures=not args.no_pictures, frames_every=args.frames_every))
        marginal = (wall - (time.perf_counter() - t0)) / (m["frames"] - few) if m["frames"] > few \
            else float("nan")
        fps = m["frames"] / wall
        # a difference of two runs: on a busy machine the shorter one can take longer
        steady = f"{1.0 / marginal / rate:.1f}x" if marginal > 0 else "not measurable in this run (noise)"
        # the reference, same run: frames read and decoded in turn, not ahead by the thread
        t0 = time.perf_counter()
        replay(ReplayOptions(bag=bag, out=tmp / "in_turn", mapper=MapperConfig(method="ipm"), pipeline=0,
                             pictures=not args.no_pictures, frames_every=args.frames_every))
        fps_in_turn = m["frames"] / (time.perf_counter() - t0)
        print(f"bag: {bag} ({size / 1e6:.1f} MB, {n} frames at {rate:.2f} Hz)")
        print(f"replay (ipm, pictures {'off' if args.no_pictures else f'every {args.frames_every}'}): "
              f"{m['frames']} frames in {wall:.2f} s (best of {args.repeat}: "
              f"{', '.join(f'{w:.2f}' for w in walls)})")
        print(f"throughput     : {fps:7.1f} frames/s = {1000.0 / fps:6.1f} ms/frame end to end")
        print(f"vs real time   : {fps / rate:7.1f}x real time (drive at {rate:.1f} Hz)")
        print(f"one thread     : {fps_in_turn:7.1f} frames/s = {fps_in_turn / rate:.1f}x real time (--pipeline 0, "
              f"same run): the pipeline is {fps / fps_in_turn:.2f}x")
        print(f"steady state   : {marginal * 1000.0:6.1f} ms/frame = {steady} real "
              f"time, without the fixed cost (opening the bag, IPM tables: "
              f"{wall - marginal * m['frames']:.2f} s)")
        lat = m["latency_ms"]
        print(f"mapping only   : p50 {lat['p50']} ms, p95 {lat['p95']} ms per frame "
              f"(the rest is reading, decoding, scoring and writing)")
        print(f"drivable IoU {m['classes']['drivable']['iou']:.3f}, mIoU {m['miou']:.3f}")
        write_rows(args.json, "bench_replay.py", [row(
            f"bev-bag replay, IPM, surround6 drive at {rate:.0f} Hz", f"{fps / rate:.1f}x real time ({fps:.1f} frames/s)",
            f"{fps_in_turn / rate:.1f}x real time (one thread, --pipeline 0)", fps / fps_in_turn,
            f"steady state {steady}; mapping p50 {lat['p50']} ms of {1000.0 / fps:.0f} ms a frame")])
        if args.keep:
            shutil.copytree(out, args.keep, dirs_exist_ok=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
