"""The README's results table on the demo drive, generated: replays the demo drive as
``bash scripts/demo.sh`` does (``bev-bag replay data/demo_drive``), once per row, and renders
each run's mIoU, the vehicle area it claims in cells no camera sees and its vehicle CD_p from
the run's ``metrics.json``.

    .venv/bin/python experiments/demo_figures.py            # print the table (~1 min on 2 cores)
    .venv/bin/python experiments/demo_figures.py --readme   # ... and write it into README.md

The demo drive is generated first when it is missing, with the command of ``scripts/demo.sh``.
``tests/test_readme.py`` replays the same rows and checks the README's table against them.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys
import tempfile

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
BAG = ROOT / "data" / "demo_drive"
BEV_BAG = pathlib.Path(sys.executable).parent / "bev-bag"
#: the command of scripts/demo.sh that writes the demo drive (a test seed, never trained on)
SYNTH = ["synth", str(BAG), "--rig", "surround6", "--frames", "50", "--seed", "950000008", "--storage", "mcap"]
START, END = "<!-- demo-figures:begin (generated: experiments/demo_figures.py --readme) -->", "<!-- demo-figures:end -->"

#: (what runs, the flags of ``bash scripts/demo.sh`` / ``bev-bag replay``), in table order
ROWS = (
    ("Bi-Mapper, shipped weights (the default)", ()),
    ("IPM with occlusion reasoning", ("--method", "ipm")),
    ("IPM, classical", ("--method", "ipm", "--no-ipm-occlusion")),
)


def ensure_demo_drive() -> pathlib.Path:
    """The demo drive, written first (as ``scripts/demo.sh`` does) when it is missing."""
    if not (BAG / "metadata.yaml").is_file():
        subprocess.run([str(BEV_BAG), *SYNTH], cwd=ROOT, check=True, capture_output=True, text=True)
    return BAG


def replay(flags, out: pathlib.Path) -> dict:
    """``bev-bag replay`` of the demo drive with ``flags`` (no pictures, no report); its metrics."""
    cmd = [str(BEV_BAG), "replay", str(ensure_demo_drive()), "--out", str(out), "--force",
           "--no-pictures", "--no-report", *flags]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return json.loads((out / "metrics.json").read_text())


def row(label: str, flags, metrics: dict) -> str:
    """One table row from a run's ``metrics.json``."""
    vehicle = metrics["classes"]["vehicle"]
    hidden = metrics["occlusion"]["classes"]["vehicle"]
    command = " ".join(("bash scripts/demo.sh", *flags))
    return (f"| {label} | `{command}` | **{100 * metrics['miou']:.1f}** | {hidden['claim_m2_per_frame']:.1f} "
            f"({hidden['false_m2_per_frame']:.1f}) | {vehicle['cd_p']:.3f} |")


HEADER = ("| method | command | mIoU % | vehicle claimed where no camera sees, m²/frame (false) | vehicle CD_p, m |\n"
          "|---|---|---|---|---|")


def table(runs: list[dict]) -> str:
    """The markdown table of :data:`ROWS` from their runs' metrics (same order)."""
    return "\n".join([HEADER, *(row(label, flags, m) for (label, flags), m in zip(ROWS, runs))])


def measure() -> list[dict]:
    """Replay every row of :data:`ROWS`; their metrics, in order."""
    with tempfile.TemporaryDirectory(prefix="demo_figures_") as tmp:
        return [replay(flags, pathlib.Path(tmp) / str(k)) for k, (_, flags) in enumerate(ROWS)]


def readme_table(text: str) -> str | None:
    """The table between the README's markers (None without them)."""
    if START not in text or END not in text:
        return None
    return text.split(START, 1)[1].split(END, 1)[0].strip("\n")


def write_readme(tab: str) -> None:
    """Replace the text between the README's markers with ``tab``."""
    text = README.read_text()
    if readme_table(text) is None:
        raise SystemExit(f"error: {README} has no {START} ... {END} block")
    head, rest = text.split(START, 1)
    _, tail = rest.split(END, 1)
    README.write_text(f"{head}{START}\n{tab}\n{END}{tail}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--readme", action="store_true", help="write the table into README.md")
    args = ap.parse_args()
    tab = table(measure())
    print(tab)
    if args.readme:
        write_readme(tab)


if __name__ == "__main__":
    main()
