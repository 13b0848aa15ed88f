"""``bev-bag propose-mask`` finds a hood painted into a synthetic drive, and ``bev-bag replay
--ego-mask`` with its proposal no longer maps the hood as a vehicle; bad masks are refused."""

import json
import pathlib

import cv2
import numpy as np
import pytest

from bags.cli.main import main
from bags.io.writer import write_drive
from bags.replay import METRICS_FILE
from bev_mapper_core.geometry.grid import BevGrid
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.labels.classes import BEV_CLASSES, Label
from bev_mapper_core.synth import generate_drive
from bev_mapper_core.synth.config import SynthConfig

GRID = BevGrid(x_min=-20, x_max=20, y_min=-10, y_max=10, resolution=0.25)
HOOD = {"front": 14, "back": 10}  # camera -> rows of ego body at the image's bottom
HOOD_RGB = (40, 40, 48)


def _with_hood(frames):
    for f in frames:
        for cam, rows in HOOD.items():
            f.cameras[cam].labels[-rows:] = Label.VEHICLE
            f.cameras[cam].rgb[-rows:] = HOOD_RGB
        yield f


@pytest.fixture(scope="module")
def hood_bag(tmp_path_factory) -> pathlib.Path:
    rig = preset_rig("surround6").scaled(0.5)  # 200x112 images
    out = tmp_path_factory.mktemp("hood") / "drive"
    frames = generate_drive(rig, GRID, SynthConfig(frames=40, seed=11), BEV_CLASSES)
    write_drive(out, rig, GRID, _with_hood(frames), classes=BEV_CLASSES)
    return out


def _near(out: pathlib.Path) -> dict:
    """The replay's IoU per class within 10 m of the ego."""
    return json.loads((out / METRICS_FILE).read_text())["iou_by_range"]["0-10"]


def test_propose_mask_finds_the_hood(hood_bag, tmp_path, capsys):
    assert main(["propose-mask", str(hood_bag), "--out", str(tmp_path / "m")]) == 0
    text = capsys.readouterr().out
    assert "CHECK" in text and "--ego-mask front=" in text
    for cam in ("front", "back"):
        mask = cv2.imread(str(tmp_path / "m" / f"{cam}.png"), cv2.IMREAD_UNCHANGED) > 0
        truth = np.zeros_like(mask)
        truth[-HOOD[cam]:] = True
        assert (mask & truth).sum() > 0.9 * truth.sum(), cam
        assert (mask & ~truth).sum() < 0.1 * truth.sum(), cam
    for cam in ("front_left", "back_right"):  # no hood painted: (nearly) nothing proposed
        mask = cv2.imread(str(tmp_path / "m" / f"{cam}.png"), cv2.IMREAD_UNCHANGED) > 0
        assert mask.mean() < 0.02, cam
    # existing masks are kept unless --force
    assert main(["propose-mask", str(hood_bag), "--out", str(tmp_path / "m")]) == 1


def test_replay_with_the_proposed_masks_drops_the_hood(hood_bag, tmp_path):
    assert main(["propose-mask", str(hood_bag), "--out", str(tmp_path / "m")]) == 0
    base = ["replay", str(hood_bag), "--quiet", "--method", "ipm", "--no-pictures", "--no-report"]
    assert main([*base, "--out", str(tmp_path / "plain")]) == 0
    masks = [a for cam in HOOD for a in ("--ego-mask", f"{cam}={tmp_path / 'm' / f'{cam}.png'}")]
    assert main([*base, "--out", str(tmp_path / "masked"), *masks]) == 0
    plain, masked = _near(tmp_path / "plain"), _near(tmp_path / "masked")
    assert plain["vehicle"] == 0.0  # no vehicle near the ego, but the hood mapped as one
    assert masked["vehicle"] is None  # none in the GT and none mapped
    assert masked["drivable"] > plain["drivable"] - 0.05  # the road in front is kept


def test_bad_masks_refused_by_replay(hood_bag, tmp_path, capsys):
    base = ["replay", str(hood_bag), "--quiet", "--method", "ipm", "--no-pictures", "--no-report",
            "--max-frames", "1"]
    cv2.imwrite(str(tmp_path / "small.png"), np.full((10, 10), 255, np.uint8))
    grey = np.zeros((112, 200), np.uint8)
    grey[-5:] = 255
    grey[0, 0] = 3
    cv2.imwrite(str(tmp_path / "grey.png"), grey)
    cases = {"small.png": "10x10", "grey.png": "not binary", "missing.png": "no such file"}
    for i, (name, said) in enumerate(cases.items()):
        assert main([*base, "--out", str(tmp_path / f"o{i}"), "--ego-mask", f"front={tmp_path / name}"]) == 1
        err = capsys.readouterr().err
        assert "error:" in err and said in err and "Traceback" not in err, err
    assert main([*base, "--out", str(tmp_path / "o9"), "--ego-mask", "front"]) == 1
    assert "CAM=PNG" in capsys.readouterr().err
