"""Small synthetic bags for the bag tests: synthesize with ``bev-bag synth``, replay with IPM."""

from __future__ import annotations

import json
import pathlib

from bags.cli.main import main
from bags.replay import BAG_DIR, FRAMES_DIR, METRICS_FILE

#: The 40 m x 20 m grid at 0.25 m of the small test drives (160 x 80 cells).
SMALL_GRID_ARGS = ["--grid-x-min", "-20", "--grid-x-max", "20", "--grid-y-min", "-10",
                   "--grid-y-max", "10", "--grid-res", "0.25"]
#: Frames of the shared small drive (conftest's ``small_drive_*`` fixtures).
SMALL_DRIVE_FRAMES = 4


def synth_small(out: pathlib.Path, *, frames: int = SMALL_DRIVE_FRAMES, storage: str = "mcap",
                seed: int = 5, compressed: bool = False, extra: tuple = ()) -> pathlib.Path:
    """``bev-bag synth``: surround6 at half image scale on the small grid (``compressed``: its
    images as CompressedImage on ``<image topic>/compressed``; ``extra``: more arguments).
    """
    argv = ["synth", str(out), "--frames", str(frames), "--seed", str(seed), "--scale", "0.5",
            "--storage", storage, *SMALL_GRID_ARGS, *(["--compressed"] if compressed else []), *extra]
    assert main(argv) == 0
    return out


def rewrite_bag(src: pathlib.Path, dst: pathlib.Path, edit) -> pathlib.Path:
    """A copy of the bag ``src`` at ``dst`` (MCAP), each message as ``edit(topic, msgtype, cdr)``
    returns it: ``(topic, msgtype, cdr)`` to write (renamed, retyped or changed bytes), or ``None``
    to leave it out. Metadata and latched topics are kept.
    """
    from bags.io.reader import BagReader  # noqa: PLC0415
    from bags.io.writer import BagWriter  # noqa: PLC0415

    with BagReader(src) as r, BagWriter(dst) as w:
        for key, value in r.custom_data.items():
            w.set_custom_data(key, value)
        latched = r.latched_topics
        for m in r.messages(raw=True):
            out = edit(m.topic, m.msgtype, bytes(m.msg))
            if out is None:
                continue
            topic, msgtype, data = out
            w.add_topic(topic, msgtype, latched=m.topic in latched)
            w.write_raw(topic, data, m.log_ns)
    return dst


def replay_ipm(bag: pathlib.Path, out: pathlib.Path, *extra: str) -> int:
    """``bev-bag replay`` with IPM (no shipped weights fit the small grid)."""
    return main(["replay", str(bag), "--out", str(out), "--quiet", "--method", "ipm", *extra])


def replay_outputs(out: pathlib.Path):
    """A replay's outputs but its timings: ``(metrics.json, pictures, output bag files, the
    report up to its latency section)``, pictures and bag files as ``{name: bytes}``.
    """
    metrics = json.loads((out / METRICS_FILE).read_text())
    metrics.pop("latency_ms")
    metrics.pop("score_process")  # where the frames were scored (and the load then): not an output
    metrics.pop("bag")
    pictures = {p.name: p.read_bytes() for p in sorted((out / FRAMES_DIR).glob("*.png"))}
    bag = {p.name: p.read_bytes() for p in sorted((out / BAG_DIR).iterdir())}
    report = (out / "report.html").read_text().replace(str(out), "OUT")
    return metrics, pictures, bag, report[:report.index("<h2>Mapping latency</h2>")]  # then timings


def replay_scores(out: pathlib.Path) -> dict:
    """A replay's metrics.json without its timings and paths (two replays compare equal on it)."""
    m = json.loads((out / METRICS_FILE).read_text())
    for key in ("latency_ms", "score_process", "bag"):
        m.pop(key)
    return m
