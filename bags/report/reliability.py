"""Reliability diagram of a replay: how often a class is present where the method says ``p``.

:func:`reliability_picture` draws the ``calibration`` part of ``metrics.json`` (see
:class:`~bev_mapper_core.metrics.WholeGridAccumulator`) as an RGB image with OpenCV: x is the
mean published probability of a bin (confidence), y the share of its cells where the class is
present (frequency), one line per class in its colour (:data:`~bev_mapper_core.labels.classes.CLASS_COLORS`),
a dot per non-empty bin whose area grows with the log of its cell count, and the diagonal of
perfect calibration. The legend gives each class's ECE. :func:`reliability_svg` draws the same
as inline SVG for ``report.html``.
"""

from __future__ import annotations

import math
from html import escape

import cv2
import numpy as np

from bev_mapper_core.display import STRIP_BG, STRIP_FG
from bev_mapper_core.labels.classes import CLASS_COLORS

_PLOT = 420  # plot side (px)
_LEFT, _TOP, _BOTTOM = 58, 34, 46  # margins (px)
_LEGEND = 230  # legend width (px)
_GRID = (215, 215, 215)
_AXIS = (90, 90, 90)
_GREY = (128, 128, 128)
_TEXT = (30, 30, 30)  # on the white plot


def _series(calibration: dict):
    """``(name, colour, [(confidence, frequency, count), ...], ece)`` per class with cells."""
    out = []
    for name, c in (calibration.get("classes") or {}).items():
        rel = c.get("reliability") or {}
        pts = [(x, y, n) for x, y, n in zip(rel.get("confidence", []), rel.get("frequency", []),
                                            rel.get("count", []))
               if n and x is not None and y is not None]
        if pts:
            out.append((name, CLASS_COLORS.get(name, _GREY), pts, c.get("ece")))
    return out


def _radius(n: int) -> int:
    return int(round(2 + 1.2 * math.log10(max(n, 1))))


def reliability_picture(calibration: dict, title: str = "") -> np.ndarray:
    """The reliability diagram of ``calibration`` (a ``metrics.json`` ``calibration`` dict) as an
    ``(H, W, 3)`` uint8 RGB image.
    """
    h = _TOP + _PLOT + _BOTTOM
    w = _LEFT + _PLOT + 16 + _LEGEND
    img = np.full((h, w, 3), 255, np.uint8)
    x0, y0 = _LEFT, _TOP + _PLOT  # plot origin (p = 0, frequency = 0)

    def px(x: float, y: float) -> tuple[int, int]:
        return int(round(x0 + x * _PLOT)), int(round(y0 - y * _PLOT))

    font = cv2.FONT_HERSHEY_SIMPLEX
    for i in range(11):
        v = i / 10
        cv2.line(img, px(v, 0), px(v, 1), _GRID, 1)
        cv2.line(img, px(0, v), px(1, v), _GRID, 1)
        if i % 2 == 0:
            cv2.putText(img, f"{v:.1f}", (px(v, 0)[0] - 10, y0 + 16), font, 0.4, _AXIS, 1, cv2.LINE_AA)
            cv2.putText(img, f"{v:.1f}", (x0 - 30, px(0, v)[1] + 4), font, 0.4, _AXIS, 1, cv2.LINE_AA)
    cv2.rectangle(img, px(0, 1), px(1, 0), _AXIS, 1)
    for k in range(0, _PLOT, 8):  # dashed diagonal: perfect calibration
        a, b = k / _PLOT, min(k + 4, _PLOT) / _PLOT
        cv2.line(img, px(a, a), px(b, b), _AXIS, 1, cv2.LINE_AA)
    cv2.putText(img, "published probability (bin mean)", (x0 + 90, h - 10), font, 0.45, _TEXT, 1,
                cv2.LINE_AA)
    label = np.full((18, 240, 3), 255, np.uint8)
    cv2.putText(label, "frequency of the class", (4, 13), font, 0.45, _TEXT, 1, cv2.LINE_AA)
    rot = np.ascontiguousarray(np.rot90(label))  # (240, 18, 3) reading upwards
    top = _TOP + (_PLOT - rot.shape[0]) // 2
    img[top:top + rot.shape[0], 2:2 + rot.shape[1]] = rot
    bins = calibration.get("bins")
    head = f"reliability on visible cells, {bins} bins" + (f" - {title}" if title else "")
    cv2.putText(img, head, (x0, 20), font, 0.5, _TEXT, 1, cv2.LINE_AA)

    series = _series(calibration)
    for _, color, pts, _ in series:
        poly = np.array([px(x, y) for x, y, _ in pts], np.int32)
        cv2.polylines(img, [poly], False, color, 2, cv2.LINE_AA)
        for (_, _, n), p in zip(pts, poly):
            cv2.circle(img, tuple(int(v) for v in p), _radius(n), color, -1, cv2.LINE_AA)
    lx = x0 + _PLOT + 16
    img[:, lx - 4:] = STRIP_BG
    cv2.putText(img, "class        ECE %", (lx, _TOP + 4), font, 0.45, STRIP_FG, 1, cv2.LINE_AA)
    for i, (name, color, _, ece) in enumerate(series):
        y = _TOP + 26 + 20 * i
        cv2.rectangle(img, (lx, y - 10), (lx + 12, y + 2), color, -1)
        cv2.putText(img, name, (lx + 18, y), font, 0.45, STRIP_FG, 1, cv2.LINE_AA)
        text = "-" if ece is None else f"{100 * ece:.2f}"
        cv2.putText(img, text, (lx + 170, y), font, 0.45, STRIP_FG, 1, cv2.LINE_AA)
    mean = calibration.get("mean_ece")
    y = _TOP + 26 + 20 * len(series) + 8
    cv2.putText(img, f"mean         {'-' if mean is None else f'{100 * mean:.2f}'}", (lx, y), font,
                0.45, STRIP_FG, 1, cv2.LINE_AA)
    cv2.putText(img, "dot area ~ log(cells)", (lx, y + 24), font, 0.4, STRIP_FG, 1, cv2.LINE_AA)
    return img


def reliability_svg(calibration: dict, size: int = 320) -> str:
    """The same diagram as an inline ``<svg>`` element (no legend: the report's table names the
    classes and their ECE).
    """
    m = 36  # margin (px)
    side = size - 2 * m

    def pt(x: float, y: float) -> str:
        return f"{m + x * side:.1f},{m + (1 - y) * side:.1f}"

    out = [f'<svg width="{size}" height="{size}" viewBox="0 0 {size} {size}" role="img">']
    for i in range(0, 11, 2):
        v = i / 10
        out.append(f'<line x1="{m + v * side:.1f}" y1="{m}" x2="{m + v * side:.1f}" y2="{m + side}" '
                   'stroke="#ddd"/>')
        out.append(f'<line x1="{m}" y1="{m + (1 - v) * side:.1f}" x2="{m + side}" '
                   f'y2="{m + (1 - v) * side:.1f}" stroke="#ddd"/>')
        out.append(f'<text x="{m + v * side:.1f}" y="{m + side + 14}" text-anchor="middle" '
                   f'font-family="sans-serif" font-size="10">{v:.1f}</text>')
        out.append(f'<text x="{m - 4}" y="{m + (1 - v) * side + 3:.1f}" text-anchor="end" '
                   f'font-family="sans-serif" font-size="10">{v:.1f}</text>')
    out.append(f'<polyline points="{pt(0, 0)} {pt(1, 1)}" fill="none" stroke="#555" '
               'stroke-dasharray="4 4"/>')
    for name, color, pts, _ in _series(calibration):
        rgb = "rgb({},{},{})".format(*color)
        out.append(f'<polyline points="{" ".join(pt(x, y) for x, y, _ in pts)}" fill="none" '
                   f'stroke="{rgb}" stroke-width="2"><title>{escape(name)}</title></polyline>')
        for x, y, n in pts:
            cx, cy = pt(x, y).split(",")
            out.append(f'<circle cx="{cx}" cy="{cy}" r="{_radius(n)}" fill="{rgb}">'
                       f'<title>{escape(name)}: p {x:.3f}, frequency {y:.3f}, {n} cells</title></circle>')
    out.append(f'<text x="{m + side / 2}" y="{size - 4}" text-anchor="middle" font-family="sans-serif" '
               'font-size="11">published probability</text>')
    out.append(f'<text x="11" y="{m + side / 2}" transform="rotate(-90 11 {m + side / 2})" '
               'text-anchor="middle" font-family="sans-serif" font-size="11">frequency</text>')
    out.append("</svg>")
    return "".join(out)
