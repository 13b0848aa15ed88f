r"""Pictures of real frames for the README: CamVid test image | the shipped segmenter's labels |
the BEV map ``segipm`` makes of that one image; with ``--methods``, CamVid test image | the BEV
map of each method named (``segipm``, the learned monocular ``s2g2`` and ``focusbev``).

    .venv/bin/python experiments/real_frames.py --camvid /work/data/camvid \
        [--frames Seq05VD_f04350 Seq05VD_f01800] [--segmenter FILE] [--out docs/images/real_camvid.png]
    .venv/bin/python experiments/real_frames.py --camvid /work/data/camvid --methods segipm,s2g2,focusbev \
        [--s2g2-weights FILE] [--focusbev-weights FILE] [--out docs/images/real_camvid_methods.png]

Each frame is one row: the 480x360 RGB image, the labels of the shipped segmenter
(``bev_mapper_core/weights/segmenter.safetensors``, or ``--segmenter``) blended over it
(``overlay_labels``, as ``bev-bag segment`` writes them), and the BEV picture of ``segipm``
(that segmenter + IPM with occlusion reasoning, ``SegIpmMapper``) on the ``ahead`` grid (32 m x
32 m ahead at 0.25 m, 2 px per cell), drawn by the package's BEV painter (the replay pictures'
colours, legend, ego and scale bar). A band at the bottom names the label colours of the middle
column (``LABEL_COLORS``; the BEV uses the colour-blind-safe BEV class colours of its legend).

CamVid has no calibration in the version used here (the SegNet tutorial's 480x360 frames), so
the BEV uses an assumed mounting, :func:`assumed_rig`: the ``front1`` preset's camera (nuScenes
CAM_FRONT: 1.51 m above the ground, level, 64.6 degrees across) with its intrinsics scaled to 480
px wide (square pixels) and its principal point at the centre of the 360 px height. The BEV
column is qualitative. :data:`CAPTION` is the caption (also in ``docs/images/ATTRIBUTION.md``).

The default frames, picked by hand for their content: ``Seq05VD_f04350`` (parked cars and cars
ahead, pedestrians on the pavement; among the most car + pedestrian + pavement pixels of the
test annotation) and ``Seq05VD_f01800`` (the most pavement of the test annotation). The dusk
sequence (``0001TP_*``) segments well too, but its frames have cars and pedestrians close
ahead, so occlusion reasoning leaves most of their BEV unknown beyond 5-10 m.

**The methods picture** (``--methods``, :func:`compose_methods`, caption :data:`METHODS_CAPTION`).
S2G2 and FocusBEV are trained for the ``front1`` rig (one 400x225, 16:9 camera) and load only
for it, so every method there maps the frame as a ``front1`` frame (:func:`front1_frame`): the
centred 16:9 crop of the 480x360 CamVid frame (480x270, the middle rows: the crop of
``training/real_unlabeled.crop_to_aspect``) resized to 400x225 with the models' resize. The
assumed mounting is then ``front1``'s camera itself (1.51 m high, level, 64.6 degrees across),
the same for all columns: ``segipm`` runs on the same 400x225 frame and camera there (not on
the full frame of :func:`assumed_rig`), so the columns differ only by method. FocusBEV maps
each frame alone (no stamp, no pose: its memory holds nothing). The learned methods run on
torch (``backend="torch"``, the reference runtime) with ``--s2g2-weights`` /
``--focusbev-weights`` or the shipped files. One BEV legend for all the columns (the methods
share the class colours) and a band naming the assumption.

The picture is an 8-bit palette PNG (:func:`palette_png`: the flat colours exact, 256 colours
in all; about 340 kB instead of 1 MB). CamVid (Brostow et al.) is CC BY-NC 4.0; only the derived
picture is committed, never dataset files (``docs/images/ATTRIBUTION.md``).
"""

from __future__ import annotations

import argparse
import hashlib
import struct
import zlib
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import torch

from bev_mapper_core.display import STRIP_BG, STRIP_FG, painter, put_text, text_size
from bev_mapper_core.errors import BevMapperError
from bev_mapper_core.geometry.camera import CameraModel
from bev_mapper_core.geometry.grid import grid_preset
from bev_mapper_core.geometry.rig import Rig, preset_rig
from bev_mapper_core.labels.classes import (
    CLASS_COLORS,
    EMPTY_COLOR,
    LABEL_COLORS,
    UNKNOWN_COLORS,
    Label,
    overlay_labels,
    resolve_classes,
)
from bev_mapper_core.mapper import Mapper, MapperConfig, create_mapper
from bev_mapper_core.methods.segipm.mapper import SegIpmMapper
from bev_mapper_core.training.data import resize_rgb
from bev_mapper_core.training.real_unlabeled import crop_to_aspect

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_FRAMES = ("Seq05VD_f04350", "Seq05VD_f01800")
CAPTION = (
    "Real frames from the CamVid test split (Cambridge, 480x360; not trained on): the image, the "
    "shipped segmenter's labels over it, and the BEV map `segipm` (that segmenter + IPM) makes of "
    "that one image on the `ahead` grid (32 m x 32 m, forward up). CamVid has no calibration in "
    "this version, so the BEV uses an assumed front-camera mounting (the `front1` preset's camera, "
    "1.51 m high, scaled to 480 px wide) and is qualitative. Two frames picked for their content "
    "(cars and pedestrians; a wide pavement); written by `experiments/real_frames.py`."
)
#: the methods ``--methods`` can draw, in column order, and their column titles
METHODS = {"segipm": "BEV: segipm (segmenter + IPM)", "s2g2": "BEV: S2G2", "focusbev": "BEV: FocusBEV"}
#: the rig the methods picture maps every frame with (the learned methods' rig)
METHODS_RIG = "front1"
METHODS_CAPTION = (
    "Real frames from the CamVid test split (Cambridge; not trained on) mapped by each method: the "
    "image, then the BEV map `segipm` (the shipped segmenter + IPM), the learned monocular S2G2 and "
    "FocusBEV make of that one image on the `ahead` grid (32 m x 32 m, forward up). S2G2 and FocusBEV "
    "are trained for the `front1` camera (400x225, 16:9) on the synthetic town, so each 480x360 "
    "frame is centre-cropped to 16:9 (480x270, shown) and resized to 400x225, and all three methods "
    "map it as a `front1` frame: the assumed mounting is `front1`'s camera (1.51 m high, level, 64.6 "
    "degrees across), not CamVid's (uncalibrated here), so the maps are qualitative. FocusBEV maps "
    "each frame alone (no pose, empty memory). Written by `experiments/real_frames.py --methods`."
)
_BAND = 20  # height of the column titles and of the label legend rows (px)


def assumed_rig(width: int = 480, height: int = 360) -> Rig:
    """The ``front1`` rig with its camera seen at ``width x height``: the intrinsics scaled to
    ``width`` (square pixels, the same horizontal field of view) and the principal point moved
    to the image centre vertically (a 4:3 frame from the 16:9 camera's mounting).
    """
    rig = preset_rig("front1")
    cam = rig.cameras[0]
    w, _ = cam.model.image_size
    m = cam.model.scaled(width / w)
    K = m.K_array
    K[1, 2] = (height - 1) / 2.0
    model = CameraModel(K=K, D=m.D, distortion_model=m.distortion_model, width=width, height=height)
    return Rig("camvid_assumed_front", (replace(cam, model=model),))


def _title(width: int, text: str) -> np.ndarray:
    band = np.empty((_BAND, width, 3), np.uint8)
    band[:] = STRIP_BG
    put_text(band, text, 6, 14)
    return band


def label_legend(width: int) -> np.ndarray:
    """Bands naming the colour of every :class:`Label` (the middle column), wrapped to ``width``."""
    items = [(label.name.lower(), LABEL_COLORS[label]) for label in Label]
    rows: list[list[tuple[str, np.ndarray]]] = [[]]
    x = 6 + text_size("labels:")[0] + 10
    for name, color in items:
        w = 11 + 5 + text_size(name)[0] + 14
        if x + w > width and rows[-1]:
            rows.append([])
            x = 6
        rows[-1].append((name, color))
        x += w
    img = np.empty((_BAND * len(rows), width, 3), np.uint8)
    img[:] = STRIP_BG
    put_text(img, "labels:", 6, 14)
    for r, row in enumerate(rows):
        x = 6 + text_size("labels:")[0] + 10 if r == 0 else 6
        y = r * _BAND
        for name, color in row:
            img[y + 4:y + 15, x:x + 11] = color
            cv2.rectangle(img, (x - 1, y + 3), (x + 11, y + 15), (150, 150, 150), 1)
            put_text(img, name, x + 16, y + 14)
            x += 11 + 5 + text_size(name)[0] + 14
    return img


def frame_row(image: np.ndarray, mapper: SegIpmMapper, bev_scale: int = 2) -> np.ndarray:
    """One row: image | labels over it | BEV picture (padded to the image's height)."""
    labels = mapper.stage.segment({"front": image})["front"]
    pred = mapper.ipm.map({"front": labels})
    bev = painter(mapper.grid, tuple(resolve_classes(pred.classes)), bev_scale).picture(pred.probs, pred.known)
    h = max(image.shape[0], bev.shape[0])
    panel = np.empty((h, bev.shape[1], 3), np.uint8)
    panel[:] = STRIP_BG
    top = (h - bev.shape[0]) // 2
    panel[top:top + bev.shape[0]] = bev
    sep = np.full((h, 4, 3), STRIP_BG, np.uint8)
    return np.hstack([image, sep, overlay_labels(image, labels), sep, panel])


def compose(images: list[np.ndarray], mapper: SegIpmMapper) -> np.ndarray:
    """The picture: column titles, one row per image, the label legend."""
    rows = [frame_row(img, mapper) for img in images]
    width = rows[0].shape[1]
    w_img = images[0].shape[1]
    titles = _title(width, "")
    put_text(titles, "CamVid test image", 6, 14)
    put_text(titles, "labels (shipped segmenter)", w_img + 4 + 6, 14)
    put_text(titles, "BEV: segipm, assumed camera", 2 * (w_img + 4) + 6, 14)
    gap = np.full((4, width, 3), STRIP_BG, np.uint8)
    parts = [titles]
    for r in rows:
        parts += [r, gap]
    parts.append(label_legend(width))
    return np.vstack(parts)


def front1_frame(image: np.ndarray, rig: Rig) -> tuple[np.ndarray, np.ndarray]:
    """``(crop, frame)``: the centred crop of ``image`` ``(H, W, 3)`` to the aspect ratio of
    ``rig``'s one camera, and that crop resized to the camera's size (the models' resize): the
    frame the methods picture maps, as ``real_unlabeled`` makes real frames of a rig.
    """
    w, h = rig.cameras[0].model.image_size
    crop = np.ascontiguousarray(crop_to_aspect(image, w, h))
    return crop, resize_rgb(crop, (h, w))


def method_mappers(methods: list[str], weights: dict[str, str | None], segmenter: str = "auto",
                   threads: int = 2) -> dict[str, Mapper]:
    """Method name -> its mapper for the ``front1`` rig and the ``ahead`` grid, RGB input, torch;
    ``weights`` names the learned methods' files (None: the shipped one).

    Raises:
        BevMapperError: an unknown method, or weights that do not fit (the mapper's message).
    """
    rig, grid = preset_rig(METHODS_RIG), grid_preset("ahead")
    out = {}
    for m in methods:
        config = MapperConfig(method=m, input_kind="rgb", weights=weights.get(m), segmenter=segmenter,
                              threads=threads, backend="torch")
        out[m] = create_mapper(rig, grid, config)
    return out


def compose_methods(images: list[np.ndarray], mappers: dict[str, Mapper], bev_scale: int = 2) -> np.ndarray:
    """The methods picture: column titles; per image one row, its :func:`front1_frame` crop and
    each mapper's BEV map of that frame alone (no pose); one BEV legend at the right; a band naming
    the assumed camera.
    """
    first = next(iter(mappers.values()))
    rig, grid = first.rig, first.grid
    cam = rig.cameras[0].name
    classes = tuple(resolve_classes(first.class_names))
    paint = painter(grid, classes, bev_scale)
    sep = 4
    rows, w_img = [], 0
    for image in images:
        crop, frame = front1_frame(image, rig)
        panels = []
        for mapper in mappers.values():
            mapper.reset()  # FocusBEV: each frame alone
            pred = mapper.map({cam: frame})
            panels.append(painter(grid, tuple(resolve_classes(pred.classes)), bev_scale).paint(pred.probs, pred.known))
        h = max(crop.shape[0], *(p.shape[0] for p in panels))
        parts = []
        for p in [crop, *panels]:
            cell = np.full((h, p.shape[1], 3), STRIP_BG, np.uint8)
            top = (h - p.shape[0]) // 2
            cell[top:top + p.shape[0]] = p
            parts += [cell, np.full((h, sep, 3), STRIP_BG, np.uint8)]
        rows.append(np.hstack(parts))
        w_img = crop.shape[1]
    gap = np.full((sep, rows[0].shape[1], 3), STRIP_BG, np.uint8)
    body = np.vstack([part for r in rows for part in (r, gap)])
    legend = paint.legend(body.shape[0])
    body = np.vstack([body, np.full((legend.shape[0] - body.shape[0], body.shape[1], 3), STRIP_BG, np.uint8)])
    body = np.hstack([body, legend])
    width = body.shape[1]
    titles = _title(width, "")
    x = 6
    for title, step in [("CamVid test image, centre 16:9 crop", w_img), *((METHODS.get(m, m), paint.width)
                                                                       for m in mappers)]:
        put_text(titles, title, x, 14)
        x += step + sep
    camera = rig.cameras[0]
    (w, h), m = camera.model.image_size, camera.model
    fov = np.degrees(2 * np.arctan(m.width / 2 / m.K_array[0, 0]))
    band = _title(width, f"assumed mounting: the {rig.name} camera ({camera.ego_from_cam_array[2, 3]:.2f} m high, "
                         f"{fov:.1f} deg across); each crop resized to {w}x{h} and mapped alone by every "
                         "method; qualitative")
    return np.vstack([titles, body, band])


def fixed_colors() -> np.ndarray:
    """``(n, 3)`` uint8: the flat colours of the picture (label, BEV class, legend and band colours),
    kept exactly by :func:`palette_png`.
    """
    colors = [*LABEL_COLORS.tolist(), *CLASS_COLORS.values(), EMPTY_COLOR, *UNKNOWN_COLORS, STRIP_BG, STRIP_FG,
              (255, 255, 255), (150, 150, 150)]
    return np.unique(np.array(colors, np.uint8), axis=0)


def palette_png(picture: np.ndarray, colors: int = 256, seed: int = 0) -> bytes:
    """``picture`` (RGB uint8) as an 8-bit palette PNG: :func:`fixed_colors` plus the k-means
    colours of the rest (sampled pixels), every pixel its nearest palette colour, no dithering.
    A third of the size of the true-colour PNG for these photographs.
    """
    fixed = fixed_colors().astype(np.float32)
    px = picture.reshape(-1, 3).astype(np.float32)
    rng = np.random.default_rng(seed)
    sample = px[rng.choice(len(px), size=min(len(px), 60000), replace=False)]
    d_fixed = ((sample[:, None, :] - fixed[None]) ** 2).sum(-1).min(1)
    rest = sample[d_fixed > 0]  # the photographs' colours
    k = colors - len(fixed)
    cv2.setRNGSeed(seed)
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 0.5)
    _, _, centers = cv2.kmeans(rest, k, None, criteria, 1, cv2.KMEANS_PP_CENTERS)
    palette = np.vstack([fixed, np.clip(np.rint(centers), 0, 255)])
    p2 = (palette ** 2).sum(1)
    index = np.empty(len(px), np.uint8)
    for i in range(0, len(px), 65536):  # nearest palette colour, in chunks
        chunk = px[i:i + 65536]
        index[i:i + 65536] = np.argmin(p2[None] - 2.0 * chunk @ palette.T, axis=1)
    h, w = picture.shape[:2]
    raw = np.hstack([np.zeros((h, 1), np.uint8), index.reshape(h, w)]).tobytes()  # filter 0 per row

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", w, h, 8, 3, 0, 0, 0)  # 8-bit, colour type 3 (palette)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"PLTE", palette.astype(np.uint8).tobytes())
            + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))


def main(argv=None) -> int:
    """Command line entry (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--camvid", type=Path, required=True, help="the CamVid folder (test/ inside)")
    ap.add_argument("--frames", nargs="+", default=list(DEFAULT_FRAMES), help="test image stems, one row each")
    ap.add_argument("--segmenter", default="auto", help="segmenter file (auto: the shipped one)")
    ap.add_argument("--methods", default="",
                    help=f"comma-separated methods of the methods picture ({','.join(METHODS)}); "
                         "none: the labels picture")
    ap.add_argument("--s2g2-weights", default=None, help="S2G2 weights file (default: the shipped one)")
    ap.add_argument("--focusbev-weights", default=None, help="FocusBEV weights file (default: the shipped one)")
    ap.add_argument("--out", type=Path, default=None,
                    help="the picture (default: docs/images/real_camvid.png, with --methods real_camvid_methods.png)")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    methods = [m.strip() for m in a.methods.split(",") if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise SystemExit(f"error: --methods: unknown {unknown}; choose from {list(METHODS)}")
    if a.out is None:
        a.out = ROOT / "docs" / "images" / ("real_camvid_methods.png" if methods else "real_camvid.png")
    torch.set_num_threads(a.threads)
    images = []
    for stem in a.frames:
        bgr = cv2.imread(str(a.camvid / "test" / f"{stem}.png"), cv2.IMREAD_COLOR)
        if bgr is None:
            raise SystemExit(f"error: {a.camvid / 'test' / (stem + '.png')}: not a readable image")
        images.append(np.ascontiguousarray(bgr[..., ::-1]))
    h, w = images[0].shape[:2]
    if any(img.shape[:2] != (h, w) for img in images):
        raise SystemExit("error: the frames differ in size")
    if methods:
        weights = {"s2g2": a.s2g2_weights, "focusbev": a.focusbev_weights}
        try:
            mappers = method_mappers(methods, weights, a.segmenter, a.threads)
            picture = compose_methods(images, mappers)
        except (BevMapperError, OSError) as e:
            raise SystemExit(f"error: {e}") from None
        caption = METHODS_CAPTION
        for m, mapper in mappers.items():
            path = getattr(mapper, "weights_file", None)
            if path is not None:
                digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
                print(f"{m}: weights {path} (sha256 {digest}...)")
    else:
        config = MapperConfig(method="segipm", input_kind="rgb", segmenter=a.segmenter, threads=a.threads)
        mapper = SegIpmMapper(assumed_rig(w, h), grid_preset("ahead"), config)
        picture = compose(images, mapper)
        caption = CAPTION
    a.out.parent.mkdir(parents=True, exist_ok=True)
    buf = palette_png(picture)
    a.out.write_bytes(buf)
    print(f"wrote {a.out} ({picture.shape[1]}x{picture.shape[0]}, {len(buf) / 1024:.0f} kB)")
    print(f"caption: {caption}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
