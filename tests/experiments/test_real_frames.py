"""experiments/real_frames.py: the methods picture (``--methods``) maps tiny CamVid frames with the
shipped segipm, S2G2 and FocusBEV as front1 frames (real model passes) and writes a palette PNG
of one row per frame; the crop is front1's 16:9; bad flags exit with ``error:``."""

from __future__ import annotations

import importlib.util
import zlib
from pathlib import Path

import numpy as np
import pytest
from real_data_helpers import write_camvid

from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.labels.classes import CLASS_COLORS, EMPTY_COLOR, UNKNOWN_COLORS

pytestmark = [pytest.mark.slow]  # three real model loads and passes

REPO = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("real_frames", REPO / "experiments" / "real_frames.py")
real_frames = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(real_frames)


def _png_header(data: bytes) -> tuple[int, int, int, int]:
    """``(width, height, bit depth, colour type)`` of a PNG's IHDR."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR"
    return (int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big"), data[24], data[25])


def _png_rgb(data: bytes) -> np.ndarray:
    """The ``(H, W, 3)`` RGB of one of :func:`real_frames.palette_png`'s files (one IDAT, filter 0 rows)."""
    w, h, _, _ = _png_header(data)

    def chunk(kind: bytes) -> bytes:
        i = data.index(kind)
        return data[i + 4:i + 4 + int.from_bytes(data[i - 4:i], "big")]

    palette = np.frombuffer(chunk(b"PLTE"), np.uint8).reshape(-1, 3)
    index = np.frombuffer(zlib.decompress(chunk(b"IDAT")), np.uint8).reshape(h, w + 1)[:, 1:]
    return palette[index]


def test_front1_frame_is_the_centre_16_9_crop_at_front1_size():
    rig = preset_rig("front1")
    image = np.zeros((360, 480, 3), np.uint8)
    image[:45] = 200  # the rows the crop drops
    image[-45:] = 100
    crop, frame = real_frames.front1_frame(image, rig)
    assert crop.shape == (270, 480, 3) and not crop.any()
    assert frame.shape == (225, 400, 3) and not frame.any()


def test_methods_picture_maps_tiny_camvid_frames_with_the_shipped_methods(tmp_path, capsys):
    camvid = write_camvid(tmp_path / "camvid", n=2, splits=("test",))
    out = tmp_path / "methods.png"
    rc = real_frames.main(["--camvid", str(camvid), "--frames", "f0", "f1", "--methods", "segipm,s2g2,focusbev",
                           "--out", str(out), "--threads", "1"])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "s2g2: weights" in printed and "focusbev: weights" in printed  # the shipped files, named
    data = out.read_bytes()
    w, h, depth, kind = _png_header(data)
    assert (depth, kind) == (8, 3)  # 8-bit palette
    picture = _png_rgb(data)
    bev, sep, band = 2 * 128, 4, 20  # the ahead grid (128 cells) at 2 px per cell
    crop_w = 48  # the 16:9 crop of a 48x36 frame keeps its width
    assert w > crop_w + 3 * (bev + sep) and h == band + 2 * (bev + sep) + band  # titles, two rows, the band
    known = {tuple(c) for c in CLASS_COLORS.values()} | {tuple(EMPTY_COLOR)}
    hatch = {tuple(c) for c in UNKNOWN_COLORS}
    for row in range(2):
        y = band + row * (bev + sep)
        for k in range(3):  # segipm, S2G2, FocusBEV: known cells in the frustum, unknown outside
            x = crop_w + sep + k * (bev + sep)
            colours = {tuple(c) for c in np.unique(picture[y:y + bev, x:x + bev].reshape(-1, 3), axis=0)}
            assert colours & known and colours & hatch, (row, k)


def test_methods_picture_refuses_an_unknown_method_and_bad_weights(tmp_path):
    camvid = write_camvid(tmp_path / "camvid", n=1, splits=("test",))
    with pytest.raises(SystemExit, match="error: --methods: unknown"):
        real_frames.main(["--camvid", str(camvid), "--frames", "f0", "--methods", "segipm,nope"])
    bad = tmp_path / "bad.safetensors"
    bad.write_bytes(b"not weights")
    with pytest.raises(SystemExit, match="^error: "):
        real_frames.main(["--camvid", str(camvid), "--frames", "f0", "--methods", "s2g2", "--s2g2-weights", str(bad),
                          "--out", str(tmp_path / "x.png")])
