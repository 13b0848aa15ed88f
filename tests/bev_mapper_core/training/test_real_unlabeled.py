"""Real camera images as unlabeled frames (issue #26): CamVid's training images become unlabeled
front frames of S2G2, beside synthetic unlabeled drives."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from real_data_helpers import write_camvid

from bev_mapper_core.errors import ConfigError
from bev_mapper_core.geometry.rig import preset_rig
from bev_mapper_core.training.config import TrainConfig
from bev_mapper_core.training.data import FrameSet, resize_rgb
from bev_mapper_core.training.real_unlabeled import crop_to_aspect, join_unlabeled, real_unlabeled_frameset
from bev_mapper_core.training.sources import DataNeeds, TrainData

RIG = preset_rig("front1")


def test_crop_to_aspect_keeps_the_middle():
    img = np.arange(12 * 16 * 3, dtype=np.uint8).reshape(12, 16, 3)
    wide = crop_to_aspect(img, 16, 9)  # 4:3 -> 16:9: rows 1..10 of 12 (9 rows, centred)
    np.testing.assert_array_equal(wide, img[1:10])
    tall = crop_to_aspect(img, 1, 1)  # -> square: the middle 12 columns
    np.testing.assert_array_equal(tall, img[:, 2:14])
    assert crop_to_aspect(img, 4, 3) is img or crop_to_aspect(img, 4, 3).shape == img.shape


def test_camvid_training_images_become_unlabeled_front_frames(tmp_path):
    root = write_camvid(tmp_path / "camvid", n=3)
    size = (18, 32)
    fs = real_unlabeled_frameset(f"camvid:{root}", RIG, DataNeeds(image_size=size, rgb=True))
    assert len(fs) == 3 and fs.rgb.shape == (3, 1, 18, 32, 3) and fs.camera_names == RIG.names
    from bev_mapper_core.datasets import open_dataset

    first = open_dataset(f"camvid:{root}", "train").read(0).image  # the train split, in order
    W, H = RIG.cameras[0].model.image_size
    np.testing.assert_array_equal(fs.rgb[0, 0], resize_rgb(crop_to_aspect(first, W, H), size))
    assert len(real_unlabeled_frameset(f"camvid:{root}", RIG, DataNeeds(image_size=size, rgb=True), limit=2)) == 2
    batch = next(TrainData(fs, fs, fs).batches(1, 0, 0))["unlabeled"]
    assert set(batch) == {"images", "rgb", "index"}
    joined = join_unlabeled([fs, fs])
    assert len(joined) == 6 and joined.rgb.shape == (6, 1, 18, 32, 3)
    with pytest.raises(ConfigError, match="one-camera rig"):
        real_unlabeled_frameset(f"camvid:{root}", preset_rig("surround6"), DataNeeds(image_size=size, rgb=True))
    with pytest.raises(ConfigError, match="RGB input"):
        real_unlabeled_frameset(f"camvid:{root}", RIG, DataNeeds(image_size=size))
    other = FrameSet(np.zeros((1, 1, 9, 16), np.uint8), np.zeros((1, 0, 1, 1), bool), np.zeros((1, 1, 1), bool),
                     camera_names=RIG.names, rgb=np.zeros((1, 1, 9, 16, 3), np.uint8))
    with pytest.raises(ConfigError, match="image sizes"):
        join_unlabeled([fs, other])


def test_config_checks():
    base = dict(method="s2g2", rig="front1", input="rgb", grid="ahead")
    with pytest.raises(ConfigError, match="unlabeled_real_frames needs unlabeled_real"):
        TrainConfig.from_dict({**base, "unlabeled_real_frames": 3})
    with pytest.raises(ConfigError, match="does not mix with bags"):
        TrainConfig.from_dict({**base, "unlabeled_real": "camvid:x", "unlabeled_bag": ["a.mcap"]})
    with pytest.raises(ConfigError, match="integer >= 0"):
        TrainConfig.from_dict({**base, "unlabeled_real": "camvid:x", "unlabeled_real_frames": -1})


@pytest.mark.slow
def test_s2g2_trains_with_real_and_synthetic_unlabeled_frames(tmp_path, capsys):
    from bags.cli.train.main import main as bev_train

    root = write_camvid(tmp_path / "camvid", n=3)
    run = dict(method="s2g2", rig="front1", input="rgb", classes="drivable,vehicle", epochs=1, batch=2,
               lr=3e-3, seed=3, train_drives=1, val_drives=1, unlabeled_drives=1, frames_per_drive=4, stride=2,
               threads=1, input_width=32, width_mult=0.25, depth_mult=0.25, encoder_stages=3, bev_downsample=4,
               decoder_channels=8, consistency_ramp_steps=2, grid=[0.0, 16.0, -8.0, 8.0, 0.5], encoder_init="none",
               progress=False, cache=str(tmp_path / "cache"))
    cfg_file = tmp_path / "run.yaml"
    cfg_file.write_text(yaml.safe_dump(run))
    out = tmp_path / "run"
    assert bev_train(["--config", str(cfg_file), "--unlabeled-real", f"camvid:{root}", "--out", str(out)]) == 0
    log = capsys.readouterr().out
    assert f"3 real unlabeled frames from camvid:{root}" in log and "4 training / 7 unlabeled" in log  # 4 synthetic + 3 real
    doc = json.loads((out / "last.json").read_text())
    assert doc["config"]["unlabeled_real"] == f"camvid:{root}" and (out / "last.safetensors").is_file()
