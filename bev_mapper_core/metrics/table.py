"""Readable text tables of the metrics documents."""

from __future__ import annotations

import math

from .whole_grid import ECE_BINS


# ------------------------------------------------------------------------------ formatting
def _fmt(value, scale: float = 1.0, digits: int = 1) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value * scale:.{digits}f}"


def format_table(result: dict) -> str:
    """Readable text table of a :meth:`MetricAccumulator.result` dict.

    IoU and precision are shown in percent, Chamfer distances in metres; ``-`` marks undefined
    values.
    """
    classes = result.get("classes", {})
    names = list(classes)
    width = max([len("class"), len("mIoU / mAP")] + [len(n) for n in names])
    lines = [f"BEV metrics over {result.get('frames', 0)} frame(s)"]
    header = f"{'class':<{width}}  {'IoU%':>6}  {'CD_p m':>7}  {'CD_L m':>7}  {'CD m':>7}  {'Prec%':>6}"
    lines += [header, "-" * len(header)]
    for name in names:
        m = classes[name]
        lines.append(
            f"{name:<{width}}  {_fmt(m.get('iou'), 100):>6}  {_fmt(m.get('cd_p'), 1, 3):>7}  "
            f"{_fmt(m.get('cd_l'), 1, 3):>7}  {_fmt(m.get('cd'), 1, 3):>7}  "
            f"{_fmt(m.get('precision'), 100):>6}"
        )
    lines.append("-" * len(header))
    lines.append(f"{'mIoU / mAP':<{width}}  {_fmt(result.get('miou'), 100):>6}  "
                 f"{'':>7}  {'':>7}  {'':>7}  {_fmt(result.get('map'), 100):>6}")

    by_range = result.get("iou_by_range") or {}
    if by_range:
        cols = names + ["miou"]
        colw = [max(6, len(c)) for c in cols]
        bandw = max([len("range m")] + [len(b) for b in by_range])
        lines.append("")
        lines.append("IoU% by range band")
        head = f"{'range m':<{bandw}}  " + "  ".join(f"{c:>{w}}" for c, w in zip(cols, colw))
        lines += [head, "-" * len(head)]
        for band, row in by_range.items():
            lines.append(
                f"{band:<{bandw}}  "
                + "  ".join(f"{_fmt(row.get(c), 100):>{w}}" for c, w in zip(cols, colw))
            )
    return "\n".join(lines)



def format_whole_grid_table(result: dict) -> str:
    """Readable text table of :meth:`WholeGridAccumulator.result` (or of a ``metrics.json``
    holding its ``occlusion`` / ``calibration`` keys).

    Shares and ECE are in percent, areas in m^2 per frame; ``-`` marks undefined values.
    """
    occ = result.get("occlusion") or {}
    cal = result.get("calibration") or {}
    names = list((occ.get("classes") or {}) or (cal.get("classes") or {}))
    width = max([len("class"), len("mean")] + [len(n) for n in names])
    lines = [f"Whole grid: {_fmt(occ.get('hidden_share'), 100)}% of the cells hidden from every "
             f"camera; unknown recall {_fmt(occ.get('unknown_recall'), 100)}% (hidden cells "
             f"published as unknown), known precision {_fmt(occ.get('known_precision'), 100)}% "
             "(published-known cells some camera sees)"]
    header = (f"{'class':<{width}}  {'hidden claim%':>13}  {'false%':>6}  {'claim m2/fr':>11}  "
              f"{'false m2/fr':>11}  {'ECE%':>6}")
    lines += [header, "-" * len(header)]
    for name in names:
        o = (occ.get("classes") or {}).get(name, {})
        c = (cal.get("classes") or {}).get(name, {})
        lines.append(
            f"{name:<{width}}  {_fmt(o.get('claim_share'), 100, 2):>13}  "
            f"{_fmt(o.get('false_share'), 100):>6}  {_fmt(o.get('claim_m2_per_frame')):>11}  "
            f"{_fmt(o.get('false_m2_per_frame')):>11}  {_fmt(c.get('ece'), 100, 2):>6}")
    lines.append("-" * len(header))
    lines.append(f"{'mean':<{width}}  {'':>13}  {'':>6}  {'':>11}  {'':>11}  "
                 f"{_fmt(cal.get('mean_ece'), 100, 2):>6}")
    lines.append(f"hidden claim: cells no camera sees, published known with p >= 0.5; false: of "
                 f"those, where the class is absent (full truth); ECE: {cal.get('bins', ECE_BINS)} "
                 "equal-width bins, visible known cells")
    return "\n".join(lines)
