"""Write a PNG mosaic of a synthetic frame: camera RGB + label images and the GT BEV.

python -m bev_mapper_core.synth.preview --rig surround6 --seed 0 --frame 10 --out /tmp/x.png
"""

from __future__ import annotations

import argparse
import itertools

import cv2
import numpy as np

from ..geometry.grid import BevGrid
from ..geometry.rig import preset_rig
from ..labels.classes import colorize_labels, colorize_layers
from .config import SynthConfig
from .drive import DriveRenderer, SynthFrame
from .world import build_world


def mosaic(frame: SynthFrame, grid: BevGrid, per_row: int = 3) -> np.ndarray:
    """RGB mosaic ``(H, W, 3)`` uint8: per camera its RGB above its labels; the GT BEV (forward
    up, unseen cells darkened) on the right.
    """
    tiles = []
    for name, cam in frame.cameras.items():
        tile = np.concatenate([cam.rgb, colorize_labels(cam.labels)], axis=0).copy()
        cv2.putText(tile, name, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 0), 1)
        tiles.append(tile)
    th, tw = tiles[0].shape[:2]
    tiles = [cv2.resize(t, (tw, th), interpolation=cv2.INTER_NEAREST) for t in tiles]
    rows = []
    for chunk in itertools.zip_longest(*[iter(tiles)] * per_row, fillvalue=np.zeros_like(tiles[0])):
        rows.append(np.concatenate(chunk, axis=1))
    cams = np.concatenate(rows, axis=0)
    bev = colorize_layers(frame.gt.astype(np.float32))
    bev[~frame.visibility] = (bev[~frame.visibility] * 0.45).astype(np.uint8)
    bev = np.ascontiguousarray(grid.to_display(bev))
    scale = cams.shape[0] / bev.shape[0]
    bev = cv2.resize(bev, (int(round(bev.shape[1] * scale)), cams.shape[0]),
                     interpolation=cv2.INTER_NEAREST)
    c = bev.shape[1] // 2
    cv2.arrowedLine(bev, (c, bev.shape[0] // 2 + 12), (c, bev.shape[0] // 2 - 12), (0, 0, 0), 2)
    return np.concatenate([cams, bev], axis=1)


def main(argv=None) -> None:
    """CLI entry point."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rig", default="surround6")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frame", type=int, default=0, help="index of the frame to show")
    ap.add_argument("--out", default="/tmp/synth_preview.png")
    args = ap.parse_args(argv)
    rig, grid = preset_rig(args.rig), BevGrid()
    world = build_world(SynthConfig(frames=args.frame + 1, seed=args.seed))
    frame = DriveRenderer(world, rig, grid).frame(args.frame)
    img = mosaic(frame, grid)
    cv2.imwrite(args.out, cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    print(f"wrote {args.out} ({img.shape[1]}x{img.shape[0]})")


if __name__ == "__main__":
    main()
