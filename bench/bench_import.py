"""``bev-bag import nuscenes`` at v1.0-mini's size: 10 scenes of 40 key frames, six 1600 x 900 JPEGs each
(about 2400 images, 12 distinct contents), a map with 2000 extra walkways and lane dividers; no
sweeps. Prints the key frames imported per second (target: >= 5 on 2 cores).

    .venv/bin/python bench/bench_import.py [--scenes 10] [--samples 40] [--keep DIR]
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
for p in (REPO, REPO / "tests"):  # the package of this checkout, the tests' miniature-dataset writer
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from nuscenes_helpers import write_nuscenes  # noqa: E402

from bags.cli.main import main  # noqa: E402


def run(scenes: int, samples: int, root: Path) -> float:
    """Write the dataset under ``root``, import it, return the key frames per second."""
    t0 = time.monotonic()
    data = write_nuscenes(root / "nus", scenes=scenes, samples=samples, sweeps=False, image_size=(1600, 900),
                          clutter=2000)
    size = sum(p.stat().st_size for p in (data / "samples").rglob("*.jpg"))
    print(f"dataset: {scenes} scenes x {samples} key frames, {size / 1e6:.0f} MB of JPEGs, "
          f"written in {time.monotonic() - t0:.1f} s")
    t0 = time.monotonic()
    status = main(["import", "nuscenes", str(data), "--version", "v1.0-mini", "--split", "all",
                   "--out", str(root / "bags")])
    dt = time.monotonic() - t0
    if status != 0:
        raise SystemExit(f"import failed with status {status}")
    rate = scenes * samples / dt
    print(f"import: {scenes * samples} key frames in {dt:.1f} s: {rate:.1f} key frames/s")
    return rate


def cli() -> None:
    """Command line (see the module docstring)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", type=int, default=10)
    p.add_argument("--samples", type=int, default=40)
    p.add_argument("--keep", type=Path, default=None, help="write into DIR and keep it")
    a = p.parse_args()
    if a.keep:
        a.keep.mkdir(parents=True, exist_ok=True)
        run(a.scenes, a.samples, a.keep)
        return
    tmp = Path(tempfile.mkdtemp(prefix="bench_import_"))
    try:
        run(a.scenes, a.samples, tmp)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    cli()
