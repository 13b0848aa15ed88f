"""``bev-bag play`` publishes a bag's ``/tf_static`` (transient local, as robot_state_publisher)
and ``/tf``: a tf2_ros ``TransformListener`` gets the camera mounts and the ego motion the bag
holds, at the bag's stamps."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from ros_helpers import REPO, rclpy, ros_env, spin_until

from bags.io import topics as T
from bags.io.reader import BagReader
from msg_adapters import transform_stamped_to_matrix

tf2_ros = __import__("tf2_ros") if os.environ.get("CI") else pytest.importorskip(
    "tf2_ros", reason="tf2_ros is not built into this venv (bash scripts/setup_venv.sh builds it)")


def test_play_publishes_tf_static_and_tf_for_a_tf2_listener(small_drive_mcap, ros_domain):
    bag, _ = small_drive_mcap
    with BagReader(bag) as r:
        rig = r.rig()
        poses = [(f.stamp_ns, f.odom.world_from_ego) for f in r.frames(rgb=False, labels=True, gt=False)]
    node = player = None
    try:
        rclpy.init(domain_id=ros_domain)
        node = rclpy.create_node("bev_test_play_tf")
        buffer = tf2_ros.Buffer()
        listener = tf2_ros.TransformListener(buffer, node)  # noqa: F841 - kept alive while spinning
        player = subprocess.Popen(
            [sys.executable, "-m", "bags.cli.main", "play", str(bag), "--rate", "0.5", "--domain-id", str(ros_domain),
             "--topics", T.TF_STATIC, T.TF, "--wait-for", T.TF, "--delay", "0.5", "--quiet"],
            cwd=REPO, env=ros_env(ros_domain), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        last = rclpy.time.Time(nanoseconds=poses[-1][0])
        assert spin_until(node, lambda: buffer.can_transform("odom", "base_link", last), 60.0), player.communicate()
        out, err = player.communicate(timeout=30)
        assert player.returncode == 0 and "skipping" not in err, err
        for cam in rig.cameras:
            got = transform_stamped_to_matrix(buffer.lookup_transform("base_link", cam.frame_id, rclpy.time.Time()))
            np.testing.assert_allclose(got.matrix, cam.ego_from_cam_array, atol=1e-9)
        for stamp, want in poses:
            got = transform_stamped_to_matrix(buffer.lookup_transform("odom", "base_link",
                                                                      rclpy.time.Time(nanoseconds=stamp)))
            np.testing.assert_allclose(got.matrix, want, atol=1e-9)
    finally:
        if player is not None and player.poll() is None:
            player.kill()
            player.communicate()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
