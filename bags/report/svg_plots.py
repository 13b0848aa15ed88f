"""Small inline-SVG charts for the replay report: grouped bars, a histogram, a line.

Plain strings, no plotting library and nothing fetched: each function returns one ``<svg>``
element sized in CSS pixels, its text escaped. Missing values (None / NaN) draw no bar or point.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from html import escape

_AXIS = "#555"
_GRID = "#ddd"
_FONT = 'font-family="sans-serif" font-size="11"'


def _finite(v) -> bool:
    return v is not None and math.isfinite(v)


def _nice_max(v: float) -> float:
    """The smallest 1, 2, 2.5 or 5 x 10^k at or above ``v`` (> 0)."""
    if not v > 0:
        return 1.0
    k = 10.0 ** math.floor(math.log10(v))
    return next(m * k for m in (1, 2, 2.5, 5, 10) if m * k >= v * (1 - 1e-9))


def _num(v: float) -> str:
    """A tick or marker value with a sensible number of decimals (no exponent)."""
    a = abs(v)
    return f"{v:.0f}" if a >= 100 else f"{v:.1f}" if a >= 10 else f"{v:.2f}"


def _rgb(color) -> str:
    return color if isinstance(color, str) else "rgb({},{},{})".format(*color)


def _frame(width, height, left, bottom, top, y_max, y_fmt, y_label) -> list[str]:
    """SVG opening, horizontal grid lines with y tick labels, and the y axis title."""
    ph = height - bottom - top
    out = [f'<svg width="{width}" height="{height}" '
           f'viewBox="0 0 {width} {height}" role="img">']
    for i in range(5):
        v = y_max * i / 4
        y = top + ph - ph * i / 4
        out.append(f'<line x1="{left}" y1="{y:.1f}" x2="{width - 8}" y2="{y:.1f}" '
                   f'stroke="{_GRID if i else _AXIS}"/>')
        out.append(f'<text x="{left - 4}" y="{y + 4:.1f}" text-anchor="end" {_FONT}>'
                   f'{escape(y_fmt(v))}</text>')
    out.append(f'<text x="12" y="{top + ph / 2:.1f}" transform="rotate(-90 12 {top + ph / 2:.1f})" '
               f'text-anchor="middle" {_FONT}>{escape(y_label)}</text>')
    return out


def bar_chart(groups: Sequence[str], series: Sequence[tuple[str, object, Sequence]], *,
              y_max: float | None = None, y_label: str = "", percent: bool = False,
              width: int = 640, height: int = 260, opacities: Sequence[float] | None = None) -> str:
    """Grouped vertical bars: one group per ``groups`` entry, one bar per series in each.

    Args:
        groups: group labels (x axis).
        series: ``(name, colour, values)``; ``colour`` is a CSS colour or RGB tuple, or a list
            of them (one per group); ``values`` one per group (None = no bar).
        y_max: top of the y axis (default: a round number above the largest value).
        y_label: y axis title.
        percent: values are fractions shown as percent.
        opacities: per series bar opacity (default 1).
    """
    values = [v for _, _, vs in series for v in vs if _finite(v)]
    if y_max is None:
        y_max = _nice_max(max(values, default=0.0))
    left, bottom, top = 48, 44, 10 + 16 * (len(series) > 1)
    pw, ph = width - left - 8, height - bottom - top

    def y_fmt(v):
        return f"{100 * v:.0f}%" if percent else f"{v:g}"

    out = _frame(width, height, left, bottom, top, y_max, y_fmt, y_label)
    gw = pw / max(1, len(groups))
    bw = gw * 0.8 / max(1, len(series))
    for gi, g in enumerate(groups):
        x0 = left + gi * gw + gw * 0.1
        for si, (name, color, vals) in enumerate(series):
            v = vals[gi]
            if not _finite(v):
                continue
            c = color[gi] if isinstance(color, list) else color
            h = ph * min(max(v, 0.0), y_max) / y_max
            op = opacities[si] if opacities else 1.0
            tip = escape(f"{g} {name}: {y_fmt(v)}")
            out.append(f'<rect x="{x0 + si * bw:.1f}" y="{top + ph - h:.1f}" '
                       f'width="{bw * 0.92:.1f}" height="{h:.1f}" fill="{_rgb(c)}" '
                       f'fill-opacity="{op}" stroke="#333" stroke-width="0.5">'
                       f'<title>{tip}</title></rect>')
        out.append(f'<text x="{left + gi * gw + gw / 2:.1f}" y="{top + ph + 14}" '
                   f'text-anchor="middle" {_FONT}>{escape(g)}</text>')
    if len(series) > 1:
        x = left
        for si, (name, color, _) in enumerate(series):
            c = color[0] if isinstance(color, list) else color
            op = opacities[si] if opacities else 1.0
            out.append(f'<rect x="{x}" y="2" width="10" height="10" fill="{_rgb(c)}" '
                       f'fill-opacity="{op}" stroke="#333" stroke-width="0.5"/>')
            out.append(f'<text x="{x + 14}" y="11" {_FONT}>{escape(name)}</text>')
            x += 24 + 7 * len(name)
    out.append("</svg>")
    return "\n".join(out)


def histogram(values: Sequence[float], *, bins: int = 20, x_label: str = "",
              markers: dict[str, float] | None = None, width: int = 640, height: int = 220) -> str:
    """Histogram of ``values`` with vertical marker lines (e.g. ``{"p50": 12.1}``)."""
    vals = [float(v) for v in values if _finite(v)]
    lo, hi = (min(vals), max(vals)) if vals else (0.0, 1.0)
    if hi <= lo:
        lo, hi = lo - 0.5, hi + 0.5
    step = (hi - lo) / bins
    counts = [0] * bins
    for v in vals:
        counts[min(bins - 1, int((v - lo) / step))] += 1
    y_max = 4 * math.ceil(max(counts, default=1) / 4)  # whole frames at every tick
    left, bottom, top = 48, 44, 10
    pw, ph = width - left - 24, height - bottom - top
    out = _frame(width, height, left, bottom, top, y_max, lambda v: f"{v:g}", "frames")
    bw = pw / bins
    for i, n in enumerate(counts):
        h = ph * n / y_max
        out.append(f'<rect x="{left + i * bw:.1f}" y="{top + ph - h:.1f}" width="{bw * 0.95:.1f}" '
                   f'height="{h:.1f}" fill="#0072B2"><title>{_num(lo + i * step)}-'
                   f'{_num(lo + (i + 1) * step)}: {n}</title></rect>')
    for i in range(0, bins + 1, max(1, bins // 5)):
        x = left + i * bw
        out.append(f'<text x="{x:.1f}" y="{top + ph + 14}" text-anchor="middle" {_FONT}>'
                   f'{_num(lo + i * step)}</text>')
    out.append(f'<text x="{left + pw / 2:.1f}" y="{height - 6}" text-anchor="middle" {_FONT}>'
               f'{escape(x_label)}</text>')
    for k, (name, v) in enumerate((markers or {}).items()):
        if not _finite(v):
            continue
        x = left + pw * (v - lo) / (hi - lo)
        out.append(f'<line x1="{x:.1f}" y1="{top}" x2="{x:.1f}" y2="{top + ph}" stroke="#D55E00" '
                   f'stroke-width="1.5" stroke-dasharray="4 3"/>')
        out.append(f'<text x="{x + 3:.1f}" y="{top + 12 + 12 * k}" {_FONT} fill="#D55E00">'
                   f'{escape(name)} {_num(v)}</text>')
    out.append("</svg>")
    return "\n".join(out)


def line_chart(xs: Sequence[float], ys: Sequence[float | None], *, x_label: str = "",
               y_label: str = "", percent: bool = False, width: int = 640,
               height: int = 220) -> str:
    """Points joined by a line (gaps where ``ys`` is None), y from 0 to 1 when ``percent``."""
    pts = [(float(x), float(y)) for x, y in zip(xs, ys) if _finite(y)]
    y_max = 1.0 if percent else _nice_max(max((y for _, y in pts), default=0.0))
    x_lo, x_hi = (min(xs), max(xs)) if len(xs) else (0.0, 1.0)
    if x_hi <= x_lo:
        x_lo, x_hi = x_lo - 0.5, x_hi + 0.5
    left, bottom, top = 48, 44, 10
    pw, ph = width - left - 24, height - bottom - top
    out = _frame(width, height, left, bottom, top, y_max,
                 (lambda v: f"{100 * v:.0f}%") if percent else (lambda v: f"{v:g}"), y_label)

    def px(x, y):
        return left + pw * (x - x_lo) / (x_hi - x_lo), top + ph - ph * min(y, y_max) / y_max

    path = " ".join(f"{'M' if i == 0 else 'L'}{px(x, y)[0]:.1f},{px(x, y)[1]:.1f}"
                    for i, (x, y) in enumerate(pts))
    if path:
        out.append(f'<path d="{path}" fill="none" stroke="#0072B2" stroke-width="1.5"/>')
    for x, y in pts:
        cx, cy = px(x, y)
        out.append(f'<circle cx="{cx:.1f}" cy="{cy:.1f}" r="2.5" fill="#0072B2">'
                   f'<title>{x:g}: {100 * y if percent else y:.1f}</title></circle>')
    ticks = [x_lo + (x_hi - x_lo) * i / 4 for i in range(5)]
    if all(float(x).is_integer() for x in xs):  # e.g. frame indices: whole, evenly spaced ticks
        step = max(1, math.ceil((x_hi - x_lo) / 4))
        ticks = list(range(math.ceil(x_lo), math.floor(x_hi) + 1, step))
    for x in ticks:
        out.append(f'<text x="{px(x, 0)[0]:.1f}" y="{top + ph + 14}" text-anchor="middle" {_FONT}>'
                   f'{x:.4g}</text>')
    out.append(f'<text x="{left + pw / 2:.1f}" y="{height - 6}" text-anchor="middle" {_FONT}>'
               f'{escape(x_label)}</text>')
    out.append("</svg>")
    return "\n".join(out)
