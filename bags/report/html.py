"""``report.html`` of ``bev-bag replay``: one self-contained page to read a replay.

:func:`render_report` turns a :class:`~bags.replay.ReplayResult` into HTML with inline CSS, inline
SVG charts (:mod:`bags.report.svg_plots`) and a few lines of inline JavaScript; it references nothing on
the network. Sections: the run (method, bag, frames, scope, grid, notes), the metrics table (per
class IoU, precision and Chamfer distances, mIoU / mAP and the classes mIoU is taken over), bar
charts of IoU and precision per class, Chamfer per class and IoU by range band, "Honest maps"
(what the method publishes where no camera sees: occluded claims per class, unknown recall,
known precision, and the calibration of its probabilities: ECE and a reliability diagram), the
per-frame mIoU, a histogram of the per-frame mapping latency, and a frame viewer (slider, prev / next,
play, arrow keys) of the ``frames/*.png`` pictures, referenced relatively: keep the report beside
its ``frames/`` folder.
"""

from __future__ import annotations

import json
from html import escape
from typing import TYPE_CHECKING

from bev_mapper_core.labels.classes import CLASS_COLORS

from .reliability import reliability_svg
from .svg_plots import bar_chart, histogram, line_chart

if TYPE_CHECKING:
    from ..replay.options import ReplayResult

_CSS = """
body{font-family:sans-serif;margin:24px auto;max-width:1000px;color:#222;background:#fff}
h1{font-size:22px;margin-bottom:4px} h2{font-size:17px;margin-top:28px;border-bottom:1px solid #ccc}
table{border-collapse:collapse;font-size:13px} td,th{padding:3px 9px;text-align:right}
th{background:#eee} td:first-child,th:first-child{text-align:left}
tr.mean td{border-top:1px solid #888;font-weight:bold}
.sw{display:inline-block;width:11px;height:11px;border:1px solid #555;margin-right:6px;
vertical-align:-1px}
.meta td{text-align:left;padding:1px 9px} .note{color:#a40} .muted{color:#777;font-size:13px}
#viewer img{max-width:100%;image-rendering:pixelated;border:1px solid #ccc;display:block}
#viewer button{font-size:14px;min-width:36px} #slider{width:50%;vertical-align:middle}
"""

_JS = """
(function(){
  var data = document.getElementById('frames-data');
  if (!data) return;
  var frames = JSON.parse(data.textContent);
  var img = document.getElementById('frame'), slider = document.getElementById('slider');
  var label = document.getElementById('frame-label'), timer = null, cur = 0;
  if (!frames.length) return;
  function show(i){
    cur = Math.max(0, Math.min(frames.length - 1, i));
    slider.value = cur; img.src = frames[cur].src;
    label.textContent = frames[cur].label + '  (' + (cur + 1) + ' / ' + frames.length + ')';
  }
  function play(){
    var b = document.getElementById('play');
    if (timer) { clearInterval(timer); timer = null; b.textContent = 'play'; return; }
    b.textContent = 'pause';
    timer = setInterval(function(){ show(cur + 1 < frames.length ? cur + 1 : 0); }, 400);
  }
  slider.max = frames.length - 1;
  slider.addEventListener('input', function(){ show(+slider.value); });
  document.getElementById('prev').addEventListener('click', function(){ show(cur - 1); });
  document.getElementById('next').addEventListener('click', function(){ show(cur + 1); });
  document.getElementById('play').addEventListener('click', play);
  document.addEventListener('keydown', function(e){
    if (e.key === 'ArrowLeft') show(cur - 1);
    if (e.key === 'ArrowRight') show(cur + 1);
  });
  show(0);
})();
"""


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}"


def _m(v) -> str:
    return "-" if v is None else f"{v:.3f}"


def _swatch(name: str) -> str:
    rgb = CLASS_COLORS.get(name)
    if rgb is None:
        return ""
    return f'<span class="sw" style="background:rgb({rgb[0]},{rgb[1]},{rgb[2]})"></span>'


def _run_section(m: dict, result: "ReplayResult") -> str:
    g = m.get("grid") or {}
    rows = [
        ("method", f"{m['method']} (input: {m['input']})"),
        ("bag", m["bag"]),
        ("frames", f"{m['frames']} mapped, {m['frames_scored']} scored, "
                   f"{m['frames_skipped']} skipped"),
        ("scope", f"{m['scope']} (used: {m['scope_used'] or 'none'})"),
        ("grid", f"x [{g.get('x_min')}, {g.get('x_max')}] m, y [{g.get('y_min')}, "
                 f"{g.get('y_max')}] m at {g.get('resolution')} m"),
        ("complete", "yes" if m["complete"] else f"no: {m['damage']}"),
    ]
    body = "".join(f"<tr><td><b>{escape(k)}</b></td><td>{escape(str(v))}</td></tr>"
                   for k, v in rows)
    notes = "".join(f'<p class="note">note: {escape(n)}</p>' for n in result.notes if n)
    return f'<table class="meta">{body}</table>{notes}'


def _metrics_section(m: dict) -> str:
    classes = m.get("classes") or {}
    if not classes:
        return '<p class="muted">No frame with ground truth: nothing was scored.</p>'
    head = ("<tr><th>class</th><th>IoU %</th><th>precision %</th><th>CD<sub>p</sub> m</th>"
            "<th>CD<sub>L</sub> m</th><th>CD m</th></tr>")
    rows = "".join(
        f"<tr><td>{_swatch(n)}{escape(n)}</td><td>{_pct(c.get('iou'))}</td>"
        f"<td>{_pct(c.get('precision'))}</td><td>{_m(c.get('cd_p'))}</td>"
        f"<td>{_m(c.get('cd_l'))}</td><td>{_m(c.get('cd'))}</td></tr>"
        for n, c in classes.items())
    mean = (f'<tr class="mean"><td>mIoU / mAP</td><td>{_pct(m.get("miou"))}</td>'
            f'<td>{_pct(m.get("map"))}</td><td></td><td></td><td></td></tr>')
    over = [n for n, c in classes.items() if c.get("iou") is not None]
    undefined = [n for n in classes if n not in over]
    text = (f"mIoU is the mean IoU over the {len(over)} class(es) with a defined IoU: "
            f"{', '.join(over) or 'none'}.")
    if undefined:
        text += f" Undefined (absent from prediction and ground truth): {', '.join(undefined)}."
    if m.get("unscored_classes"):
        text += f" Not scored (no ground truth in the bag): {', '.join(m['unscored_classes'])}."
    text += (" IoU and precision are summed over all scored frames; Chamfer distances (metres)"
             " average the frames where the class is present.")
    return f"<table>{head}{rows}{mean}</table><p class=\"muted\">{escape(text)}</p>"


def _charts_section(m: dict) -> str:
    classes = m.get("classes") or {}
    if not classes:
        return ""
    names = list(classes)
    colors = [CLASS_COLORS.get(n, (128, 128, 128)) for n in names]
    parts = ["<h2>Per class</h2>",
             '<p class="muted">IoU (solid) and precision (pale), over all scored frames</p>',
             bar_chart(names, [("IoU", colors, [classes[n].get("iou") for n in names]),
                               ("precision", colors, [classes[n].get("precision") for n in names])],
                       y_max=1.0, percent=True, y_label="IoU / precision", opacities=(1.0, 0.4)),
             '<p class="muted">Chamfer distance (metres, lower is better)</p>',
             bar_chart(names, [("Chamfer distance", colors, [classes[n].get("cd") for n in names])],
                       y_label="CD (m)", height=220)]
    by_range = m.get("iou_by_range") or {}
    if by_range:
        bands = list(by_range)
        series = [(n, CLASS_COLORS.get(n, (128, 128, 128)), [by_range[b].get(n) for b in bands])
                  for n in names]
        series.append(("mIoU", "#444", [by_range[b].get("miou") for b in bands]))
        parts += ["<h2>IoU by range</h2>",
                  '<p class="muted">IoU per class in bands of distance from the ego origin</p>',
                  bar_chart([f"{b} m" for b in bands], series, y_max=1.0, percent=True,
                            y_label="IoU", width=900, height=300)]
    return "\n".join(parts)


def _m2(v) -> str:
    return "-" if v is None else f"{v:.1f}"


def _honest_section(m: dict) -> str:
    """Occluded claims, unknown recall / known precision and calibration (ECE, reliability)."""
    occ, cal = m.get("occlusion"), m.get("calibration")
    if not occ or not cal or not m.get("frames_scored"):
        return ""
    head = ("<tr><th>class</th><th>hidden cells claimed %</th><th>false %</th>"
            "<th>claimed m&sup2;/frame</th><th>false m&sup2;/frame</th><th>ECE %</th></tr>")
    rows = "".join(
        f"<tr><td>{_swatch(n)}{escape(n)}</td><td>{_pct(o.get('claim_share'))}</td>"
        f"<td>{_pct(o.get('false_share'))}</td><td>{_m2(o.get('claim_m2_per_frame'))}</td>"
        f"<td>{_m2(o.get('false_m2_per_frame'))}</td>"
        f"<td>{_pct((cal['classes'].get(n) or {}).get('ece'))}</td></tr>"
        for n, o in occ["classes"].items())
    mean = (f'<tr class="mean"><td>mean ECE</td><td></td><td></td><td></td><td></td>'
            f'<td>{_pct(cal.get("mean_ece"))}</td></tr>')
    truth = ("counted against the full truth (/bev/truth/&lt;class&gt;) of "
             f"{occ.get('frames_with_truth')} frame(s)" if occ.get("frames_with_truth")
             else "not counted: the bag has no /bev/truth/&lt;class&gt; layers")
    text = (f"{_pct(occ.get('hidden_share'))} % of the cells are hidden from every camera. Of "
            f"those, {_pct(occ.get('unknown_recall'))} % are published as unknown (unknown "
            f"recall); of the cells published as known, {_pct(occ.get('known_precision'))} % are "
            "seen by some camera (known precision). A hidden cell is claimed for a class when it "
            f"is published known with p &ge; 0.5; false claims are {truth}. ECE: "
            f"{cal.get('bins')} equal-width bins of the published probability, on the visible, "
            "known cells of each class's scoring scope.")
    return ("<h2>Honest maps</h2>"
            f'<p class="muted">{text}</p><table>{head}{rows}{mean}</table>'
            '<p class="muted">Reliability diagram: per bin, the share of cells where the class is '
            "present against the bin's mean published probability (dashed: perfect calibration; "
            "dot area grows with the log of the bin's cells; also reliability.png)</p>"
            + reliability_svg(cal))


def _per_frame_section(result: "ReplayResult") -> str:
    scores = result.frame_scores.frames
    if not scores:
        return ""
    return ("<h2>mIoU per frame</h2>"
            + line_chart([s.index for s in scores], [s.miou for s in scores], percent=True,
                         x_label="frame", y_label="mIoU"))


def _latency_section(m: dict, result: "ReplayResult") -> str:
    lat = m.get("latency_ms") or {}
    if not result.latencies_ms:
        return '<h2>Mapping latency</h2><p class="muted">No frame was mapped.</p>'
    text = (f"per-frame mapping time (mapper only) over {len(result.latencies_ms)} frames: "
            f"p50 {lat.get('p50')} ms, p95 {lat.get('p95')} ms, mean {lat.get('mean')} ms, "
            f"max {lat.get('max')} ms")
    return (f'<h2>Mapping latency</h2><p class="muted">{escape(text)}</p>'
            + histogram(result.latencies_ms, x_label="ms per frame",
                        markers={"p50": lat.get("p50"), "p95": lat.get("p95")}))


def _viewer_section(result: "ReplayResult") -> str:
    if not result.pictures:
        return ('<h2>Frames</h2><p class="muted">No pictures were written '
                "(--no-pictures).</p>")
    by_index = {s.index: s for s in result.frame_scores.frames}
    frames = []
    for p in result.pictures:
        index = int(p.stem.rsplit("_", 1)[1])
        s = by_index.get(index)
        miou = "" if s is None or s.miou is None else f", mIoU {100 * s.miou:.1f}%"
        frames.append({"src": f"{p.parent.name}/{p.name}", "label": f"frame {index}{miou}"})
    data = json.dumps(frames).replace("</", "<\\/")
    first = escape(frames[0]["src"])
    return f"""<h2>Frames</h2>
<div id="viewer">
<p><button id="prev" title="previous (left arrow)">&#9664;</button>
<input id="slider" type="range" min="0" max="{len(frames) - 1}" value="0">
<button id="next" title="next (right arrow)">&#9654;</button>
<button id="play">play</button> <span id="frame-label">{escape(frames[0]['label'])}</span></p>
<img id="frame" src="{first}" alt="prediction, ground truth and legend of the frame">
</div>
<script type="application/json" id="frames-data">{data}</script>"""


def render_report(result: "ReplayResult") -> str:
    """The HTML text of ``report.html`` for a finished replay (see the module docstring)."""
    m = result.metrics
    title = f"bev-bag replay: {m['method']} on {m['bag']}"
    body = "\n".join([
        f"<h1>{escape(title)}</h1>",
        _run_section(m, result),
        "<h2>Metrics</h2>", _metrics_section(m),
        _charts_section(m),
        _honest_section(m),
        _per_frame_section(result),
        _latency_section(m, result),
        _viewer_section(result),
        '<p class="muted">Written by bev-bag replay; self-contained (no network).</p>',
    ])
    return (f'<!doctype html>\n<html lang="en"><head><meta charset="utf-8">'
            f"<title>{escape(title)}</title><style>{_CSS}</style></head>\n<body>\n{body}\n"
            f"<script>{_JS}</script>\n</body></html>\n")
