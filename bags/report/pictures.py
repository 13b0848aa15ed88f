"""Pictures of replayed frames: prediction vs ground truth side by side, PNG and GIF output.

Layers are drawn by :class:`bev_mapper_core.display.BevPainter` (forward up, left on the
left; colours of :data:`~bev_mapper_core.labels.classes.CLASS_COLORS`, unknown cells hatched, the ego
footprint at the origin) beside a legend with the axes and a metres scale bar. The replay writes
the encoded pictures with :func:`bags.files.write_atomic`, so a reader never sees a half-written one.

GIFs use Pillow when it is installed, else OpenCV's GIF encoder (``cv2.imencodeanimation``,
OpenCV >= 4.12); without either, :func:`encode_gif` reports why and nothing is written.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence

import cv2
import numpy as np

from bev_mapper_core.display import STRIP_BG, STRIP_FG, painter
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.labels.classes import BevClass

from ..files import write_atomic

#: Pictures are upscaled (nearest) until the BEV panels are at least this many pixels tall.
MIN_PANEL_HEIGHT = 360
_BAND = 22  # header / footer text band height (px)
_GAP = 6  # between the panels (px)
_FRAME = (120, 120, 120)  # outline of the maps
#: Name of the hatch in the legend of replay pictures: unknown to the mapper, or not visible in
#: the ground truth (both panels hatch the cells the ground truth cannot see).
UNKNOWN_LABEL = "unknown / unseen"


def _text(img: np.ndarray, text: str, x: int, y: int, scale: float = 0.45) -> None:
    cv2.putText(img, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, STRIP_FG, 1, cv2.LINE_AA)


def _banded(panel: np.ndarray, title: str) -> np.ndarray:
    """``panel`` with a title band above it."""
    out = np.empty((panel.shape[0] + _BAND, panel.shape[1], 3), np.uint8)
    out[:_BAND] = STRIP_BG
    out[_BAND:] = panel
    _text(out, title, 4, _BAND - 7)
    return out


def panel_scale(grid: BevGrid) -> int:
    """Display pixels per cell of replay pictures (panels at least :data:`MIN_PANEL_HEIGHT`)."""
    return max(1, math.ceil(MIN_PANEL_HEIGHT / grid.width))


def panel_boxes(grid: BevGrid) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """Where :func:`comparison_picture` puts the prediction and ground-truth maps: two
    ``(x, y, width, height)`` pixel boxes.
    """
    scale = panel_scale(grid)
    w, h = grid.height * scale, grid.width * scale
    return (_GAP, _BAND, w, h), (w + 2 * _GAP, _BAND, w, h)


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
    ious: Mapping[str, float | None] | None = None,
) -> np.ndarray:
    """Prediction (left), ground truth (middle) and the legend (right), as one RGB uint8 image.

    Both panels hatch the cells the ground truth cannot see (``gt_mask`` False) the same way,
    and the prediction panel also hatches its own unknown cells: the two panels then show the
    same, scored, cells side by side (the ``bev_bag`` keeps the whole prediction). The legend
    (:meth:`~bev_mapper_core.display.BevPainter.legend`) names the class colours, with the
    frame's IoU per class when ``ious`` is given, and shows the ego, the axes and a scale bar.

    Args:
        grid: the grid of the layers.
        pred, pred_known: predicted probabilities ``(C, H, W)`` and known mask ``(H, W)``.
        pred_classes: the classes of ``pred``'s layers.
        gt: ground-truth layers ``(C', H, W)`` (bool or [0, 1]), or ``None`` (drawn as "no GT",
            all hatched).
        gt_mask: ``(H, W)`` cells where the GT is known (others hatched), or ``None``.
        gt_classes: the classes of ``gt``'s layers.
        method: shown in the prediction's title.
        caption: footer text (frame index, stamp, mIoU, ...).
        ious: class name -> this frame's IoU (None = undefined), shown in the legend.
    """
    scale = panel_scale(grid)
    (lx, _, w, _), (rx, _, _, _) = panel_boxes(grid)
    pp = painter(grid, tuple(pred_classes), scale)
    gp = painter(grid, tuple(gt_classes), scale)
    hidden = None if gt is None or gt_mask is None else ~np.asarray(gt_mask, bool)
    left = pp.paint(pred, pred_known, hidden)
    right = gp.unknown() if gt is None else gp.paint(np.asarray(gt, np.float32), gt_mask)
    left = _banded(left, f"prediction ({method})" if method else "prediction")
    right = _banded(right, "ground truth (visible cells)" if gt is not None else "no ground truth")
    h = left.shape[0]
    legend = pp.legend(h, ious=ious, unknown_label=UNKNOWN_LABEL,
                       header="frame IoU" if ious is not None else "legend")
    lh, lw = legend.shape[:2]
    out = np.empty((max(h, lh) + _BAND, rx + w + _GAP + lw, 3), np.uint8)
    out[:] = STRIP_BG
    for x, panel in ((lx, left), (rx, right)):
        out[:h, x:x + w] = panel
        # a frame around the map, so that hatched cells at its edge do not melt into the bands
        cv2.rectangle(out, (x - 1, _BAND - 1), (x + w, h), _FRAME, 1)
    out[:lh, rx + w + _GAP:] = legend
    if caption:
        _text(out, caption, 4, out.shape[0] - 7)
    return out


def save_comparison(path, *args, **kwargs) -> np.ndarray:
    """:func:`comparison_picture` of ``args`` and ``kwargs``, written to ``path`` as a PNG
    (:func:`bags.files.write_atomic`); returns the picture.
    """
    picture = comparison_picture(*args, **kwargs)
    write_atomic(path, encode_png(picture))
    return picture


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an RGB uint8 image."""
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR) if rgb.ndim == 3 and rgb.shape[2] == 3 else rgb[..., ::-1]  # ~10x a numpy copy
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(bgr))
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
