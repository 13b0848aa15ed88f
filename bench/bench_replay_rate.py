"""Benchmark: ``bev-bag replay``'s marginal rate (IPM, surround6 at 10 Hz) against real time and
against the replay before issue #28, measured in the same run.

Writes a synthetic surround6 drive (full-size 400x225 cameras, the standard 400x200 grid at
0.15 m, 10 Hz) unless ``--bag`` is given. The marginal cost of a frame is measured two ways: in
one run (``in-run``: the time from the first third of the whole drive's frames to its last, as
the mapper took them, over the frames between; the rows report it) and as the replay of the whole
drive less the replay of its first third (``all - few``; two runs, so it is noisier on a shared
machine); the process start, opening the bag and the IPM tables enter neither. Each repeat
replays four ways in turn, interleaved, so all see the same machine load
(``replay_reference.py``; the same outputs):

* ours: the scoring in a process of its own (``--score-process on``, what ``auto`` does for a
  drive of 100 frames or more on 2 cores or more);
* ``ours, one process``: the same, scored in the replay's own process (``--score-process off``);
* ``io before``: the reading and writing before #28's second part (every message read and
  deserialized by rosbags, every GT layer through ``occupancy_grid_to_layer``, every output
  message serialized by rosbags), with today's scoring;
* ``before #28``: that reading and writing and the scoring before #28 (whole-grid distance
  transforms, per-cell calibration sums, each frame scored twice).

The references score in the replay's process, as the replay did before #28.

The best of the repeats is reported. Every output is written: the output bag, the pictures
(every ``--frames-every``), ``report.html`` and ``metrics.json``.

``--stages`` also replays ours on one thread (``--pipeline 0 --score-process off``) with each stage timed, and prints
each stage's marginal cost per frame: where the time of a frame goes.

    .venv/bin/python bench/bench_replay_rate.py [--frames 120] [--repeat 3] [--bag BAG] [--stages]
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

from bench_replay import frame_rate  # noqa: E402
from bench_rows import row, write_rows  # noqa: E402
from replay_reference import reference_io, reference_scoring  # noqa: E402

from bags.cli.synth import SynthBagOptions, synth_bag  # noqa: E402
from bags.memory import keep_freed_memory  # noqa: E402
from bags.replay import ReplayOptions, replay  # noqa: E402
from bev_mapper_core.mapper import MapperConfig  # noqa: E402
from bev_mapper_core.synth.config import SynthConfig  # noqa: E402


class _FrameClock:
    """A replay's progress bar that notes when each frame was mapped."""

    def __init__(self, total) -> None:
        del total
        self.times: list[float] = []

    def update(self, n: int) -> None:
        """``n`` more frames mapped now."""
        self.times.extend([time.perf_counter()] * n)

    def close(self) -> None:
        """Nothing to close."""


def timed_replay(bag: Path, out: Path, frames: int | None, frames_every: int,
                 pipeline: int = 4, score_process: str = "on") -> tuple[float, int, list[float]]:
    """Wall seconds of one replay (IPM, all outputs), the frames it mapped and when each was mapped."""
    shutil.rmtree(out, ignore_errors=True)
    clock: list[_FrameClock] = []
    t0 = time.perf_counter()
    result = replay(ReplayOptions(bag=bag, out=out, mapper=MapperConfig(method="ipm"), max_frames=frames,
                                  frames_every=frames_every, pipeline=pipeline, score_process=score_process),
                    progress=lambda total: clock.append(_FrameClock(total)) or clock[0])
    return time.perf_counter() - t0, result.metrics["frames"], clock[0].times


def steady_ms(times: list[float]) -> float:
    """ms per frame from the end of the first third of a replay's frames to its last frame mapped:
    in one run, so the start and the load of other runs do not enter (with a pipeline its queues
    are full at both ends, so the mapper runs at the pace of the slowest stage)."""
    k = len(times) // 3
    return 1000.0 * (times[-1] - times[k]) / (len(times) - 1 - k)


def _stages() -> list[tuple[str, object, str]]:
    """``(label, owner, attribute)`` of each timed stage, outermost first."""
    import bags.io.reader.assembly as assembly  # noqa: PLC0415
    import bags.replay.mapping as mapping  # noqa: PLC0415
    import bags.replay.outputs as outputs  # noqa: PLC0415
    import bags.replay.scoring as scoring  # noqa: PLC0415
    from bev_mapper_core.metrics import MetricAccumulator, WholeGridAccumulator, accumulator  # noqa: PLC0415

    return [("read: frames built (layers, images, odometry)", assembly.FrameAssembler, "build"),
            ("map: IPM", mapping, "_map_frame"),
            ("score: ReplayScorer.update", scoring.ReplayScorer, "update"),
            ("  MetricAccumulator.update", MetricAccumulator, "update"),
            ("    of which Chamfer distances", accumulator, "_packed_chamfer_terms"),
            ("  WholeGridAccumulator.update", WholeGridAccumulator, "update"),
            ("write: grids and /bev/image", outputs, "write_frame_messages"),
            ("write: CameraInfo copied", outputs.InfoCopier, "upto"),
            ("pictures: drawn and PNG", outputs, "save_comparison")]


def stage_times(bag: Path, frames: int, frames_every: int, repeat: int) -> tuple[float, dict[str, float]]:
    """One-thread replays of ``bag`` and of its first third, each stage timed, ``repeat`` times: the
    marginal ms/frame of the whole and of each stage (in :func:`_stages` order), each from the
    best of the repeats."""
    spent: dict[str, float] = {}
    saved = []
    for label, owner, name in _stages():
        fn = getattr(owner, name)
        saved.append((owner, name, fn))
        key = label or "pictures: drawn and PNG"

        @functools.wraps(fn)
        def timed(*a, _fn=fn, _key=key, **k):
            t0 = time.perf_counter()
            try:
                return _fn(*a, **k)
            finally:
                spent[_key] = spent.get(_key, 0.0) + time.perf_counter() - t0
        setattr(owner, name, timed)
    best: dict[str, dict[str, float]] = {"all": {}, "few": {}}
    counts = {}
    try:
        for _ in range(repeat):
            for part, limit in (("all", None), ("few", max(1, frames // 3))):
                spent.clear()
                wall, counts[part], _ = timed_replay(bag, bag.parent / "stages", limit, frames_every, pipeline=0,
                                                     score_process="off")
                for k, v in {**spent, "total": wall}.items():
                    best[part][k] = min(best[part].get(k, float("inf")), v)
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)
    n = counts["all"] - counts["few"]
    order = ["total"] + list(dict.fromkeys(label or "pictures: drawn and PNG" for label, _, _ in _stages()))
    per = {k: 1000.0 * (best["all"][k] - best["few"].get(k, 0.0)) / n for k in order if k in best["all"]}
    return per.pop("total"), per
#: the replays of each repeat, in turn: name -> the swaps of replay_reference.py it runs under
#: ``(swaps, --score-process)``: ours scores in a process of its own (as ``auto`` does for a drive
#: of 100 frames or more on 2 cores; forced here, so that the first third is scored alike)
MODES = {"ours": ((), "on"), "ours, one process": ((), "off"), "io before": ((reference_io,), "off"),
         "before #28": ((reference_io, reference_scoring), "off")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bag", type=Path, default=None, help="replay this bag instead of a synth one")
    # 120: a drive long enough that --score-process auto scores it in a process of its own (100
    # frames or more), and 80 frames of marginal rate after the first third
    ap.add_argument("--frames", type=int, default=120, help="frames of the synthetic drive")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--rate-hz", type=float, default=10.0, help="the synthetic drive's frame rate")
    ap.add_argument("--frames-every", type=int, default=ReplayOptions.frames_every)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=None, help="also write the rows for bench/bench_table.py here")
    ap.add_argument("--stages", action="store_true", help="also time each stage on one thread")
    args = ap.parse_args()
    keep_freed_memory()  # as bev-bag replay does (bags/memory.py)
    tmp = Path(tempfile.mkdtemp(prefix="bench_replay_rate_"))
    try:
        bag = args.bag
        if bag is None:
            bag = tmp / "drive"
            synth_bag(SynthBagOptions(out=bag, synth=SynthConfig(frames=args.frames, seed=args.seed,
                                                                 rate_hz=args.rate_hz)))
        timed_replay(bag, tmp / "warm", 3, args.frames_every)  # imports, caches
        best: dict[str, dict[str, float]] = {m: {} for m in MODES}
        steady: dict[str, float] = {}
        n_all = n_few = 0
        for _ in range(args.repeat):
            for mode, (swaps, score_process) in MODES.items():
                for part in ("all", "few"):
                    limit = None if part == "all" else max(1, (n_all or args.frames) // 3)
                    with contextlib.ExitStack() as stack:
                        for swap in swaps:
                            stack.enter_context(swap())
                        wall, n, times = timed_replay(bag, tmp / f"{part}", limit, args.frames_every,
                                                      score_process=score_process)
                    if part == "all":
                        n_all = n
                        steady[mode] = min(steady.get(mode, float("inf")), steady_ms(times))
                    else:
                        n_few = n
                    best[mode][part] = min(best[mode].get(part, float("inf")), wall)
        rate = frame_rate(bag)[1]
        marginal = {m: 1000.0 * (b["all"] - b["few"]) / (n_all - n_few) for m, b in best.items()}
        print(f"drive: {n_all} frames at {rate:.1f} Hz, best of {args.repeat}, the ways interleaved; in-run = "
              f"frames {n_all // 3}..{n_all - 1} of the whole replay as they were mapped; (all - few) = replay of "
              f"all - replay of the first {n_few}, over {n_all - n_few} frames")
        for m in MODES:
            print(f"{m:17s}: in-run {steady[m]:6.1f} ms/frame = {1000.0 / steady[m] / rate:.1f}x real time; "
                  f"(all - few) {marginal[m]:6.1f} ms/frame = {1000.0 / marginal[m] / rate:.1f}x; "
                  f"whole replay {best[m]['all']:.2f} s")
        ms = steady
        if args.stages:
            total, per = stage_times(bag, n_all, args.frames_every, args.repeat)
            print(f"one thread (--pipeline 0), marginal: {total:.1f} ms/frame, of which (best of {args.repeat})")
            for label, ms_ in per.items():
                print(f"  {label:48s} {ms_:6.2f} ms")
            timed_stages = sum(v for k, v in per.items() if not k.startswith(" "))
            print(f"  {'the rest (reading the bag, synchronizing, ...)':48s} {total - timed_stages:6.2f} ms")
        note = (f"frames {n_all // 3}..{n_all - 1} of a {n_all}-frame replay as mapped, best of {args.repeat}; "
                f"all outputs, pictures every {args.frames_every}")
        path = f"bev-bag replay, IPM, surround6 drive at {rate:.0f} Hz, marginal rate"
        ours = f"{1000.0 / ms['ours'] / rate:.1f}x real time ({ms['ours']:.1f} ms/frame)"
        one = ms["ours, one process"]
        write_rows(args.json, "bench_replay_rate.py", [
            row(path, ours, f"{1000.0 / one / rate:.1f}x real time ({one:.1f} ms/frame; scored in the replay's "
                "own process, --score-process off)", one / ms["ours"], note),
            row(path, ours, f"{1000.0 / ms['io before'] / rate:.1f}x real time ({ms['io before']:.1f} ms/frame; "
                "reading and writing before #28's second part, same outputs)", ms["io before"] / ms["ours"], note),
            row(path, ours, f"{1000.0 / ms['before #28'] / rate:.1f}x real time ({ms['before #28']:.1f} ms/frame; "
                "reading, writing and scoring before #28, same outputs)", ms["before #28"] / ms["ours"], note)])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
