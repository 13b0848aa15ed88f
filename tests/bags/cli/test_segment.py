"""``bev-bag segment``: label PNGs, overlays and the legend of hand-made PNG/JPEG images, equal to
the segmenter called directly; every kind of bad input is an ``error:`` naming the file, with
nothing half-written (or skipped and counted with ``--skip-bad``).
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from bags.cli.main import main
from bags.cli.segment import LEGEND, OVERLAY_DIR
from bev_mapper_core.labels.classes import NUM_LABELS, Label, overlay_labels
from bev_mapper_core.methods import WEIGHTS_DIR
from bev_mapper_core.methods.segmenter.model import Segmenter, SegmenterConfig
from bev_mapper_core.methods.segmenter.stage import GENERAL_SEGMENTER, SegmenterStage
from bev_mapper_core.methods.segmenter.weights import load_segmenter, save_segmenter
from msg_adapters import DEFAULT_LIMITS

TINY = SegmenterConfig(input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3, decoder_channels=8)


@pytest.fixture(scope="module")
def tiny_segmenter(tmp_path_factory) -> Path:
    """A small random segmenter file whose classifier favours a different label per colour."""
    torch.manual_seed(0)
    model = Segmenter(TINY).eval()
    with torch.no_grad():
        model.classifier.bias.copy_(torch.linspace(-1.0, 1.0, NUM_LABELS))
    return save_segmenter(model, tmp_path_factory.mktemp("seg") / "tiny.safetensors", "front1")


def _rgb(h: int, w: int, seed: int) -> np.ndarray:
    """A smooth random RGB picture (blocks of colour: JPEG keeps it close)."""
    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (max(1, h // 4), max(1, w // 4), 3), dtype=np.uint8)
    return np.ascontiguousarray(cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST))


def _write(path: Path, arr: np.ndarray) -> Path:
    """Write RGB(A) / grey / 16-bit ``arr`` with OpenCV (BGR order on disk)."""
    bgr = arr[..., [2, 1, 0, 3][: arr.shape[2]]] if arr.ndim == 3 else arr
    assert cv2.imwrite(str(path), bgr)
    return path


def _direct(segmenter: Path, rgb: np.ndarray) -> np.ndarray:
    """The segmenter called directly (load_segmenter + Segmenter.segment)."""
    return load_segmenter(segmenter).segment(torch.from_numpy(rgb)[None])[0].numpy()


def _read(path: Path) -> np.ndarray:
    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert arr is not None, path
    return arr if arr.ndim == 2 else np.ascontiguousarray(arr[..., ::-1])


def _no_partials(out: Path) -> None:
    assert not [p for p in out.rglob("*") if ".partial-" in p.name]


def _huge_png(path: Path, w: int, h: int) -> Path:
    """A PNG whose header claims ``w x h`` (8-bit RGB) with a tiny, bogus body."""
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    chunk = struct.pack(">I", 13) + b"IHDR" + ihdr + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk + b"\x00" * 64)
    return path


def test_folder_of_png_and_jpeg(tmp_path, tiny_segmenter, capsys):
    src = tmp_path / "in"
    src.mkdir()
    a = _rgb(17, 24, 1)
    _write(src / "a.png", a)
    _write(src / "b.JPG", _rgb(12, 20, 2))
    (src / "notes.txt").write_text("not an image")
    (src / "sub").mkdir()
    _write(src / "sub" / "c.png", _rgb(8, 8, 3))  # subfolders are not walked
    out = tmp_path / "out"
    assert main(["segment", str(src), "--out", str(out), "--segmenter", str(tiny_segmenter)]) == 0
    assert "segmented 2 image(s)" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["a.png", "b.png", LEGEND, OVERLAY_DIR]
    assert sorted(p.name for p in (out / OVERLAY_DIR).iterdir()) == ["a.png", "b.png"]
    for stem, rgb in (("a", a), ("b", _read(src / "b.JPG"))):  # the JPEG as decoded
        labels = _read(out / f"{stem}.png")
        assert labels.dtype == np.uint8 and labels.shape == rgb.shape[:2]
        assert labels.max() < NUM_LABELS
        np.testing.assert_array_equal(labels, _direct(tiny_segmenter, rgb))
        overlay = _read(out / OVERLAY_DIR / f"{stem}.png")
        np.testing.assert_array_equal(overlay, overlay_labels(rgb, labels))
    assert len(np.unique(_read(out / "a.png"))) > 1  # the test model does not paint one label
    assert json.loads((out / LEGEND).read_text()) == {str(int(lab)): lab.name.lower() for lab in Label}
    _no_partials(out)


def test_shipped_segmenter_grey_and_rgba(tmp_path, capsys, caplog):
    """Default --segmenter: the shipped file; grey is repeated into RGB, RGBA loses its alpha."""
    rgb = _rgb(18, 26, 4)
    grey = rgb[..., 1].copy()
    rgba = np.dstack([rgb, np.full(rgb.shape[:2], 7, np.uint8)])
    files = [_write(tmp_path / "grey.png", grey), _write(tmp_path / "rgba.png", rgba),
             _write(tmp_path / "rgb.jpeg", rgb)]
    out = tmp_path / "out"
    assert main(["segment", *map(str, files), "--out", str(out)]) == 0
    assert "grey image" in caplog.text
    stage = SegmenterStage(WEIGHTS_DIR / GENERAL_SEGMENTER)
    np.testing.assert_array_equal(_read(out / "grey.png"), stage.segment({"c": np.repeat(grey[..., None], 3, 2)})["c"])
    np.testing.assert_array_equal(_read(out / "rgba.png"), stage.segment({"c": rgb})["c"])
    assert _read(out / "rgb.png").shape == rgb.shape[:2]


def test_same_stem_is_refused_before_writing(tmp_path, tiny_segmenter, capsys):
    _write(tmp_path / "a.png", _rgb(8, 8, 1))
    _write(tmp_path / "a.jpg", _rgb(8, 8, 2))
    out = tmp_path / "out"
    assert main(["segment", str(tmp_path), "--out", str(out), "--segmenter", str(tiny_segmenter)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error:") and "a.png" in err and "a.jpg" in err
    assert not out.exists()


def test_output_never_replaces_an_input(tmp_path, tiny_segmenter, capsys):
    img = _write(tmp_path / "a.png", _rgb(8, 8, 1))
    before = img.read_bytes()
    assert main(["segment", str(tmp_path), "--out", str(tmp_path), "--segmenter", str(tiny_segmenter)]) == 1
    assert "is an input image" in capsys.readouterr().err
    assert img.read_bytes() == before


def _bad(kind: str, path: Path) -> Path:
    """A bad input image of ``kind`` at ``path`` (``missing``: none)."""
    if kind == "corrupt":  # a valid header, the data cut short
        data = cv2.imencode(".png", _rgb(16, 16, 5))[1].tobytes()
        path.write_bytes(data[: len(data) // 2])
    elif kind == "not_an_image":
        path.write_bytes(b"hello, I am text\n" * 4)
    elif kind == "16bit":
        assert cv2.imwrite(str(path), (_rgb(8, 8, 6).astype(np.uint16) * 257))
    elif kind == "16bit_grey":
        assert cv2.imwrite(str(path), (_rgb(8, 8, 6)[..., 0].astype(np.uint16) * 257))
    elif kind == "huge":
        side = DEFAULT_LIMITS.max_image_side  # within the side bound, far over the pixel bound
        _huge_png(path, side, side)
    elif kind == "huge_side":
        _huge_png(path, DEFAULT_LIMITS.max_image_side + 1, 1)
    elif kind == "empty":
        path.write_bytes(b"")
    return path


BAD = {"corrupt": "corrupt or truncated", "not_an_image": "neither PNG nor JPEG", "16bit": "16-bit",
       "16bit_grey": "16-bit", "huge": "exceeds the maximum", "huge_side": "per side", "empty": "neither PNG nor JPEG",
       "missing": "no such file"}


@pytest.mark.parametrize("kind", sorted(BAD))
def test_bad_image_is_an_error_naming_it_and_writes_nothing(tmp_path, tiny_segmenter, capsys, kind):
    bad = _bad(kind, tmp_path / "bad.png")
    out = tmp_path / "out"
    assert main(["segment", str(bad), "--out", str(out), "--segmenter", str(tiny_segmenter)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error:") and str(bad) in err and BAD[kind] in err, err
    assert "Traceback" not in err
    assert not out.exists()


def test_bad_image_mid_run_keeps_the_earlier_outputs_complete(tmp_path, tiny_segmenter, capsys):
    src = tmp_path / "in"
    src.mkdir()
    _write(src / "a.png", _rgb(9, 11, 1))
    _bad("corrupt", src / "b.png")  # decoded after a.png
    _write(src / "c.png", _rgb(9, 11, 3))
    out = tmp_path / "out"
    assert main(["segment", str(src), "--out", str(out), "--segmenter", str(tiny_segmenter)]) == 1
    assert "b.png" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["a.png", LEGEND, OVERLAY_DIR]
    assert [p.name for p in (out / OVERLAY_DIR).iterdir()] == ["a.png"]
    assert _read(out / "a.png").shape == (9, 11)
    _no_partials(out)


def test_header_problems_stop_the_run_before_anything_is_written(tmp_path, tiny_segmenter, capsys):
    src = tmp_path / "in"
    src.mkdir()
    _write(src / "a.png", _rgb(9, 11, 1))
    _bad("huge", src / "z.png")  # the last one, found by the header check up front
    out = tmp_path / "out"
    assert main(["segment", str(src), "--out", str(out), "--segmenter", str(tiny_segmenter)]) == 1
    assert "z.png" in capsys.readouterr().err
    assert not out.exists()


def test_skip_bad_skips_and_counts(tmp_path, tiny_segmenter, capsys):
    src = tmp_path / "in"
    src.mkdir()
    _write(src / "a.png", _rgb(9, 11, 1))
    for kind in ("corrupt", "16bit", "huge", "not_an_image"):
        _bad(kind, src / f"{kind}.png")
    out = tmp_path / "out"
    args = ["segment", str(src), "--out", str(out), "--segmenter", str(tiny_segmenter), "--skip-bad"]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert "skipped 4 of 5 images" in err and all(f"{k}.png" in err for k in ("corrupt", "16bit", "huge"))
    assert sorted(p.name for p in out.iterdir()) == ["a.png", LEGEND, OVERLAY_DIR]
    (src / "a.png").unlink()
    out2 = tmp_path / "out2"
    assert main([*args[:2], "--out", str(out2), *args[4:]]) == 1  # nothing left to segment
    assert "none of the 4 images" in capsys.readouterr().err
    assert not out2.exists()


@pytest.mark.parametrize("kind", ["garbage", "missing", "empty_folder"])
def test_bad_segmenter_or_no_images(tmp_path, capsys, kind):
    img = _write(tmp_path / "a.png", _rgb(8, 8, 1))
    seg = tmp_path / "seg.safetensors"
    args = ["segment", str(img), "--out", str(tmp_path / "out"), "--segmenter", str(seg)]
    if kind == "garbage":
        seg.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{not json}      ")
    elif kind == "empty_folder":
        (tmp_path / "empty").mkdir()
        args[1] = str(tmp_path / "empty")
    assert main(args) == 1
    err = capsys.readouterr().err
    assert err.startswith("error:") and (str(tmp_path / "empty") if kind == "empty_folder" else str(seg)) in err, err
    assert not (tmp_path / "out").exists()
