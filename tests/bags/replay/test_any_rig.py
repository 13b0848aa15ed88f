"""Issue #38: a bag of a rig that is no preset (five cameras of 4:3 images, other mountings: a
seeded random rig no training drive used) replays with the default method, on label images and
on JPEG-compressed RGB cameras: the shipped weights for any rig, behind the segmenter on RGB.
"""

from __future__ import annotations

import json

import pytest

from bags.cli.main import main

pytest.importorskip("bev_mapper_core.synth")
pytest.importorskip("torch")

HELD_OUT_RIG = "random-950000044"  # 5 cameras, 404 x 304 (4:3)


@pytest.mark.slow  # renders a drive of five cameras and runs the learned default
def test_a_rig_no_training_drive_used_maps_with_the_default_method(tmp_path, capsys):
    bag = tmp_path / "drive"
    assert main(["synth", str(bag), "--rig", HELD_OUT_RIG, "--frames", "2", "--seed", "950000010", "--compressed"]) == 0
    scores = {}
    for kind in ("labels", "rgb"):
        out = tmp_path / kind
        assert main(["replay", str(bag), "--out", str(out), "--quiet", "--input", kind]) == 0, capsys.readouterr().err
        m = json.loads((out / "metrics.json").read_text())
        assert m["method"] == "bimapper" and m["weights"] == "bimapper_any_labels.safetensors"
        assert m["rig"]["name"] == HELD_OUT_RIG and len(m["rig"]["cameras"]) == 5
        assert m["frames_scored"] == 2 and m["complete"]
        scores[kind] = m["miou"]
    assert scores["labels"] > 0.6 and scores["rgb"] > 0.3  # it maps: true labels well, RGB through the segmenter
    assert main(["replay", str(bag), "--out", str(tmp_path / "ipm"), "--quiet", "--method", "ipm"]) == 0
    ipm = json.loads((tmp_path / "ipm" / "metrics.json").read_text())
    assert ipm["weights"] is None and scores["labels"] > ipm["miou"]  # the learned default beats IPM here too
