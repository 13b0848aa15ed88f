"""Readable pictures: class colours, unknown hatch, ego / legend / scale bar in ``bev/image`` and
replay PNGs, per-frame IoU, ``--frames-every``, and ``report.html`` (self-contained, rendered by
headless Chromium)."""

from __future__ import annotations

import itertools
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from bags.cli.main import main
from bags.replay import FRAMES_DIR, REPORT_FILE, ReplayOptions
from bags.replay.frame_scores import FrameScores
from bags.report.pictures import comparison_picture, panel_boxes, panel_scale
from bev_mapper_core.display import EGO_CENTER_X_M, EGO_LENGTH_M, EGO_WIDTH_M, STRIP_FG, BevPainter, painter
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.labels.classes import (
    BEV_CLASSES,
    CAM2BEV_CLASSES,
    CLASS_COLORS,
    EMPTY_COLOR,
    S2G2_CLASSES,
    UNKNOWN_COLORS,
    bev_class,
    bev_picture,
)
from bev_mapper_core.metrics import MetricAccumulator, scope_masks

GRID = BevGrid(-20.0, 20.0, -10.0, 10.0, 0.25)
GRID_ARGS = ["--grid-x-min", "-20", "--grid-x-max", "20", "--grid-y-min", "-10",
             "--grid-y-max", "10", "--grid-res", "0.25"]

# ----------------------------------------------------------------------------- colours
# Colour-vision deficiency simulation (Machado, Oliveira & Fernandes 2009, severity 1.0), applied
# to linear RGB; distances are CIEDE2000 (Sharma, Wu & Dalal 2005) in CIELAB (D65). About 2 is
# just noticeable; 10 and more reads as a different colour at a glance.
_CVD = {
    "protanopia": [[0.152286, 1.052583, -0.204868], [0.114503, 0.786281, 0.099216],
                   [-0.003882, -0.048116, 1.051998]],
    "deuteranopia": [[0.367322, 0.860646, -0.227968], [0.280085, 0.672501, 0.047413],
                     [-0.011820, 0.042940, 0.968881]],
    "tritanopia": [[1.255528, -0.076749, -0.178779], [-0.078411, 0.930809, 0.147602],
                   [0.004733, 0.691367, 0.303900]],
}
_VISION_MARGINS = ((None, 15.0), ("protanopia", 10.0), ("deuteranopia", 10.0),
                   ("tritanopia", 10.0))


def _linear(rgb):
    c = np.asarray(rgb, np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _lab(lin):
    xyz = lin @ np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722],
                          [0.0193, 0.1192, 0.9505]]).T / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > 0.008856, np.cbrt(xyz), 7.787 * xyz + 16 / 116)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]),
                     200 * (f[..., 1] - f[..., 2])], -1)


def _de2000(lab1, lab2) -> float:
    (L1, a1, b1), (L2, a2, b2) = lab1, lab2
    cm = (np.hypot(a1, b1) + np.hypot(a2, b2)) / 2
    g = 0.5 * (1 - np.sqrt(cm ** 7 / (cm ** 7 + 25.0 ** 7)))
    a1, a2 = (1 + g) * a1, (1 + g) * a2
    c1, c2 = np.hypot(a1, b1), np.hypot(a2, b2)
    h1, h2 = np.degrees(np.arctan2(b1, a1)) % 360, np.degrees(np.arctan2(b2, a2)) % 360
    dh = 0.0 if c1 * c2 == 0 else (h2 - h1 + 180) % 360 - 180
    dH = 2 * np.sqrt(c1 * c2) * np.sin(np.radians(dh / 2))
    lm, cpm = (L1 + L2) / 2, (c1 + c2) / 2
    if c1 * c2 == 0:
        hm = h1 + h2
    elif abs(h1 - h2) <= 180:
        hm = (h1 + h2) / 2
    else:
        hm = (h1 + h2 + 360) / 2 if h1 + h2 < 360 else (h1 + h2 - 360) / 2
    t = (1 - 0.17 * np.cos(np.radians(hm - 30)) + 0.24 * np.cos(np.radians(2 * hm))
         + 0.32 * np.cos(np.radians(3 * hm + 6)) - 0.20 * np.cos(np.radians(4 * hm - 63)))
    rc = 2 * np.sqrt(cpm ** 7 / (cpm ** 7 + 25.0 ** 7))
    rt = -np.sin(np.radians(60 * np.exp(-(((hm - 275) / 25) ** 2)))) * rc
    sl = 1 + 0.015 * (lm - 50) ** 2 / np.sqrt(20 + (lm - 50) ** 2)
    sc, sh = 1 + 0.045 * cpm, 1 + 0.015 * cpm * t
    dl, dc, dh_ = (L2 - L1) / sl, (c2 - c1) / sc, dH / sh
    return float(np.sqrt(dl ** 2 + dc ** 2 + dh_ ** 2 + rt * dc * dh_))


def _delta_e(a, b, vision=None) -> float:
    la, lb = _linear([a, b])
    if vision is not None:
        m = np.asarray(_CVD[vision])
        la, lb = np.clip(la @ m.T, 0, 1), np.clip(lb @ m.T, 0, 1)
    return _de2000(_lab(la), _lab(lb))


def _too_close(colours: dict, neutral: dict) -> list[str]:
    """Pairs of class colours, or of a class colour and a neutral one, closer than the margins."""
    out = []
    pairs = list(itertools.combinations(colours, 2)) + [(c, n) for c in colours for n in neutral]
    both = {**colours, **neutral}
    for vision, margin in _VISION_MARGINS:
        for a, b in pairs:
            d = _delta_e(both[a], both[b], vision)
            if d < margin:
                out.append(f"{a}/{b} {vision or 'normal'}: dE {d:.1f} < {margin}")
    return out


def test_delta_e_2000_reference_pairs():  # Sharma et al.'s test data, pairs 1 and 17
    assert _de2000((50, 2.6772, -79.7751), (50, 0, -82.7485)) == pytest.approx(2.0425, abs=1e-4)
    assert _de2000((50, 2.5, 0), (73, 25, -18)) == pytest.approx(27.1492, abs=1e-4)


def test_class_colours_are_distinct_also_for_colour_blind_viewers():
    names = [c.name for c in BEV_CLASSES + CAM2BEV_CLASSES + S2G2_CLASSES]
    assert set(names) == set(CLASS_COLORS) and len(CLASS_COLORS) == 11
    for c in BEV_CLASSES + CAM2BEV_CLASSES + S2G2_CLASSES:  # one source: every class takes its name's colour
        assert c.color == CLASS_COLORS[c.name]
    neutral = {"empty": EMPTY_COLOR, "unknown": UNKNOWN_COLORS[0], "hatch": UNKNOWN_COLORS[1]}
    # the standard and Cam2BEV sets together (mixed by --classes on cam2bev4), and S2G2's set
    first_nine = {c.name: c.color for c in BEV_CLASSES + CAM2BEV_CLASSES}
    assert len(first_nine) == 9 and _too_close(first_nine, neutral) == []
    assert _too_close({c.name: c.color for c in S2G2_CLASSES}, neutral) == []
    for own in ("terrain", "obstacle"):  # S2G2's own colours stay well away from every other one
        assert min(_delta_e(CLASS_COLORS[own], CLASS_COLORS[n]) for n in first_nine) > 24
    # the reported pair, by a wide margin in every vision
    assert min(_delta_e(CLASS_COLORS["pedestrian"], CLASS_COLORS["road_boundary"], v)
               for v, _ in _VISION_MARGINS) > 30
    # the check itself fails the old palette: pedestrian and curb reds, the same road colours
    old = {"drivable": (128, 64, 128), "lane_divider": (255, 255, 255),
           "ped_crossing": (255, 200, 0), "road_boundary": (255, 0, 0),
           "sidewalk": (244, 35, 232), "vehicle": (0, 0, 255), "pedestrian": (220, 20, 60), "road": (128, 64, 128), "static": (70, 70, 70)}
    bad = _too_close(old, {"empty": (200, 200, 200), "unknown": (40, 40, 40)})
    assert any(b.startswith("road_boundary/pedestrian normal") for b in bad)
    assert any(b.startswith("drivable/road") for b in bad)


# ----------------------------------------------------------------------------- bev/image
def _layers(grid: BevGrid, name_cells: dict[str, np.ndarray]) -> np.ndarray:
    out = np.zeros((len(BEV_CLASSES),) + grid.shape, np.float32)
    for name, mask in name_cells.items():
        out[[c.name for c in BEV_CLASSES].index(name)][mask] = 1.0
    return out


def _runs(mask: np.ndarray) -> int:
    """Longest run of True along the last axis, over all rows."""
    best = 0
    for row in mask:
        padded = np.concatenate([[0], row.astype(np.int8), [0]])
        edges = np.flatnonzero(np.diff(padded))
        if edges.size:
            best = max(best, int((edges[1::2] - edges[::2]).max()))
    return best


def test_bev_picture_has_map_ego_legend_axes_and_scale_bar():
    grid = BevGrid()  # the node's default 400 x 200 cells at 0.15 m
    xs, ys = grid.centers
    known = ~((xs > 20) & (ys > 5))  # an unknown corner: front left
    layers = _layers(grid, {"drivable": np.abs(ys) < 6, "pedestrian": (xs > -15) & (xs < -14)
                            & (ys > 8) & (ys < 9)})
    img = bev_picture(grid, layers, BEV_CLASSES, known)
    p = painter(grid, BEV_CLASSES)
    assert img.flags.c_contiguous and img.dtype == np.uint8
    assert img.shape[:2] == (grid.width, grid.height + p.legend_width())
    mp, strip = img[:grid.width, :grid.height], img[:, grid.height:]

    def px(x, y):
        c, r = p.to_px(x, y)
        return mp[int(r), int(c)]

    # cells: classes, empty, unknown hatch (both hatch colours), forward up and left on the left
    assert tuple(px(-10, 0)) == CLASS_COLORS["drivable"]
    assert tuple(px(-14.5, 8.5)) == CLASS_COLORS["pedestrian"]
    assert tuple(px(-10, -9)) == EMPTY_COLOR
    corner = mp[: int(p.to_px(20.5, 0)[1]), : int(p.to_px(0, 5.5)[0])]
    assert {tuple(v) for v in corner.reshape(-1, 3)} == set(UNKNOWN_COLORS)
    # ego footprint: white body, black outline, drawn over the map at the origin
    c0, r0, c1, r1 = p.ego_box_px()
    assert abs((r1 - r0 + 1) - EGO_LENGTH_M / 0.15) <= 1
    assert abs((c1 - c0 + 1) - EGO_WIDTH_M / 0.15) <= 1
    assert tuple(px(EGO_CENTER_X_M - 1.0, 0)) == (255, 255, 255)
    assert tuple(mp[r0, c0]) == tuple(mp[r1, c1]) == (0, 0, 0)
    assert tuple(px(EGO_CENTER_X_M - EGO_LENGTH_M / 2 - 0.5, 0)) == CLASS_COLORS["drivable"]
    # legend: a swatch of every class colour, of empty and of the hatch
    for c in BEV_CLASSES:
        assert np.all(strip == c.color, axis=-1).sum() >= 100, c.name
    assert np.all(strip == EMPTY_COLOR, axis=-1).sum() >= 100
    assert all(np.all(strip == u, axis=-1).sum() >= 20 for u in UNKNOWN_COLORS)
    fg = np.all(strip == STRIP_FG, axis=-1)
    # scale bar: a horizontal line as long as its label says (10 m at 0.15 m per pixel)
    bar_m = p.scale_bar_m(p.legend_width() - 12)
    assert bar_m == 10.0 and _runs(fg) == round(bar_m / 0.15)
    # the forward arrow: a vertical line of ~30 px (anti-aliased: light pixels); text is shorter
    assert _runs((strip.min(axis=-1) > 120).T) >= 25


def test_bev_picture_static_parts_are_cached():
    grid = BevGrid(-10.0, 10.0, -5.0, 5.0, 0.5)
    painter.cache_clear()
    layers = np.zeros((len(BEV_CLASSES),) + grid.shape, np.float32)
    a = bev_picture(grid, layers, BEV_CLASSES, None)
    b = bev_picture(grid, layers, BEV_CLASSES, None)
    info = painter.cache_info()
    assert info.misses == 1 and info.hits == 1
    assert np.array_equal(a, b)
    # a small grid: the picture grows to hold the legend, the map stays at the top left
    assert a.shape[0] > grid.width and np.all(a[:grid.width, :grid.height] == EMPTY_COLOR,
                                              axis=-1).sum() > 0.9 * grid.width * grid.height


# ----------------------------------------------------------------------------- replay picture
def _display_mask(grid: BevGrid, mask: np.ndarray, scale: int) -> np.ndarray:
    d = grid.to_display(mask)
    return np.repeat(np.repeat(d, scale, axis=0), scale, axis=1)


def test_unknown_and_unseen_cells_are_drawn_identically_in_both_panels():
    grid, rng = GRID, np.random.default_rng(3)
    xs, ys = grid.centers
    gt = rng.random((len(BEV_CLASSES),) + grid.shape) > 0.7
    pred = rng.random((len(BEV_CLASSES),) + grid.shape).astype(np.float32)
    gt_mask = ~((xs > 5) & (ys > 0))  # GT cannot see the front left
    pred_known = ~((xs < -5) & (ys < 0))  # the mapper does not know the rear right
    pic = comparison_picture(grid, pred, pred_known, BEV_CLASSES, gt, gt_mask, BEV_CLASSES,
                             method="test", caption="frame 0", ious={"drivable": 0.5})
    (lx, ly, w, h), (rx, ry, _, _) = panel_boxes(grid)
    left, right = pic[ly:ly + h, lx:lx + w], pic[ry:ry + h, rx:rx + w]
    s = panel_scale(grid)
    hidden = _display_mask(grid, ~gt_mask, s)
    unknown = _display_mask(grid, ~pred_known & gt_mask, s)
    hatch = {tuple(u) for u in UNKNOWN_COLORS}
    # GT not visible: the same hatch, pixel for pixel, in both panels
    assert np.array_equal(left[hidden], right[hidden])
    assert {tuple(v) for v in left[hidden]} == hatch
    # the mapper's unknown cells are hatched in the prediction; the GT shows its classes there
    assert {tuple(v) for v in left[unknown]} == hatch
    assert not ({tuple(v) for v in right[unknown]} & hatch)
    # elsewhere the prediction shows colours, not the hatch (the ego aside)
    ego = np.zeros((h, w), bool)
    c0, r0, c1, r1 = painter(grid, BEV_CLASSES, s).ego_box_px()
    ego[r0:r1 + 1, c0:c1 + 1] = True
    assert not ({tuple(v) for v in left[~hidden & ~unknown & ~ego]} & hatch)
    # the legend strip right of the panels holds every class swatch
    strip = pic[:, rx + w:]
    assert all(np.all(strip == c.color, axis=-1).sum() >= 100 for c in BEV_CLASSES)


def test_frame_scores_equal_the_accumulators_frame_iou():
    grid, rng = GRID, np.random.default_rng(7)
    names = [c.name for c in BEV_CLASSES]
    probs = rng.random((len(names),) + grid.shape).astype(np.float32)
    gt = rng.random((len(names),) + grid.shape) > 0.6
    gt[names.index("pedestrian")] = False
    probs[names.index("pedestrian")] = 0.0  # absent from both: undefined
    visible, ground = rng.random(grid.shape) > 0.2, rng.random(grid.shape) > 0.4
    known = rng.random(grid.shape) > 0.1
    for scope in ("visible", "ground"):
        want = MetricAccumulator(grid, names).update(
            probs, gt, scope_masks(names, visible, ground, scope), known)
        got = FrameScores().add(4, 99, probs, known, names, gt, names, visible, ground, scope)
        assert got.index == 4 and list(got.ious) == names
        assert got.ious["pedestrian"] is None
        np.testing.assert_allclose([np.nan if v is None else v for v in got.ious.values()], want)
        assert got.miou == pytest.approx(np.nanmean(want))


# ----------------------------------------------------------------------------- replay + report
@pytest.fixture(scope="module")
def replays(tmp_path_factory):
    """A 3-frame drive replayed with --frames-every 1 (and report), the default, and the old
    --picture-every 2."""
    pytest.importorskip("bev_mapper_core.synth")
    root = tmp_path_factory.mktemp("pictures")
    bag = root / "drive"
    assert main(["synth", str(bag), "--frames", "3", "--seed", "5", "--scale", "0.5",
                 *GRID_ARGS]) == 0
    outs = {k: root / k for k in ("every", "default", "alias")}
    base = ["replay", str(bag), "--quiet", "--method", "ipm", "--out"]
    assert main(base + [str(outs["every"]), "--frames-every", "1"]) == 0
    assert main(base + [str(outs["default"]), "--no-report"]) == 0
    assert main(base + [str(outs["alias"]), "--picture-every", "2", "--no-report"]) == 0
    return bag, outs


def test_frames_every(replays):
    bag, outs = replays
    names = {k: sorted(p.name for p in (o / FRAMES_DIR).glob("*.png")) for k, o in outs.items()}
    assert names["every"] == ["frame_0000.png", "frame_0001.png", "frame_0002.png"]
    assert ReplayOptions.frames_every == 10 and names["default"] == ["frame_0000.png"]
    assert names["alias"] == ["frame_0000.png", "frame_0002.png"]
    img = cv2.imread(str(outs["every"] / FRAMES_DIR / "frame_0001.png"))[..., ::-1]
    (_, _, w, _), (rx, _, _, _) = panel_boxes(GRID)
    strip = img[:, rx + w:]  # the legend, with the classes' colours
    assert all(np.all(strip == c.color, axis=-1).sum() >= 100 for c in BEV_CLASSES)


def test_frames_every_must_be_positive(replays, tmp_path, capsys):
    bag, _ = replays
    assert main(["replay", str(bag), "--out", str(tmp_path / "o"), "--method", "ipm",
                 "--frames-every", "0"]) == 1
    assert "error: --frames-every must be >= 1" in capsys.readouterr().err


def test_help_lists_outputs_and_default(capsys):
    assert main(["replay", "--help"]) == 0
    text = capsys.readouterr().out
    assert "report.html" in text and "--no-report" in text and "--frames-every" in text
    assert f"default {ReplayOptions.frames_every}" in text


def test_report_is_self_contained(replays):
    _, outs = replays
    html = (outs["every"] / REPORT_FILE).read_text()
    assert not re.search(r"https?://", html)
    assert "<link" not in html and not re.search(r"<script[^>]+src=", html)
    srcs = re.findall(r'(?:src|href)="([^"]+)"', html)
    data = json.loads(re.search(r'id="frames-data">(.*?)</script>', html, re.S).group(1))
    srcs += [f["src"] for f in data]
    assert srcs and all(s.startswith("frames/") for s in srcs)
    assert all((outs["every"] / s).is_file() for s in srcs)
    assert len(data) == 3 and "mIoU" in data[0]["label"]
    for needle in ("drivable", "pedestrian", "mIoU / mAP", "IoU by range", "Mapping latency",
                   "<svg", 'id="slider"', "mIoU is the mean IoU over the"):
        assert needle in html, needle
    assert not (outs["default"] / REPORT_FILE).exists()  # --no-report


def test_no_report_removes_a_stale_report(replays, tmp_path):
    bag, outs = replays
    out = tmp_path / "o"
    shutil.copytree(outs["every"], out)
    assert main(["replay", str(bag), "--quiet", "--method", "ipm", "--out", str(out), "--force",
                 "--no-report", "--no-pictures"]) == 0
    assert not (out / REPORT_FILE).exists() and not (out / FRAMES_DIR).exists()


# ----------------------------------------------------------------------------- Chromium
_BROWSERS = ("chromium-headless-shell", "chromium", "chromium-browser", "google-chrome")


def _browser() -> str:
    for name in _BROWSERS:
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no headless browser: chromium-headless-shell (or chromium) is not installed; "
                "scripts/test.sh installs it with apt-get when run as root")


def _render(browser: str, html: Path, png: Path, tmp: Path, *extra: str):
    """Run the browser on ``html``: ``(returncode, console messages, stdout)``."""
    args = [browser, "--headless", "--disable-gpu", f"--user-data-dir={tmp / 'profile'}",
            "--enable-logging=stderr", "--v=0", "--window-size=1100,3200", *extra,
            html.resolve().as_uri()]
    if os.geteuid() == 0:
        args.insert(1, "--no-sandbox")
    if png is not None:
        args.insert(1, f"--screenshot={png}")
    proc = subprocess.run(args, capture_output=True, text=True, timeout=120)
    console = [ln for ln in proc.stderr.splitlines() if ":CONSOLE" in ln]
    return proc.returncode, console, proc.stdout


def test_report_renders_in_headless_chromium(replays, tmp_path):
    browser = _browser()
    _, outs = replays
    html = outs["every"] / REPORT_FILE
    png = tmp_path / "report.png"
    rc, console, _ = _render(browser, html, png, tmp_path)
    assert rc == 0 and console == []
    img = cv2.imread(str(png))
    assert img is not None and img.shape[:2] == (3200, 1100)
    assert img.std() > 20 and len(np.unique(img.reshape(-1, 3), axis=0)) > 50  # not blank
    # the viewer's script ran: it wrote the frame counter into the page
    rc, console, dom = _render(browser, html, None, tmp_path, "--dump-dom")
    assert rc == 0 and console == [] and "(1 / 3)" in dom
    # a report without pictures (no viewer) runs its script without errors too
    from bags.replay import ReplayResult  # noqa: PLC0415
    from bags.report.html import render_report  # noqa: PLC0415

    metrics = json.loads((outs["every"] / "metrics.json").read_text())
    bare = tmp_path / "bare.html"
    bare.write_text(render_report(ReplayResult(metrics, tmp_path, tmp_path, [])))
    rc, console, _ = _render(browser, bare, tmp_path / "bare.png", tmp_path)
    assert rc == 0 and console == []
    # and a page with a script error is caught the same way
    bad = tmp_path / "bad.html"
    bad.write_text("<!doctype html><p>x</p><script>undefinedFunction();</script>")
    rc, console, _ = _render(browser, bad, tmp_path / "bad.png", tmp_path)
    assert any("Uncaught ReferenceError" in c for c in console)


def test_painter_rejects_bad_scale():
    with pytest.raises(ValueError):
        BevPainter(GRID, BEV_CLASSES, scale=0)
    assert bev_class("road").color != bev_class("drivable").color


def test_report_without_pictures_or_ground_truth(replays, tmp_path):
    bag, _ = replays
    out = tmp_path / "o"
    assert main(["replay", str(bag), "--quiet", "--method", "ipm", "--out", str(out),
                 "--no-pictures"]) == 0
    html = (out / REPORT_FILE).read_text()
    assert "No pictures were written" in html and 'id="frames-data"' not in html
    assert "mIoU / mAP" in html
    from bags.replay import ReplayResult  # noqa: PLC0415
    from bags.report.html import render_report  # noqa: PLC0415

    metrics = json.loads((out / "metrics.json").read_text())
    metrics.update(frames_scored=0, classes={}, miou=None, map=None, iou_by_range={},
                   scope_used=None)
    html = render_report(ReplayResult(metrics, out, out / "bev_bag", []))
    assert "nothing was scored" in html and "No frame was mapped" in html
    assert "<svg" not in html and not re.search(r"https?://", html)
