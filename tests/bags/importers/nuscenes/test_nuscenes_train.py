"""Imported nuScenes drives into ``bev-train``: the official split each bag records, RGB frames
from the CompressedImage cameras, unscored classes and unknown cells masked per class, and a short
training run on the ``mini_train`` bags validated on the ``mini_val`` ones.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from nuscenes_helpers import IMG_H, IMG_W, write_nuscenes

from bags.cli.main import main as bag_main
from bags.cli.train.main import main as bev_train
from bags.importers.nuscenes.splits import scene_split
from bags.io.reader import BagReader
from bags.io.train_data import bag_frameset, bag_rig_grid, select_split
from bev_mapper_core.errors import ConfigError

# 32 m x 16 m at 0.5 m (64 x 32 cells): holds the fixture's box below the point filter at (-12, -6)
GRID = ("--grid-x-min", "-16", "--grid-x-max", "16", "--grid-y-min", "-8", "--grid-y-max", "8", "--grid-res", "0.5")


@pytest.fixture(scope="module")
def drives(tmp_path_factory) -> Path:
    """``mapped/`` (scene-0061: mini_train, scene-0103: mini_val) and ``nomap/scene-0061`` (no map
    expansion: the map classes unscored)."""
    root = tmp_path_factory.mktemp("drives")
    data = write_nuscenes(tmp_path_factory.mktemp("nus"), sweeps=False)
    assert bag_main(["import", "nuscenes", str(data), "--version", "v1.0-mini", "--split", "all",
                     "--out", str(root / "mapped"), *GRID]) == 0
    shutil.rmtree(data / "maps")
    assert bag_main(["import", "nuscenes", str(data), "--version", "v1.0-mini", "--scene", "scene-0061",
                     "--out", str(root / "nomap"), *GRID]) == 0
    return root


def test_each_bag_records_its_official_split(drives):
    for scene, split in (("scene-0061", "mini_train"), ("scene-0103", "mini_val")):
        with BagReader(drives / "mapped" / scene) as r:
            assert r.custom_data["bev_mapper.split"] == split
    assert [p.name for p in select_split([drives / "mapped"], "mini_val")] == ["scene-0103"]
    assert [str(p) for p in select_split([drives], "mini_train")] == [
        str(drives / "mapped" / "scene-0061"), str(drives / "nomap" / "scene-0061")]
    with pytest.raises(ConfigError, match="no bag of split 'val'"):
        select_split([drives], "val")
    # the devkit's lists: scene-0103 is in val of v1.0-trainval, scene-0061 in train, scene-0077 in test
    assert (scene_split("v1.0-trainval", "scene-0103"), scene_split("v1.0-trainval", "scene-0061"),
            scene_split("v1.0-test", "scene-0077"), scene_split("v1.0-mini", "scene-0061")) == (
        "val", "train", "test", "mini_train")


def test_rgb_frames_with_unscored_classes_and_unknown_cells_masked_per_class(drives):
    bag = drives / "nomap" / "scene-0061"
    rig, grid = bag_rig_grid(bag)
    assert len(rig.names) == 6 and grid.shape == (32, 64)
    fs = bag_frameset([bag, drives / "mapped" / "scene-0061"], ("drivable", "vehicle"), rig, grid,
                      (IMG_H // 2, IMG_W // 2), rgb=True, labels=False)
    assert len(fs) == 8 and fs.rgb.shape == (8, 6, IMG_H // 2, IMG_W // 2, 3) and fs.rgb.any()
    assert fs.class_mask is not None
    # drivable has no source in the first bag: unknown everywhere there, not "no road"; known in the other
    assert not fs.class_mask[:4, 0].any() and not fs.target[:4, 0].any()
    assert fs.class_mask[4:, 0].all() and fs.target[4:, 0].any()
    # vehicle: unknown exactly on the GT layer's -1 cells (the car below the point filter), known elsewhere
    with BagReader(bag) as r:
        known = np.stack([f.gt_known[f.gt_classes.index("vehicle")]
                          for f in r.frames(rgb=True, labels=False, gt=True, odom=False) if f.gt is not None])
    assert np.array_equal(fs.class_mask[:4, 1], known) and np.array_equal(fs.class_mask[4:, 1], known)
    assert 0 < (~known).sum() < known.size // 20
    assert np.array_equal(fs.mask, fs.class_mask.any(1)) and fs.mask[4:].all()  # some class known there
    # a bag without that metadata still must have every requested class
    with pytest.raises(ConfigError, match="no GT topics for classes"):
        bag_frameset([bag], ("drivable", "road"), rig, grid, rgb=True, labels=False)
    # a model that reads label images cannot train on these bags
    with pytest.raises(ConfigError, match="no label images"):
        bag_frameset([bag], ("vehicle",), rig, grid)
    # a class no bag has a source for cannot be trained at all
    with pytest.raises(ConfigError, match="nothing to train them on"):
        bag_frameset([bag], ("drivable",), rig, grid, rgb=True, labels=False)


@pytest.mark.slow  # a training run
def test_bev_train_trains_on_the_train_split_and_validates_on_val(drives, tmp_path, capsys):
    out = tmp_path / "run"
    rc = bev_train(["--method", "bimapper", "--input", "rgb", "--bag", str(drives), "--split", "mini_train",
                    "--val-split", "mini_val", "--classes", "drivable,vehicle,pedestrian", "--epochs", "1",
                    "--batch", "2", "--input-width", "48", "--gv-hidden", "16", "--threads", "1",
                    "--out", str(out), "--no-progress"])
    log = capsys.readouterr().out
    assert rc == 0, log
    assert (out / "best.safetensors").is_file()
    lines = [ln for ln in log.splitlines() if ln.startswith("data: ")]
    assert f"data: train bag {drives / 'mapped' / 'scene-0061'} (split mini_train): 4 frames" in lines
    assert f"data: train bag {drives / 'nomap' / 'scene-0061'} (split mini_train): 4 frames" in lines
    assert f"data: val bag {drives / 'mapped' / 'scene-0103'} (split mini_val): 4 frames" in lines
    assert not any("scene-0103" in ln for ln in lines if ln.startswith("data: train"))
    train_line = next(ln for ln in lines if ln.startswith("data: train: "))
    # half the training frames (the bag without the map) have no drivable GT: masked, not zero
    assert train_line.startswith("data: train: 8 frames from 2 bag(s); unknown ground truth left out per class: "
                                 "drivable 50 %")
    assert '"epoch": 1' in log


def test_split_flags_are_checked_before_any_work(drives, tmp_path, capsys):
    base = ["--method", "bimapper", "--input", "rgb", "--bag", str(drives), "--out", str(tmp_path / "r"),
            "--no-progress", "--threads", "1"]
    for extra, msg in ((["--split", "mini_train"], "needs the held-out split"),
                       (["--split", "mini_train", "--val-split", "mini_train"], "are both 'mini_train'"),
                       (["--split", "train", "--val-split", "val"], "no bag of split 'train'")):
        assert bev_train(base + extra) == 1
        assert msg in capsys.readouterr().err
