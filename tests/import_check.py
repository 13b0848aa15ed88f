"""Which ROS modules a fresh interpreter has loaded after running some imports."""

from __future__ import annotations

import subprocess
import sys

#: Top-level packages that only exist with ROS (plus any ``*_msgs`` package).
ROS_TOP_LEVEL = ("rclpy", "rosbags", "mcap")


def ros_modules_loaded_by(statements: str) -> list[str]:
    """Run ``statements`` in a new interpreter; return the ROS modules in its ``sys.modules``."""
    code = (
        f"{statements}\n"
        "import sys\n"
        f"bad = sorted(k for k in sys.modules if k.split('.')[0] in {ROS_TOP_LEVEL!r} "
        "or k.split('.')[0].endswith('_msgs'))\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return [m for m in out.stdout.strip().split(",") if m]
