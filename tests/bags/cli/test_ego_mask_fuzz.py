"""Issue #41: ``bev-bag replay --ego-mask CAM=PNG`` with each kind of bad mask file.

A table of mask files (wrong size, not binary, colours, missing, empty, a directory, a PNG whose
header claims 30000x30000 px over 100 bytes, an unknown camera, the option given twice, the
only camera masked whole) and of acceptable ones (16-bit, RGBA with equal channels): each bad
one ends the replay with an ``error:`` line naming the problem and no output; each good one
replays. (The core's mask checks: tests/bev_mapper_core/geometry/test_ego_mask.py; the node's
``ego_mask.<camera>``: tests/bev_mapper_ros/test_node_ego_mask.py.)
"""

from __future__ import annotations

import contextlib
import io

import compressed_cases as C
import cv2
import numpy as np
import pytest

from bags.cli.main import main

pytest.importorskip("bev_mapper_core.synth")

W, H = 100, 56  # front1 at scale 0.25
GRID = ["--grid-x-min", "-10", "--grid-x-max", "10", "--grid-y-min", "-5", "--grid-y-max", "5",
        "--grid-res", "0.5"]
HOOD = np.zeros((H, W), np.uint8)
HOOD[-5:] = 255


def _grey(hood_value: int = 255, stray: int | None = None, size=(W, H)) -> np.ndarray:
    img = np.zeros(size[::-1], np.uint8)
    img[-5:] = hood_value
    if stray is not None:
        img[0, 0] = stray
    return img


#: name -> (what the file holds: array, bytes, or None for no file; expected error words or None)
MASKS = {
    "wrong size": (_grey(size=(50, 28)), "is 50x28"),
    "not binary": (_grey(stray=7), "not binary"),
    "colours": (np.dstack([HOOD, HOOD * 0, HOOD]), "has colours"),
    "missing": (None, "no such file"),
    "empty file": (b"", "not an image"),
    "PNG header claiming 30000x30000": (C.png_claiming(30000, 30000), "not an image"),
    "whole image (the only camera)": (np.full((H, W), 255, np.uint8), "nothing would be mapped"),
    "16-bit 0/65535": (HOOD.astype(np.uint16) * 257, None),
    "RGBA, equal channels": (np.dstack([HOOD] * 4), None),
    "all zero": (HOOD * 0, None),
}


@pytest.fixture(scope="module")
def bag(tmp_path_factory):
    out = tmp_path_factory.mktemp("ego_fuzz") / "bag"
    assert main(["synth", str(out), "--rig", "front1", "--scale", "0.25", "--frames", "2", "--seed", "3",
                 *GRID]) == 0
    return out


def replay(bag, out, *masks: str) -> tuple[int, str]:
    argv = ["replay", str(bag), "--out", str(out), "--quiet", "--method", "ipm", "--no-pictures", "--no-report"]
    for m in masks:
        argv += ["--ego-mask", m]
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = main(argv)
    assert "Traceback" not in err.getvalue()
    return rc, err.getvalue()


@pytest.mark.parametrize("name", list(MASKS))
def test_mask_file(bag, tmp_path, name):
    content, refused = MASKS[name]
    path = tmp_path / "mask.png"
    if isinstance(content, bytes):
        path.write_bytes(content)
    elif content is not None:
        assert cv2.imwrite(str(path), content)
    rc, err = replay(bag, tmp_path / "out", f"front={path}")
    if refused is None:
        assert rc == 0, err
        return
    assert rc == 1 and "error: " in err and refused in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_mask_arguments(bag, tmp_path):
    """An unknown camera, a directory, no PNG and the option twice: each an ``error:`` of its own."""
    cv2.imwrite(str(tmp_path / "hood.png"), HOOD)
    hood = tmp_path / "hood.png"
    for masks, said in ((["roof=" + str(hood)], "no camera of rig"), ([f"front={tmp_path}"], "no such file"),
                        (["front="], "CAM=PNG"), ([f"front={hood}", f"front={hood}"], "given twice")):
        rc, err = replay(bag, tmp_path / "out", *masks)
        assert rc == 1 and said in err, (masks, err)
