"""bev-bag's reader takes the ego pose from ``/tf`` (``odom -> base_link``) when a bag has no
``/odom``, as the node's ``pose_source: tf`` does; replay then fuses frames by it."""

from __future__ import annotations

import json

import numpy as np
from bag_damage import GRID_ARGS

from bags.cli.main import main
from bags.io import topics as T
from bags.io.reader import BagReader
from bags.io.writer import BagWriter


def _without(src, dst, dropped: set[str]):
    """A copy of bag ``src`` without the topics in ``dropped`` (not even declared)."""
    with BagReader(src) as r, BagWriter(dst) as w:
        for topic, summary in r.topics.items():
            if topic not in dropped:
                w.add_topic(topic, summary.msgtype, latched=topic in r.latched_topics)
        for m in r.messages([t for t in r.topics if t not in dropped]):
            w.write(m.topic, m.msg, m.log_ns)
    return dst


def test_frames_take_ego_poses_from_tf_when_the_bag_has_no_odom(tmp_path):
    bag = tmp_path / "drive"
    assert main(["synth", str(bag), "--rig", "front1", "--scale", "0.25", "--frames", "4", "--seed", "7",
                 *GRID_ARGS]) == 0
    with BagReader(bag) as r:
        assert r.topics[T.TF].count == 4 and r.topics[T.TF].msgtype == T.TF_TYPE
        by_odom = [(f.stamp_ns, f.odom.world_from_ego) for f in r.frames()]
    tf_only = _without(bag, tmp_path / "tf_only", {T.ODOM})
    with BagReader(tf_only) as r:
        by_tf = [(f.stamp_ns, f.odom) for f in r.frames()]
    assert len(by_tf) == len(by_odom) == 4
    moved = 0
    for (stamp, want), (stamp_tf, got) in zip(by_odom, by_tf):
        assert stamp == stamp_tf and got is not None and (got.frame_id, got.child_frame_id) == ("odom", "base_link")
        np.testing.assert_allclose(got.world_from_ego, want, atol=1e-9)
        moved += int(not np.allclose(want, by_odom[0][1]))
    assert moved > 0  # the drive moves: the poses say something
    neither = _without(bag, tmp_path / "neither", {T.ODOM, T.TF})
    with BagReader(neither) as r:
        assert all(f.odom is None for f in r.frames())
    # replay fuses by the poses of /tf as by those of /odom: the same scores
    outs = {}
    for name, path in (("odom", bag), ("tf", tf_only)):
        out = tmp_path / f"out_{name}"
        assert main(["replay", str(path), "--out", str(out), "--quiet", "--method", "ipm", "--temporal-window", "2",
                     "--no-pictures"]) == 0
        metrics = json.loads((out / "metrics.json").read_text())
        outs[name] = {k: metrics[k] for k in ("classes", "miou", "temporal")}
    assert outs["odom"] == outs["tf"]
