"""Test-wide settings: ROS traffic stays on this machine; tests import helpers from tests/."""

import os
import pathlib
import sys

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
sys.path.insert(0, str(pathlib.Path(__file__).parent))
