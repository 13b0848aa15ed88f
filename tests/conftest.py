"""Test-wide settings, the layer markers and fixtures shared across modules.

Layers (markers registered in pytest.ini, ``--strict-markers``):

- ``ros``: needs rclpy or ROS message packages, a DDS graph, or starts a ROS process. Every test
  that uses the ``ros_domain`` fixture (all DDS tests must: it hands out a private domain id) is
  marked here automatically; so is every test in a module that sets ``pytestmark = pytest.mark.ros``.
- ``slow``: takes more than ~1 s for reasons other than ROS (training runs, synthesizing many
  frames, fresh interpreters that import torch). Tests using a fixture in ``SLOW_FIXTURES`` are
  marked automatically.

A folder's own ``conftest.py`` marks what all its tests need (``bev_mapper_ros/``: ``ros``;
``bags/fleet/``: ``slow``, a Ray runtime each); a module marks itself with ``pytestmark``, a test
with its decorator. The folders mirror the source tree (``tests/bags/replay/`` tests
``bags/replay/``); helpers shared across folders sit here (``*_helpers.py``, ``bag_damage.py``,
``import_check.py``), on ``sys.path``.

``bash scripts/test.sh -m "not ros and not slow"`` is the fast unit layer; without ``-m`` every
test runs.
"""

from __future__ import annotations

import os
import pathlib
import sys

import pytest

TESTS = pathlib.Path(__file__).resolve().parent
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
# Discovery in ~0.1 s instead of up to 3 s (see the file); inherited by the ROS processes tests start.
os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(TESTS / "fastdds_discovery.xml"))
sys.path.insert(0, str(TESTS))

#: Fixtures that make a test a ``ros`` test.
ROS_FIXTURES = {"ros_domain"}
#: Fixtures whose set-up alone takes more than ~1 s without ROS (training data).
SLOW_FIXTURES = {"tiny_data"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        names = set(getattr(item, "fixturenames", ()))
        if names & ROS_FIXTURES:
            item.add_marker(pytest.mark.ros)
        if names & SLOW_FIXTURES:
            item.add_marker(pytest.mark.slow)


@pytest.fixture()
def ros_domain():
    """A ROS domain id no other test process on this machine uses while the test runs."""
    from ros_helpers import DomainClaim  # noqa: PLC0415 - rclpy is only needed by ROS tests

    claim = DomainClaim()
    try:
        yield claim.id
    finally:
        claim.release()


# ------------------------------------------------------------------ shared bags
@pytest.fixture(scope="session")
def small_drive_mcap(tmp_path_factory):
    """A 4-frame MCAP drive (seed 5) and its IPM replay, with pictures and a GIF.

    Shared by the replay and play tests: (bag, replay output dir). Read-only for tests.
    """
    from bag_helpers import replay_ipm, synth_small  # noqa: PLC0415 - needs the bag libraries

    root = tmp_path_factory.mktemp("small_drive_mcap")
    bag = synth_small(root / "drive_mcap", storage="mcap")
    assert replay_ipm(bag, root / "out_mcap", "--picture-every", "1", "--gif") == 0
    return bag, root / "out_mcap"


@pytest.fixture(scope="session")
def small_drive_sqlite3(tmp_path_factory):
    """The same drive as :func:`small_drive_mcap` as a sqlite3 bag, replayed without pictures."""
    from bag_helpers import replay_ipm, synth_small  # noqa: PLC0415 - needs the bag libraries

    root = tmp_path_factory.mktemp("small_drive_sqlite3")
    bag = synth_small(root / "drive_sqlite3", storage="sqlite3")
    assert replay_ipm(bag, root / "out_sqlite3", "--no-pictures") == 0
    return bag, root / "out_sqlite3"
