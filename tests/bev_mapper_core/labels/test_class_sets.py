"""Scoring across class sets: Cam2BEV's road / vehicle / static against the standard seven."""

from __future__ import annotations

import json

import pytest

from bags.cli.main import main as bev_bag
from bev_mapper_core.errors import ConfigError
from bev_mapper_core.labels.classes import BEV_CLASS_NAMES, class_cover

pytestmark = [pytest.mark.slow]


def test_class_cover_by_definition():
    std = BEV_CLASS_NAMES
    assert class_cover("vehicle", std) == ("vehicle",)
    assert class_cover("road", std) == ("drivable",)  # same label ids: road, divider, crossing
    assert class_cover("drivable", ("road", "vehicle", "static")) == ("road",)
    assert class_cover("static", std) is None  # no obstacle / building / terrain layer
    assert class_cover("lane_divider", ("road", "vehicle", "static")) is None  # road is wider
    with pytest.raises(ConfigError):
        class_cover("lava", std)


@pytest.fixture(scope="module")
def small_bags(tmp_path_factory):
    d = tmp_path_factory.mktemp("classsets")
    for rig in ("front1", "cam2bev4"):
        assert bev_bag(["synth", str(d / rig), "--rig", rig, "--frames", "3", "--seed", "950000002",
                        "--scale", "0.5"]) == 0
    return d


def _replay(bag, out, *flags):
    assert bev_bag(["replay", str(bag), "--out", str(out), "--method", "ipm", "--no-pictures", *flags]) == 0
    return json.loads((out / "metrics.json").read_text())


def test_replay_maps_classes_by_definition_and_names_the_unscored(small_bags, tmp_path, capsys):
    m = _replay(small_bags / "front1", tmp_path / "c2b", "--classes", "road", "vehicle", "static")
    err = capsys.readouterr().err
    assert m["miou_classes"] == ["road", "vehicle"]
    assert m["unscored_classes"] == ["static"]
    assert m["class_map"] == {"road": ["drivable"]}
    assert "NOT SCORED: ['static']" in err and "road = drivable" in err
    # road is scored against the drivable layer: the same IoU as drivable predicted under its own name
    ref = _replay(small_bags / "front1", tmp_path / "std", "--classes", "drivable", "vehicle")
    assert m["classes"]["road"] == ref["classes"]["drivable"]
    assert m["miou"] == pytest.approx(ref["miou"])


def test_cam2bev_bags_carry_both_class_sets(small_bags, tmp_path):
    m = _replay(small_bags / "cam2bev4", tmp_path / "c2b", "--classes", "road", "vehicle", "static")
    assert m["miou_classes"] == ["road", "vehicle", "static"] and m["unscored_classes"] == []
    assert m["classes"]["static"]["iou"] is not None
    std = _replay(small_bags / "cam2bev4", tmp_path / "std")
    assert std["miou_classes"] == list(BEV_CLASS_NAMES) and std["class_map"] == {}
