"""``bev-bag propose-mask BAG --out DIR``: propose each camera's ego-body mask from a drive.

Per camera, the pixels whose label (label images) and colour (RGB images; both where the bag
has both) never change over the drive's frames, cleaned and restricted to regions touching the
image's bottom or side border (:class:`~bev_mapper_core.geometry.ego_mask_proposal.StaticPixels`),
written as ``DIR/<camera>.png`` (255 = ego body), with ``DIR/<camera>_overlay.png`` (the mask in
red over the camera's last image) for a person to check. The printed summary gives the fraction
masked per camera and the flags that use the masks (``bev-bag replay --ego-mask``, the node's
``ego_mask.<camera>``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from bev_mapper_core.geometry.ego_mask_proposal import COLOUR_TOLERANCE, StaticPixels

from ..errors import BagContentError, BagError, BagExistsError
from ..io import topics as T
from ..io.reader import BagReader

HELP = "propose each camera's ego-body mask (pixels that never change over a drive), for a person to check"
#: fewer frames than this make a proposal the summary warns about
FEW_FRAMES = 30


def configure(p: argparse.ArgumentParser) -> None:
    """Arguments of ``bev-bag propose-mask``."""
    p.add_argument("bag", type=Path, help="input bag: rosbag2 directory, .mcap or .db3")
    p.add_argument("--out", type=Path, required=True, help="output directory of the mask PNGs")
    p.add_argument("--input", choices=("auto", "labels", "rgb"), default="auto",
                   help="which images to watch (auto: every kind the bag has; default %(default)s)")
    p.add_argument("--tolerance", type=int, default=COLOUR_TOLERANCE, metavar="N",
                   help="RGB: a pixel changed when a channel differs by more than N (default %(default)s)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="read at most N frames")
    p.add_argument("--force", action="store_true", help="replace existing masks in DIR")


def _kinds(reader: BagReader, wanted: str) -> tuple[bool, bool]:
    """(labels, rgb): which images to read."""
    have = {k for k in T.IMAGE_KINDS for cam in reader.camera_names if reader.image_topic(cam, k) in reader.topics}
    if wanted != "auto":
        if wanted not in have:
            raise BagContentError(f"the bag has no {wanted} images (it has: {sorted(have) or 'none'})")
        have = {wanted}
    if not have:
        raise BagContentError("the bag has no camera images")
    return "labels" in have, "rgb" in have


def run(args: argparse.Namespace) -> int:
    """Run ``bev-bag propose-mask``."""
    if args.max_frames is not None and args.max_frames < 1:
        raise BagError(f"--max-frames must be >= 1, got {args.max_frames}")
    if not 0 <= args.tolerance <= 255:
        raise BagError(f"--tolerance must be in [0, 255], got {args.tolerance}")
    out = Path(args.out)
    with BagReader(args.bag) as reader:
        cams = reader.camera_names
        existing = [out / f"{c}.png" for c in cams if (out / f"{c}.png").exists()]
        if existing and not args.force:
            raise BagExistsError(f"{existing[0]} exists (--force replaces it)")
        labels, rgb = _kinds(reader, args.input)
        watch = {c: StaticPixels(args.tolerance) for c in cams}
        last: dict[str, np.ndarray] = {}
        n = 0
        for frame in reader.frames(rgb=rgb, labels=labels, gt=False, odom=False):
            for c in cams:
                if frame.valid.get(c):
                    watch[c].add(frame.labels.get(c), frame.rgb.get(c))
                    last[c] = frame.rgb[c] if rgb else np.repeat((frame.labels[c] * 20)[..., None], 3, axis=2)  # grey ids
            n += 1
            if args.max_frames is not None and n >= args.max_frames:
                break
    out.mkdir(parents=True, exist_ok=True)
    kinds = " and ".join(k for k, on in (("label", labels), ("colour", rgb)) if on)
    print(f"ego-body masks proposed from {n} frame(s): pixels whose {kinds} never changed, touching the "
          f"image's bottom or sides")
    flags = []
    for c in cams:
        if watch[c].frames == 0:
            print(f"  {c}: no frame with an image: no mask")
            continue
        mask = watch[c].proposal(str(out / f"{c}.png"))
        cv2.imwrite(str(out / f"{c}.png"), mask.pixels.astype(np.uint8) * 255)
        overlay = last[c].copy()
        overlay[mask.pixels] = (overlay[mask.pixels] // 2 + np.array([127, 0, 0], np.uint8))
        cv2.imwrite(str(out / f"{c}_overlay.png"), cv2.cvtColor(overlay, cv2.COLOR_RGB2BGR))
        print(f"  {c}: {mask.fraction:6.1%} masked ({int(mask.pixels.sum())} px of {mask.size[0]}x{mask.size[1]}) "
              f"-> {out / f'{c}.png'}")
        if mask.pixels.any():
            flags.append(f"--ego-mask {c}={out / f'{c}.png'}")
    if n < FEW_FRAMES:
        print(f"warning: only {n} frame(s): pixels may look constant by chance (a drive of {FEW_FRAMES}+ frames "
              f"with turns is better)", file=sys.stderr)
    print("CHECK each proposal before use (the *_overlay.png files show it in red): a uniform road right in "
          "front of a vehicle that drove straight can look as constant as its hood; edit the PNGs as needed "
          "(255 = ego body, 0 = seen).")
    if flags:
        print("then: bev-bag replay BAG ... " + " ".join(flags) + "  (node: -p ego_mask.<camera>:=<png>)")
    return 0


__all__ = ["HELP", "configure", "run"]
