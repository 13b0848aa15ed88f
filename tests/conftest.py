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
import signal
import sys
import time
import uuid

import pytest

TESTS = pathlib.Path(__file__).resolve().parent
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
# Discovery in ~0.1 s instead of up to 3 s (see the file); inherited by the ROS processes tests start.
os.environ.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(TESTS / "fastdds_discovery.xml"))
sys.path.insert(0, str(TESTS))

#: Marks every process this test session starts (inherited through the environment, also by
#: processes that detach, e.g. the ``ros2 daemon`` the ros2 CLI spawns): what the session-end
#: check looks for.
SESSION_ENV = "BEV_MAPPER_TEST_SESSION"
os.environ[SESSION_ENV] = f"{os.getpid()}-{uuid.uuid4().hex[:8]}"
#: Seconds the session-end check gives processes to finish exiting.
LEFTOVER_GRACE_S = 10.0

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


# ------------------------------------------------------------------ no leftovers
def session_processes() -> dict[int, str]:
    """``{pid: command line}`` of every live process that carries this session's mark (not this
    process): children, grandchildren and detached daemons alike. Linux ``/proc`` only.
    """
    mark = f"{SESSION_ENV}={os.environ[SESSION_ENV]}".encode()
    found = {}
    for entry in pathlib.Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            if mark not in (entry / "environ").read_bytes().split(b"\0"):
                continue
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:  # gone, or another user's
            continue
        if cmd and not _own_helper(entry, cmd):  # a zombie has no command line: exited, only not reaped yet
            found[int(entry.name)] = cmd
    return found


#: Helper processes multiprocessing starts for this interpreter (torch's DataLoader and spawn do):
#: they exit when it does, so they are no leftover.
MULTIPROCESSING_HELPERS = ("from multiprocessing.resource_tracker import main",
                           "from multiprocessing.forkserver import main")


def _own_helper(entry: pathlib.Path, cmd: str) -> bool:
    """True for a multiprocessing helper process whose parent is this interpreter."""
    if not any(h in cmd for h in MULTIPROCESSING_HELPERS):
        return False
    try:
        ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return False
    return ppid == os.getpid()


def _stop(pids) -> None:
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pid in pids:
            try:
                os.kill(pid, sig)
            except OSError:
                pass
        deadline = time.monotonic() + 3
        while time.monotonic() < deadline and set(pids) & set(session_processes()):
            time.sleep(0.1)


@pytest.fixture(scope="session", autouse=True)
def no_leftover_processes():
    """At the end of the session: stop the ``ros2 daemon`` processes the ros2 CLI spawned (one per
    domain a test used it on), then fail if any other process this session started is still
    running after :data:`LEFTOVER_GRACE_S` (it is stopped, and named in the failure).
    """
    yield
    if not pathlib.Path("/proc/self/environ").exists():
        return
    daemons = [pid for pid, cmd in session_processes().items() if "ros2cli.daemon" in cmd]
    _stop(daemons)
    deadline = time.monotonic() + LEFTOVER_GRACE_S
    left = session_processes()
    while left and time.monotonic() < deadline:
        time.sleep(0.2)
        left = session_processes()
    if left:
        _stop(list(left))
        listing = "; ".join(f"{pid}: {cmd[:160]}" for pid, cmd in sorted(left.items()))
        pytest.fail(f"{len(left)} process(es) started by the tests outlived the session (now stopped): {listing}",
                    pytrace=False)


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
