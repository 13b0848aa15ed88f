"""Helpers for tests that talk to real ROS 2 processes over DDS (loopback only)."""

from __future__ import annotations

import os
import pathlib
import subprocess
import sys
import time

import pytest

REPO = pathlib.Path(__file__).resolve().parents[1]
rclpy = pytest.importorskip("rclpy")


def ros_env(domain_id: int) -> dict:
    """Environment for a child ROS process on its own domain, discovery on this machine only."""
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    env["PYTHONUNBUFFERED"] = "1"
    return env


def free_domain_id(worker_salt: int = 0) -> int:
    """A domain id unlikely to collide with other test runs on the machine."""
    return 110 + (os.getpid() + worker_salt) % 100


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


def spin_until(node, predicate, timeout: float, step: float = 0.02) -> bool:
    """Spin ``node`` until ``predicate()`` is true or ``timeout`` seconds pass."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=step)
        if predicate():
            return True
    return predicate()
