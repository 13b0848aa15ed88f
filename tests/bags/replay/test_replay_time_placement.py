"""Replay with each camera at its own time (issue #38): on a drive whose cameras fire 43 ms apart
(``bev-bag synth --stagger-ms``) the placement is counted and maps closer to the ground truth; on
a drive whose cameras share the frame's stamp the outputs are today's; without odometry, the
replay maps as today and says so once."""

from __future__ import annotations

import pytest
from bag_helpers import replay_ipm, replay_scores, rewrite_bag, synth_small

from bags.io import topics as T
from bags.io.reader import BagReader

pytest.importorskip("bev_mapper_core.synth")
pytestmark = pytest.mark.slow

FRAMES = 8


@pytest.fixture(scope="module")
def staggered(tmp_path_factory):
    return synth_small(tmp_path_factory.mktemp("staggered") / "drive", frames=FRAMES, extra=("--stagger-ms", "43"))


def test_synth_staggers_the_cameras_stamps_and_keeps_the_frame_stamp_for_gt_and_odometry(staggered):
    with BagReader(staggered) as r:
        frames = list(r.frames(rgb=False))
    f = frames[0]
    offsets = [f.camera_stamps[c] - f.camera_stamps["front"] for c in r.camera_names]
    assert offsets == [round(i * 43e6 / 5) for i in range(6)]  # rig order, evenly over 43 ms
    assert f.stamp_ns == f.camera_stamps["front"] == f.odom.stamp_ns  # GT and odometry at the frame stamp
    assert all(p is not None for p in frames[1].stamp_poses.values())  # a pose at every camera's stamp


def test_each_camera_at_its_time_is_counted_and_maps_closer_to_the_truth(staggered, tmp_path, capsys):
    assert replay_ipm(staggered, tmp_path / "auto", "--no-pictures", "--no-report") == 0
    assert f"{FRAMES - 1} set(s) with each camera at its own time" in capsys.readouterr().out  # the summary says it
    assert replay_ipm(staggered, tmp_path / "off", "--no-pictures", "--no-report", "--time-placement", "off") == 0
    auto, off = replay_scores(tmp_path / "auto"), replay_scores(tmp_path / "off")
    p = auto["placement"]
    assert off["placement"] == {"mode": "off"}
    # the last frame's later cameras lie past the last odometry: its corrections round to nothing
    assert p["sets_placed"] == FRAMES - 1 and p["sets_static"] == 1
    assert p["cameras_without_pose"] == p["stamp_jumps"] == p["sets_without_pose"] == 0
    assert 1 <= p["rebuilds"] < FRAMES and p["max_offset_m"] > 0.2
    # measured: vehicle 81.0 -> 86.7, mIoU 58.7 -> 60.7 on this drive
    assert auto["classes"]["vehicle"]["iou"] > off["classes"]["vehicle"]["iou"] + 0.03
    assert auto["miou"] > off["miou"]


def test_cameras_at_the_frames_stamp_map_as_today(tmp_path):
    bag = synth_small(tmp_path / "drive", frames=3, seed=31)
    assert replay_ipm(bag, tmp_path / "auto", "--no-pictures", "--no-report") == 0
    assert replay_ipm(bag, tmp_path / "off", "--no-pictures", "--no-report", "--time-placement", "off") == 0
    auto, off = replay_scores(tmp_path / "auto"), replay_scores(tmp_path / "off")
    p = auto.pop("placement")
    assert p["sets_static"] == 3 and p["rebuilds"] == 0 and p["max_offset_m"] == 0
    off.pop("placement")
    assert auto == off


def test_without_odometry_the_drive_is_mapped_as_today_and_said_once(staggered, tmp_path, capsys):
    bag = rewrite_bag(staggered, tmp_path / "no_odom.mcap",
                      lambda topic, t, data: None if topic in (T.ODOM, T.TF) else (topic, t, data))
    capsys.readouterr()
    assert replay_ipm(bag, tmp_path / "auto", "--no-pictures", "--no-report") == 0
    said = capsys.readouterr()
    assert (said.out + said.err).count("time placement: no ego pose") == 1
    assert replay_ipm(bag, tmp_path / "off", "--no-pictures", "--no-report", "--time-placement", "off") == 0
    auto, off = replay_scores(tmp_path / "auto"), replay_scores(tmp_path / "off")
    p = auto.pop("placement")
    assert p["sets_without_pose"] == FRAMES and p["cameras_without_pose"] == 6 * FRAMES and p["rebuilds"] == 0
    off.pop("placement")
    assert auto == off
