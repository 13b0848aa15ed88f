"""``bev-train --method segmenter --real ...`` and ``bev-train eval --method segmenter --real ...``
on tiny fixtures (issue #24): bad datasets end with ``error:`` and leave no run directory, the
eval prints per-class IoU that can be checked by hand, and it scores as experiments/eval_camvid.py."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from real_data_helpers import constant_segmenter, write_camvid, write_folder

from bags.cli.train.main import main
from bev_mapper_core.datasets import CamVid, FolderDataset
from bev_mapper_core.labels.classes import Label
from bev_mapper_core.labels.spaces import IGNORE
from bev_mapper_core.methods.segmenter.weights import save_segmenter

torch.set_num_threads(1)
REPO = Path(__file__).resolve().parents[3]
TINY_RUN = ["--method", "segmenter", "--rig", "front1", "--classes", "standard", "--train-drives", "1", "--val-drives", "1",
            "--frames-per-drive", "2", "--stride", "2", "--seg-width", "32", "--epochs", "1", "--batch", "1",
            "--threads", "1", "--no-progress", "--real-batch", "2"]


@pytest.fixture(scope="module")
def drive_cache(tmp_path_factory):
    return tmp_path_factory.mktemp("cache")


@pytest.mark.parametrize("damage", ["no_folder", "missing_annotation", "bad_spec",
                                    # found while reading the frames, after the drives are rendered
                                    pytest.param("unreadable_image", marks=pytest.mark.slow),
                                    pytest.param("id_outside", marks=pytest.mark.slow)])
def test_a_broken_real_dataset_is_an_error_line_and_leaves_no_run_directory(tmp_path, capsys, damage, drive_cache):
    cam = write_camvid(tmp_path / "camvid", n=2)
    bad = {"no_folder": tmp_path / "nowhere" / "train", "missing_annotation": cam / "trainannot" / "f1.png",
           "unreadable_image": cam / "train" / "f1.png", "id_outside": cam / "trainannot" / "f0.png"}.get(damage)
    spec = f"camvid:{tmp_path / 'nowhere'}" if damage == "no_folder" else f"camvid:{cam}"
    if damage == "missing_annotation":
        bad.unlink()
    elif damage == "unreadable_image":
        bad.write_bytes(b"not a png")
    elif damage == "id_outside":
        import cv2

        cv2.imwrite(str(bad), np.full((36, 48), 12, np.uint8))
    elif damage == "bad_spec":
        spec = f"kitti:{cam}"
    out = tmp_path / "run"
    status = main(TINY_RUN + ["--cache", str(drive_cache), "--out", str(out), "--real", spec])
    err = capsys.readouterr().err
    assert status == 1 and err.startswith("error: ") and "Traceback" not in err, err
    assert (str(bad) in err) if bad is not None else "kitti:" in err
    assert not out.exists()


def test_eval_real_prints_per_class_iou_checkable_by_hand(tmp_path, capsys):
    """A segmenter that predicts ROAD everywhere: Road's IoU is the road share of the labelled
    pixels, every other class present 0, classes in neither truth nor prediction '-'."""
    cam, team = write_camvid(tmp_path / "camvid"), write_folder(tmp_path / "team")
    seg = save_segmenter(constant_segmenter(int(Label.ROAD)), tmp_path / "road.safetensors")
    out = tmp_path / "eval.json"
    status = main(["eval", "--method", "segmenter", "--real", f"camvid:{cam}", "--real", f"folder:{team}", "--split",
                   "test", "--segmenter", str(seg), "--threads", "1", "--timing-frames", "1", "--json", str(out)])
    text = capsys.readouterr().out
    assert status == 0, text
    labs = np.stack([s.labels for s in CamVid(cam, "test")])
    road = 100 * (labs == 3).sum() / (labs != IGNORE).sum()
    flabs = np.stack([s.labels for s in FolderDataset(team)])
    froad = 100 * (flabs == Label.ROAD).sum() / (flabs != IGNORE).sum()
    assert f"Sky 0.0  Building 0.0  Pole -  Road {road:.1f}  Pavement 0.0  Tree -" in text
    assert f"common: road {road:.1f}  sidewalk 0.0  vehicle 0.0  pedestrian -  building 0.0  mean {road / 4:.1f}" in text
    assert f"common: road {froad:.1f}  sidewalk 0.0  vehicle 0.0  pedestrian -  building 0.0" in text
    assert "ms/frame (48x36, 1 thread(s))" in text
    doc = json.loads(out.read_text())
    cam_res, team_res = doc["results"]
    assert cam_res["dataset"] == f"camvid:{cam}" and cam_res["split"] == "test" and cam_res["frames"] == 3
    assert cam_res["per_class"]["Road"] == round(road, 2) and cam_res["per_class"]["Pole"] is None
    assert team_res["per_class"]["road"] == round(froad, 2) and doc["cpu_ms_per_frame"] > 0


def test_eval_real_equals_experiments_eval_camvid(tmp_path, capsys):
    cam = write_camvid(tmp_path / "camvid")
    torch.manual_seed(5)
    from real_data_helpers import TINY_SEG

    from bev_mapper_core.methods.segmenter.model import Segmenter

    seg = save_segmenter(Segmenter(TINY_SEG).eval(), tmp_path / "random.safetensors")
    assert main(["eval", "--method", "segmenter", "--real", f"camvid:{cam}", "--segmenter", str(seg), "--threads", "1",
                 "--timing-frames", "1", "--json", str(tmp_path / "a.json")]) == 0
    spec = importlib.util.spec_from_file_location("eval_camvid", REPO / "experiments" / "eval_camvid.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main([str(seg), "--camvid", str(cam), "--timing-frames", "1", "--json", str(tmp_path / "b.json")]) == 0
    a, b = json.loads((tmp_path / "a.json").read_text())["results"][0], json.loads((tmp_path / "b.json").read_text())
    assert a["per_class"] == b["per_class"] and a["common"] == b["common"] and a["frames"] == b["frames"] == 3
    capsys.readouterr()


def test_eval_real_refuses_other_methods_and_missing_splits(tmp_path, capsys):
    cam = write_camvid(tmp_path / "camvid", splits=("train",))
    assert main(["eval", "--method", "ipm", "--real", f"camvid:{cam}"]) == 1
    assert "use --method segmenter" in capsys.readouterr().err
    assert main(["eval", "--method", "segmenter", "--real", f"camvid:{cam}", "--split", "test"]) == 1
    assert "no 'test' split" in capsys.readouterr().err
    assert main(["eval", "--method", "segmenter", "--real", f"camvid:{tmp_path / 'nowhere'}"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: ") and str(tmp_path / "nowhere" / "test") in err and "Traceback" not in err
