"""Issue #38: ``bev-bag play`` republishes a bag's compressed cameras (``sensor_msgs/CompressedImage``
on ``<image topic>/compressed``) as they are: the same format and bytes, over DDS.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from bag_helpers import synth_small
from ros_helpers import REPO, rclpy, ros_env, spin_until
from sensor_msgs.msg import CompressedImage  # noqa: E402

from bags.io.reader import BagReader

pytest.importorskip("bev_mapper_core.synth")
pytestmark = pytest.mark.ros

FRAMES = 2
TOPICS = ("/cameras/front/image_raw/compressed", "/cameras/front/labels/compressed")


def test_play_republishes_compressed_images_as_they_are(tmp_path, ros_domain):
    bag = synth_small(tmp_path / "drive", frames=FRAMES, compressed=True)
    with BagReader(bag) as r:
        want = {(m.topic, m.msg.header.stamp.sec, m.msg.header.stamp.nanosec): (m.msg.format, m.msg.data.tobytes())
                for m in r.messages(TOPICS)}
    assert len(want) == 2 * FRAMES
    got: dict = {}
    rclpy.init(domain_id=ros_domain)
    node = rclpy.create_node("bev_play_compressed_test")
    for topic in TOPICS:
        node.create_subscription(CompressedImage, topic, lambda m, t=topic: got.setdefault(
            (t, m.header.stamp.sec, m.header.stamp.nanosec), (m.format, bytes(np.asarray(m.data, np.uint8)))), 10)
    play = subprocess.Popen(
        [sys.executable, "-m", "bags.cli.main", "play", str(bag), "--domain-id", str(ros_domain), "--topics", *TOPICS,
         "--wait-for", *TOPICS, "--delay", "0.3"],
        cwd=REPO, env=ros_env(ros_domain), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        spin_until(node, lambda: play.poll() is not None and len(got) == len(want), 30.0)
        out, err = play.communicate(timeout=20)
    finally:
        if play.poll() is None:
            play.kill()
            play.communicate()
        node.destroy_node()
        rclpy.try_shutdown()
    assert play.returncode == 0 and "skipping" not in err, err
    assert got == want
