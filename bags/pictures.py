"""Pictures of replayed frames: prediction vs ground truth side by side, PNG and GIF output.

Layers are drawn with :func:`bev_mapper_core.classes.colorize_layers` and re-oriented with
:meth:`BevGrid.to_display` (forward up, left on the left). Files are written atomically:
:func:`write_atomic` writes a hidden temporary file next to the target and renames it, so a
reader never sees a half-written picture.

GIFs use Pillow when it is installed, else OpenCV's GIF encoder (``cv2.imencodeanimation``,
OpenCV >= 4.12); without either, :func:`encode_gif` reports why and nothing is written.
"""

from __future__ import annotations

import io
import math
import os
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from bev_mapper_core.classes import BevClass, bev_picture
from bev_mapper_core.grid import BevGrid

#: Pictures are upscaled (nearest) until the BEV panels are at least this many pixels tall.
MIN_PANEL_HEIGHT = 360
_BAND = 22  # header / footer text band height (px)
_GAP = 6  # between the panels (px)
_BG = (24, 24, 24)
_FG = (235, 235, 235)


def partial_name(path: Path) -> Path:
    """The hidden temporary name ``<dir>/.<name>.partial-<pid>`` used while writing ``path``."""
    return path.parent / f".{path.name}.partial-{os.getpid()}"


def write_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` via a temporary file and a rename (no half-written file)."""
    path = Path(path)
    tmp = partial_name(path)
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _text(img: np.ndarray, text: str, x: int, y: int, scale: float = 0.45) -> None:
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, _FG, 1, cv2.LINE_AA)


def _banded(panel: np.ndarray, title: str, factor: int) -> np.ndarray:
    """Upscale a panel by ``factor`` (nearest) and put a title band above it."""
    big = np.repeat(np.repeat(panel, factor, axis=0), factor, axis=1)
    out = np.empty((big.shape[0] + _BAND, big.shape[1], 3), np.uint8)
    out[:_BAND] = _BG
    out[_BAND:] = big
    _text(out, title, 4, _BAND - 7)
    return out


def comparison_picture(
    grid: BevGrid,
    pred: np.ndarray,
    pred_known: np.ndarray,
    pred_classes: Sequence[BevClass],
    gt: np.ndarray | None,
    gt_mask: np.ndarray | None,
    gt_classes: Sequence[BevClass],
    *,
    method: str = "",
    caption: str = "",
) -> np.ndarray:
    """Prediction (left) and ground truth (right) side by side, as one RGB uint8 image.

    Args:
        grid: the grid of the layers.
        pred, pred_known: predicted probabilities ``(C, H, W)`` and known mask ``(H, W)``.
        pred_classes: the classes of ``pred``'s layers.
        gt: ground-truth layers ``(C', H, W)`` (bool or [0, 1]), or ``None`` (drawn as "no GT").
        gt_mask: ``(H, W)`` cells where the GT is known (others drawn dark grey), or ``None``.
        gt_classes: the classes of ``gt``'s layers.
        method: shown in the prediction's title.
        caption: footer text (frame index, stamp, ...).
    """
    left = bev_picture(grid, pred, pred_classes, pred_known)
    if gt is None:
        right = np.full_like(left, 40)
    else:
        right = bev_picture(grid, np.asarray(gt, np.float32), gt_classes, gt_mask)
    factor = max(1, math.ceil(MIN_PANEL_HEIGHT / left.shape[0]))
    left = _banded(left, f"prediction ({method})" if method else "prediction", factor)
    right = _banded(right, "ground truth (visible cells)" if gt is not None else "no ground truth",
                    factor)
    h, w = left.shape[:2]
    out = np.empty((h + _BAND, 2 * w + _GAP, 3), np.uint8)
    out[:] = _BG
    out[:h, :w] = left
    out[:h, w + _GAP:] = right
    if caption:
        _text(out, caption, 4, h + _BAND - 7)
    return out


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB uint8 image."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))  # RGB -> BGR
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def gif_backend() -> str | None:
    """``'pillow'``, ``'opencv'`` or ``None``: what :func:`encode_gif` would use."""
    try:
        import PIL.Image  # noqa: F401, PLC0415 - optional
        return "pillow"
    except ImportError:
        pass
    if hasattr(cv2, "imencodeanimation") and hasattr(cv2, "Animation"):
        return "opencv"
    return None


def encode_gif(frames: Sequence[np.ndarray], fps: float = 5.0) -> tuple[bytes | None, str]:
    """Animated GIF bytes of RGB frames (looping), and a note saying how (or why not).

    Returns ``(None, reason)`` when neither Pillow nor OpenCV's GIF encoder is available.
    """
    if not frames:
        return None, "no pictures to animate"
    duration_ms = max(20, int(round(1000.0 / fps)))
    backend = gif_backend()
    if backend == "pillow":
        from PIL import Image  # noqa: PLC0415

        images = [Image.fromarray(np.ascontiguousarray(f)) for f in frames]
        buf = io.BytesIO()
        images[0].save(buf, format="GIF", save_all=True, append_images=images[1:],
                       duration=duration_ms, loop=0)
        return buf.getvalue(), "GIF written with Pillow"
    if backend == "opencv":
        anim = cv2.Animation()
        anim.frames = [np.ascontiguousarray(f[..., ::-1]) for f in frames]  # RGB -> BGR
        anim.durations = [duration_ms] * len(frames)
        ok, buf = cv2.imencodeanimation(".gif", anim)
        if ok:
            return np.asarray(buf).tobytes(), "GIF written with OpenCV (Pillow is not installed)"
        return None, "OpenCV could not encode the GIF and Pillow is not installed; GIF skipped"
    return None, "neither Pillow nor an OpenCV GIF encoder is installed; GIF skipped"
