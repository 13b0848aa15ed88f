"""``bev-bag segment IMAGE_OR_DIR ... --out DIR``: what the segmenter sees in your own images.

Each RGB image (PNG or JPEG) goes through the package's 2-D segmenter the way ``segipm`` runs it
(:class:`~bev_mapper_core.methods.segmenter.stage.SegmenterStage`: ``load_segmenter`` and
``Segmenter.segment``, on the CPU with :func:`~bev_mapper_core.nn.runtime.inference_threads`
threads). Outputs in ``OUT``, each written under a temporary name and renamed when complete
(:mod:`bags.files`):

* ``OUT/<stem>.png``: mono8 :class:`~bev_mapper_core.labels.classes.Label` ids, the image's size;
* ``OUT/overlay/<stem>.png``: the labels' colours (``LABEL_COLORS``) blended over the image;
* ``OUT/labels.json``: the legend, ``{"0": "unlabeled", "1": "road", ...}``.

Behaviour (also in ``--help``): see :data:`_EPILOG`.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bev_mapper_core.datasets.base import IMAGE_SUFFIXES
from bev_mapper_core.errors import InputError
from bev_mapper_core.labels.classes import Label, overlay_labels
from bev_mapper_core.mapper import MapperConfig
from bev_mapper_core.methods import METHODS
from msg_adapters import DEFAULT_LIMITS, EncodingError, check_image_size, compressed_image_header

from ..files import write_atomic

HELP = "segment RGB images (PNG/JPEG) with the package's segmenter: label PNGs, overlays, a legend"

#: Subfolder of OUT with the colour overlays (OUT itself holds only the label PNGs and the legend).
OVERLAY_DIR = "overlay"
#: The legend file in OUT: label id -> name.
LEGEND = "labels.json"

log = logging.getLogger(__name__)

_EPILOG = f"""\
inputs: image files (PNG or JPEG, judged by their content) and folders (their own
  {"/".join("*" + s for s in IMAGE_SUFFIXES)} files, not subfolders, sorted by name).
  8-bit RGB is used as is, RGBA without its alpha; an 8-bit grey image is repeated
  into R, G and B (what the mapper node does with a mono8 camera; the segmenter was
  trained on colour, so expect worse labels). 16-bit images are refused, and so is
  an image over {DEFAULT_LIMITS.max_image_side} px a side or {DEFAULT_LIMITS.max_image_pixels} pixels (8K UHD fits),
  from its header, before it is decoded.

outputs in DIR (each written under a temporary name and renamed when complete;
outputs of the same name from an earlier run are replaced, other files left):
  <stem>.png           mono8 label ids of this package's Label, the image's size
  {OVERLAY_DIR}/<stem>.png   the label colours blended (50 %) over the image
  {LEGEND}          the legend: {{"0": "unlabeled", "1": "road", ...}}

errors ('error: ...' naming the file, exit status 1):
  Checked before anything is written: every path exists, no two images share a
  stem (a.png and a.jpg would write the same a.png: rename one, or run them into
  two --out folders), no output would replace an input, every image's header
  (PNG or JPEG, size within the bounds above), the segmenter file.
  Found while decoding (corrupt data, 16-bit): the run stops at that image; the
  outputs of the images before it stay, complete (DIR and the legend are written
  with the first segmented image: a run that segments none writes nothing).
  --skip-bad: images that fail either check are skipped instead, listed and counted
  on stderr; the exit status is 0 if any image was segmented. Missing paths, shared
  stems and a bad segmenter file stay errors.
"""


@dataclass(frozen=True)
class _Job:
    """One input image and its outputs."""

    image: Path
    labels: Path
    overlay: Path


class _BadImage(InputError):
    """An input image that cannot be segmented (the message names the file)."""


def configure(p: argparse.ArgumentParser) -> None:
    """Arguments of ``bev-bag segment``."""
    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = _EPILOG
    p.add_argument("inputs", nargs="+", type=Path, metavar="IMAGE_OR_DIR",
                   help="PNG or JPEG images, or folders of them")
    p.add_argument("--out", type=Path, required=True, help="output directory (created if missing)")
    p.add_argument("--segmenter", default="auto", metavar="auto|camvid|open|FILE",
                   help=f"segmenter: auto (default) = camvid, the shipped {METHODS['segmenter'].weights[0]} "
                        "(trained with CamVid: non-commercial); open: the shipped one whose training data all "
                        "allow commercial use; or a weights file")
    p.add_argument("--skip-bad", action="store_true",
                   help="skip (and count) images that cannot be read instead of stopping at the first")


def list_inputs(inputs: list[Path]) -> list[Path]:
    """The image files of the command line's inputs, in order (each folder's sorted), each once.

    Raises:
        InputError: a missing path, or no image at all.
    """
    files: list[Path] = []
    for p in inputs:
        if p.is_dir():
            files += sorted(f for f in p.iterdir() if f.suffix.lower() in IMAGE_SUFFIXES and f.is_file())
        elif p.is_file():
            files.append(p)
        else:
            raise InputError(f"{p}: no such file or folder")
    seen, unique = set(), []
    for f in files:  # a file named twice (itself and through its folder) is segmented once
        key = f.resolve()
        if key not in seen:
            seen.add(key)
            unique.append(f)
    if not unique:
        raise InputError(f"no PNG or JPEG image in {' '.join(map(str, inputs))}")
    return unique


def plan(files: list[Path], out: Path) -> list[_Job]:
    """Each image's output paths.

    Raises:
        InputError: ``out`` is a file, two images of one stem (their outputs would collide), or an output that
            would replace an input image.
    """
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} exists and is not a folder")
    by_stem: dict[str, Path] = {}
    for f in files:
        if f.stem in by_stem:
            raise InputError(f"{by_stem[f.stem]} and {f} would both be written as {out / (f.stem + '.png')}; "
                             "rename one, or segment them into two --out folders")
        by_stem[f.stem] = f
    jobs = [_Job(f, out / f"{f.stem}.png", out / OVERLAY_DIR / f"{f.stem}.png") for f in files]
    inputs = {f.resolve() for f in files}
    for job in jobs:
        for target in (job.labels, job.overlay):
            if target.resolve() in inputs:
                raise InputError(f"{target} is an input image; choose another --out folder")
    return jobs


def check_header(path: Path, data: bytes | None = None) -> tuple[int, int]:
    """``(width, height)`` of a PNG or JPEG file from its header, within the size bounds.

    Raises:
        _BadImage: unreadable, neither PNG nor JPEG, truncated header, or too large.
    """
    try:
        data = path.read_bytes() if data is None else data
        header = compressed_image_header(data)
        check_image_size(header.width, header.height, f"{header.format.upper()} image", limits=DEFAULT_LIMITS)
    except OSError as e:
        raise _BadImage(f"{path}: cannot read ({e.strerror or e})") from None
    except EncodingError as e:
        raise _BadImage(f"{path}: {e}") from None
    return header.width, header.height


def read_image(path: Path) -> np.ndarray:
    """``(H, W, 3)`` uint8 RGB of a PNG or JPEG file (see the rules in ``--help``).

    Raises:
        _BadImage: unreadable, not PNG/JPEG, too large, corrupt, or not 8-bit.
    """
    import cv2  # noqa: PLC0415 - only this subcommand decodes image files

    try:
        data = path.read_bytes()
    except OSError as e:
        raise _BadImage(f"{path}: cannot read ({e.strerror or e})") from None
    w, h = check_header(path, data)  # the size is checked before anything is allocated
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise _BadImage(f"{path}: cannot decode ({str(e).strip().splitlines()[-1]})") from None
    if img is None:
        raise _BadImage(f"{path}: cannot decode (corrupt or truncated data)")
    if img.shape[:2] != (h, w):
        raise _BadImage(f"{path}: decoded to {img.shape[1]}x{img.shape[0]}, its header says {w}x{h}")
    if img.dtype != np.uint8:
        raise _BadImage(f"{path}: {img.dtype.itemsize * 8}-bit image; segment takes 8-bit RGB (convert it first)")
    if img.ndim == 2:
        log.warning("%s: grey image, repeated into R, G and B (the segmenter was trained on colour)", path)
        return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))
    if img.shape[2] not in (3, 4):
        raise _BadImage(f"{path}: {img.shape[2]} channels; segment takes RGB or RGBA")
    return np.ascontiguousarray(img[..., 2::-1])  # BGR(A) -> RGB


def legend() -> dict[str, str]:
    """``labels.json``: label id (as a string) -> name, every :class:`Label`."""
    return {str(int(label)): label.name.lower() for label in Label}


def _encode_png(arr: np.ndarray) -> bytes:
    import cv2  # noqa: PLC0415

    ok, buf = cv2.imencode(".png", arr if arr.ndim == 2 else arr[..., ::-1])  # RGB -> BGR
    if not ok:
        raise InputError(f"OpenCV could not encode a {arr.shape} PNG")
    return buf.tobytes()


def run(args: argparse.Namespace) -> int:
    """``bev-bag segment``; returns the exit status."""
    out: Path = args.out
    jobs = plan(list_inputs(args.inputs), out)
    skipped: list[str] = []
    good = []
    for job in jobs:  # headers first: nothing is written when one is bad (without --skip-bad)
        try:
            check_header(job.image)
            good.append(job)
        except _BadImage as e:
            if not args.skip_bad:
                raise
            skipped.append(str(e))
    # torch only now: bev-bag's parser (every subcommand's configure) must not import it
    from bev_mapper_core.methods.segmenter.stage import SegmenterStage, segmenter_path  # noqa: PLC0415
    from bev_mapper_core.nn.runtime import inference_device  # noqa: PLC0415

    config = MapperConfig(device="cpu", segmenter=args.segmenter)
    stage = SegmenterStage(segmenter_path(config, ""), inference_device(config))
    done = 0
    for job in good:
        try:
            image = read_image(job.image)
        except _BadImage as e:
            if not args.skip_bad:
                raise
            skipped.append(str(e))
            continue
        labels = stage.segment({"image": image})["image"]
        if not done:  # OUT is created with the first segmented image: a run that segments none writes nothing
            (out / OVERLAY_DIR).mkdir(parents=True, exist_ok=True)
        write_atomic(job.overlay, _encode_png(overlay_labels(image, labels)))
        write_atomic(job.labels, _encode_png(labels))  # the label PNG last: it marks the image done
        if not done:
            write_atomic(out / LEGEND, (json.dumps(legend(), indent=1) + "\n").encode())
        done += 1
    for reason in skipped:
        print(f"skipped: {reason}", file=sys.stderr)
    if skipped:
        print(f"skipped {len(skipped)} of {len(jobs)} images", file=sys.stderr)
    if not done:
        raise InputError(f"none of the {len(jobs)} images could be segmented")
    print(f"segmented {done} image(s) with {stage.path}: labels in {out}/, overlays in {out / OVERLAY_DIR}/, "
          f"legend {out / LEGEND}")
    return 0


__all__ = ["HELP", "LEGEND", "OVERLAY_DIR", "check_header", "configure", "legend", "list_inputs", "plan",
           "read_image", "run"]
