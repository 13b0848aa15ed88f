"""Helpers for tests that talk to real ROS 2 processes over DDS (loopback only)."""

from __future__ import annotations

import fcntl
import os
import pathlib
import random
import subprocess
import sys
import tempfile
import time

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
FASTDDS_PROFILE = REPO / "tests" / "fastdds_discovery.xml"
rclpy = pytest.importorskip("rclpy")


def ros_env(domain_id: int) -> dict:
    """Environment for a child ROS process on its own domain, discovery on this machine only."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    # Fast discovery (tests/fastdds_discovery.xml), unless the caller chose a profile.
    env.setdefault("FASTRTPS_DEFAULT_PROFILES_FILE", str(FASTDDS_PROFILE))
    env["PYTHONUNBUFFERED"] = "1"
    return env


#: Domain ids tests claim: 1-100, clear of the default domain 0, of ``scripts/test.sh``'s random
#: ``ROS_DOMAIN_ID`` (101-200), of the benches' ids and of the ephemeral port range.
DOMAIN_IDS = range(1, 101)
_LOCK_DIR = pathlib.Path(tempfile.gettempdir()) / "bev_mapper_test_domains"


class DomainClaim:
    """A ROS domain id held exclusively by this process (an ``flock`` on a file per id).

    Concurrent test runs on the machine (other checkouts, pytest-xdist workers) claim different
    ids, so their DDS graphs never meet. The lock goes with the process, even when it is killed.
    """

    def __init__(self) -> None:
        _LOCK_DIR.mkdir(parents=True, exist_ok=True)
        ids = list(DOMAIN_IDS)
        start = random.Random().randrange(len(ids))  # spread (own generator: global state untouched)
        for domain in ids[start:] + ids[:start]:
            fd = os.open(_LOCK_DIR / f"{domain}.lock", os.O_RDWR | os.O_CREAT, 0o666)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue
            self.id, self._fd = domain, fd
            return
        raise RuntimeError(f"every ROS domain id in {DOMAIN_IDS} is claimed by other test processes")

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing drops the lock
            self._fd = None


def start_process(args: list[str], domain_id: int, log_path: pathlib.Path) -> subprocess.Popen:
    """Start a Python entry point (``[module, args...]``) in its own process, output to a log."""
    log = open(log_path, "w")  # noqa: SIM115 - closed by stop_process
    proc = subprocess.Popen(
        [sys.executable, "-m", *args], cwd=REPO, env=ros_env(domain_id), stdout=log, stderr=subprocess.STDOUT
    )
    proc._log = log  # type: ignore[attr-defined]
    return proc


def stop_process(proc: subprocess.Popen, timeout: float = 10.0) -> int:
    """SIGINT, then kill if needed; returns the exit code."""
    if proc.poll() is None:
        proc.send_signal(2)
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    proc._log.close()  # type: ignore[attr-defined]
    return proc.returncode


def loaded_torch(pid: int) -> list[str]:
    """The torch libraries a running process has mapped (``/proc/PID/maps``): what ``import torch``
    leaves in a process, seen from outside it."""
    with open(f"/proc/{pid}/maps") as f:
        return sorted({line.split()[-1] for line in f if "/torch/" in line.split()[-1]})


def spin_until(node, predicate, timeout: float, step: float = 0.02) -> bool:
    """Spin ``node`` until ``predicate()`` is true or ``timeout`` seconds pass."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=step)
        if predicate():
            return True
    return predicate()


def core_map_as_received(mapper, grid, images: dict, node_data, max_missing: int = 2):
    """The core's prediction on the cameras the node actually mapped, and the names it lacked.

    Images go over sensor-data QoS (best effort): on a loaded machine DDS may lose one, and the
    node then maps the set without it once its sync timeout passes (as designed). The node's
    unknown cells (-1 in ``node_data``, an OccupancyGrid's data) tell which cameras it had: the
    camera subset, at most ``max_missing`` short, whose coverage gives the same unknown cells.
    Fails if none does.
    """
    import itertools  # noqa: PLC0415

    import numpy as np  # noqa: PLC0415

    _, node_known = grid.from_occupancy(node_data, grid.width, grid.height)
    names = list(images)
    for k in range(max_missing + 1):
        for lost in itertools.combinations(names, k):
            pred = mapper.map({n: images[n] for n in names if n not in lost})
            if np.array_equal(pred.known, node_known):
                return pred, lost
    raise AssertionError(f"the node's unknown cells match no set of cameras with at most {max_missing} missing")


_CLAIMS: dict[int, DomainClaim] = {}


def free_domain_id(salt: int = 0) -> int:
    """A domain id held (:class:`DomainClaim`) for the rest of this test process, one per ``salt``.

    For tests that start several ROS processes on one domain without the ``ros_domain`` fixture
    (module-level helpers); the claim keeps concurrent test runs on the machine apart.
    """
    if salt not in _CLAIMS:
        _CLAIMS[salt] = DomainClaim()
    return _CLAIMS[salt].id
