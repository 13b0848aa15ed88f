"""``bev-bag replay --label-map`` and ``bev-train --label-map`` on bags whose label topics hold
another segmenter's ids (or Cam2BEV's colours): the same metrics and training frames as the
native labels they stand for."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from bag_helpers import replay_ipm
from label_map_helpers import equivalent_native, relabel_bag, to_upstream

from bags.cli.train.train import train_parser
from bags.io.train_data import bag_frameset, bag_rig_grid
from bev_mapper_core.labels.classes import NUM_LABELS
from bev_mapper_core.training.config import TrainConfig

#: metrics.json entries that must not depend on how the labels were spelled
SCORES = ("frames", "frames_scored", "classes", "miou", "map", "iou_by_range", "occlusion", "calibration")
#: a one-to-one YAML map: upstream id 200 + k means native label k
SHIFT = 200


def _metrics(out) -> dict:
    return json.loads((out / "metrics.json").read_text())


def _assert_same_scores(got: dict, want: dict) -> None:
    for key in SCORES:
        assert got[key] == want[key], key
    assert got["frames_scored"] > 0 and got["decode_errors"] == 0


@pytest.fixture(scope="module")
def equivalent(small_drive_mcap, tmp_path_factory):
    """The small drive with its labels as a Cityscapes-style segmenter can give them (no lane
    dividers, crossings or curbs), and its native IPM replay: (bag, metrics)."""
    bag, _ = small_drive_mcap
    root = tmp_path_factory.mktemp("label_map_equivalent")
    eq = relabel_bag(bag, root / "equivalent", lambda a: (equivalent_native(a), "mono8"))
    assert replay_ipm(eq, root / "out", "--no-pictures", "--no-report") == 0
    return eq, _metrics(root / "out")


def test_replay_with_a_yaml_label_map_scores_as_native(small_drive_mcap, tmp_path):
    """Every native label under another id, a YAML file mapping them back: the very metrics of the
    native replay (all seven classes, lane dividers included)."""
    bag, native_out = small_drive_mcap
    spec = tmp_path / "shifted.yaml"
    spec.write_text(yaml.safe_dump({"labels": {SHIFT + k: name for k, name in enumerate(
        ["unlabeled", "road", "lane_divider", "ped_crossing", "road_boundary", "sidewalk", "vehicle",
         "pedestrian", "obstacle", "building", "terrain"])}}))
    assert NUM_LABELS == 11
    shifted = relabel_bag(bag, tmp_path / "shifted", lambda a: ((a + SHIFT).astype(np.uint8), "mono8"))
    assert replay_ipm(shifted, tmp_path / "out", "--label-map", str(spec), "--no-pictures", "--no-report") == 0
    got = _metrics(tmp_path / "out")
    _assert_same_scores(got, _metrics(native_out))
    assert got["label_map"] == str(spec) and _metrics(native_out)["label_map"] == "native"


@pytest.mark.parametrize("scheme", ["cityscapes_ids", "cam2bev"])
def test_replay_with_a_preset_scores_as_the_equivalent_native(equivalent, small_drive_mcap, tmp_path, scheme):
    """Cityscapes ids (mono8) and Cam2BEV's palette (rgb8 label images): the metrics of the native
    labels they stand for."""
    bag, _ = small_drive_mcap
    _, want = equivalent
    enc = "rgb8" if scheme == "cam2bev" else "mono8"
    upstream = relabel_bag(bag, tmp_path / scheme, lambda a: (to_upstream(a, scheme), enc))
    assert replay_ipm(upstream, tmp_path / "out", "--label-map", scheme, "--no-pictures", "--no-report") == 0
    got = _metrics(tmp_path / "out")
    _assert_same_scores(got, want)
    assert got["label_map"] == scheme
    if scheme == "cam2bev":  # the same bag read as native ids: every label image refused, counted
        assert replay_ipm(upstream, tmp_path / "wrong", "--no-pictures", "--no-report") == 1
        wrong = _metrics(tmp_path / "wrong")
        assert wrong["decode_errors"] > 0 and not wrong["complete"]
        assert "label images must be mono8 or 8UC1" in json.dumps(wrong["input_problems"])


def test_bev_train_reads_bag_labels_through_the_label_map(equivalent, small_drive_mcap, tmp_path):
    """``bev-train --bag ... --label-map cityscapes_train_ids``: the flag reaches TrainConfig, and the
    bag's frames are the equivalent native ones."""
    bag, _ = small_drive_mcap
    eq_bag, _ = equivalent
    args = vars(train_parser().parse_args(["--bag", "b", "--val-bag", "v", "--label-map", "cityscapes_train_ids"]))
    assert TrainConfig.from_dict(args).label_map == "cityscapes_train_ids"
    assert TrainConfig.from_dict(vars(train_parser().parse_args(["--bag", "b"]))).label_map == "native"
    upstream = relabel_bag(bag, tmp_path / "train_ids", lambda a: (to_upstream(a, "cityscapes_train_ids"), "mono8"))
    rig, grid = bag_rig_grid(bag)
    classes = ("drivable", "sidewalk", "vehicle")
    got = bag_frameset([upstream], classes, rig, grid, label_map_spec="cityscapes_train_ids")
    want = bag_frameset([eq_bag], classes, rig, grid)
    assert len(got) == len(want) > 0
    np.testing.assert_array_equal(got.labels, want.labels)
    np.testing.assert_array_equal(got.target, want.target)
