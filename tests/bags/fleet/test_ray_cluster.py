"""``bev-bag evaluate --ray-address`` on a real two-node Ray cluster (issue #41): a head started
with ``ray start --head`` and a second node with ``ray start --address`` (its own raylet, temp dir
and resources) on this machine. The cluster's aggregate is exactly the local one; a node killed
mid-run loses its bag, which the run reports (and does not hang on), and ``--resume`` completes
it to the same aggregate.

Every process of the cluster is found by its own temp dir and killed at the end (never
``ray stop``: it would stop every Ray process on the machine, other users' too).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import pytest
from bag_damage import GRID_ARGS

pytest.importorskip("ray")
psutil = pytest.importorskip("psutil")

ROOT = Path(__file__).resolve().parents[3]
RAY = str(Path(sys.executable).parent / "ray")
FAST = ["--method", "ipm", "--no-pictures", "--no-report", "--quiet"]
#: seconds any one command may take on a loaded machine (a run with a dead node waits for Ray's
#: health checks, ~15 s, before it calls the node dead)
TIMEOUT_S = 300
#: Process titles of a Ray worker running an evaluate task (watched on a cluster, or not).
TASK_TITLES = ("ray::_reporting", "ray::_evaluate_job")


def _free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


class TwoNodeCluster:
    """A head (1 CPU, resource ``head``) and a second node (1 CPU, resource ``worker2``), each with
    its own temp dir (short: Ray's socket paths must fit 107 bytes) and ports.
    """

    def __init__(self) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="bevray-", dir="/tmp"))
        self.head_dir, self.node_dir = self.root / "h", self.root / "w"
        self.env = {**os.environ, "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": uuid.uuid4().hex,
                    "RAY_USAGE_STATS_ENABLED": "0",
                    "PYTHONPATH": os.pathsep.join([str(ROOT), *filter(None, [os.environ.get("PYTHONPATH")])])}
        self.port = _free_ports(1)[0]
        self.address = f"127.0.0.1:{self.port}"
        self.frozen: set = set()  # workers left behind by a killed node (orphans, stopped)

    def _start(self, args: list[str], temp_dir: Path) -> None:
        p = _free_ports(8)
        cmd = [RAY, "start", *args, "--num-cpus=1", f"--temp-dir={temp_dir}", "--disable-usage-stats",
               f"--node-manager-port={p[0]}", f"--object-manager-port={p[1]}",
               f"--dashboard-agent-listen-port={p[2]}", f"--dashboard-agent-grpc-port={p[3]}",
               f"--runtime-env-agent-port={p[4]}", f"--metrics-export-port={p[5]}"]
        r = subprocess.run(cmd, env=self.env, capture_output=True, text=True, timeout=TIMEOUT_S)
        assert r.returncode == 0, r.stdout + r.stderr

    def start(self) -> None:
        """Start both nodes and wait until the cluster has both."""
        dash = _free_ports(1)[0]
        self._start(["--head", f"--port={self.port}", '--resources={"head": 1}', "--include-dashboard=false",
                     f"--dashboard-port={dash}"], self.head_dir)
        self._start([f"--address={self.address}", '--resources={"worker2": 1}'], self.node_dir)
        deadline = time.monotonic() + TIMEOUT_S
        while self.alive_nodes() < 2:
            assert time.monotonic() < deadline, "the second node never joined"
            time.sleep(1)

    def alive_nodes(self) -> int:
        """Nodes ``ray status`` lists as active."""
        r = subprocess.run([RAY, "status", f"--address={self.address}"], env=self.env, capture_output=True,
                           text=True, timeout=TIMEOUT_S)
        active = r.stdout.partition("Active:")[2].partition("Pending:")[0]
        return len(re.findall(r"\bnode_[0-9a-f]+", active))

    def processes(self, temp_dir: Path | None = None, descendants: bool = True) -> set:
        """The processes of one node (``temp_dir``) or of both: those naming its temp dir on their
        command line, and their descendants (workers and agents, which carry only a title).
        """
        dirs = [str(temp_dir)] if temp_dir else [str(self.head_dir), str(self.node_dir)]
        found = set()
        for proc in psutil.process_iter(["cmdline"]):
            if proc.pid != os.getpid() and any(d in a for a in proc.info["cmdline"] or () for d in dirs):
                found.add(proc)
                try:
                    if not descendants:
                        continue
                    found.update(proc.children(recursive=True))
                except psutil.NoSuchProcess:
                    pass
        return found

    def node_raylet(self):
        return next(p for p in self.processes(self.node_dir) if p.name() == "raylet")

    def kill(self, procs) -> None:
        for proc in procs:
            try:
                proc.kill()
            except psutil.NoSuchProcess:
                pass
        psutil.wait_procs(list(procs), timeout=30)

    def shutdown(self) -> None:
        """Kill every process of both nodes (twice: a dying raylet may still have started one)."""
        for _ in range(2):
            self.kill(self.processes() | self.frozen)
        shutil.rmtree(self.root, ignore_errors=True)


@pytest.fixture(scope="module")
def cluster():
    c = TwoNodeCluster()
    try:
        c.start()
        yield c
    finally:
        c.shutdown()
        assert not c.processes() and not any(p.is_running() for p in c.frozen), "processes outlived the cluster"


@pytest.fixture(scope="module")
def drives(tmp_path_factory):
    """Three short drives (one camera, small images and grid) and their local evaluation."""
    root = tmp_path_factory.mktemp("drives")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    for k in range(3):
        _bev_bag(["synth", str(root / "bags" / f"d{k}"), "--rig", "front1", "--scale", "0.25", "--frames", "60",
                  "--seed", str(41 + k), *GRID_ARGS], env)
    local = _evaluate(root / "bags", root / "local", [], env)
    assert local.returncode == 0, local.stderr
    return {"bags": root / "bags", "local": _summary(root / "local")}


def _bev_bag(argv: list[str], env: dict, check: bool = True) -> subprocess.CompletedProcess:
    r = subprocess.run([sys.executable, "-m", "bags.cli.main", *argv], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=TIMEOUT_S)
    assert not check or r.returncode == 0, r.stdout + r.stderr
    return r


def _evaluate(bags: Path, out: Path, extra: list[str], env: dict) -> subprocess.CompletedProcess:
    return _bev_bag(["evaluate", str(bags), "--out", str(out), "--workers", "2", *FAST, *extra], env, check=False)


def _summary(out: Path) -> dict:
    return json.loads((out / "summary.json").read_text())


def _timeless(aggregate: dict) -> dict:
    """The aggregate without the mapping latencies (wall-clock times: different on every run)."""
    return {k: v for k, v in aggregate.items() if k != "latency_ms"}


def _driver_env(cluster: TwoNodeCluster) -> dict:
    """The command's environment: the cluster's token, but no RAY_AUTH_MODE (evaluate finds the token)."""
    return {k: v for k, v in cluster.env.items() if k != "RAY_AUTH_MODE"}


def test_two_nodes_give_the_local_aggregate_exactly(cluster, drives, tmp_path):
    r = _evaluate(drives["bags"], tmp_path / "eval", ["--ray-address", cluster.address], _driver_env(cluster))
    assert r.returncode == 0, r.stderr
    s = _summary(tmp_path / "eval")
    assert s["ray"]["address"] == cluster.address and s["ray"]["workers"] == 2
    assert len(s["ray"]["nodes"]) == 2  # both nodes ran bags
    assert {e["node"] for e in s["per_bag"]} == set(s["ray"]["nodes"])
    assert s["bags"]["ok"] == 3 and s["aggregate"]["frames_scored"] == 180
    assert _timeless(s["aggregate"]) == _timeless(drives["local"]["aggregate"])  # exactly, floats too
    assert [e["miou"] for e in s["per_bag"]] == [e["miou"] for e in drives["local"]["per_bag"]]


def test_a_killed_node_is_reported_and_resume_completes(cluster, drives, tmp_path):
    """Run this after the test above: it leaves the cluster without its second node."""
    out = tmp_path / "eval"
    argv = [sys.executable, "-m", "bags.cli.main", "evaluate", str(drives["bags"]), "--out", str(out),
            "--workers", "2", "--ray-address", cluster.address, *FAST]
    run = subprocess.Popen(argv, cwd=ROOT, env=_driver_env(cluster), stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    try:
        # the second node's worker starts a bag: freeze it (it cannot finish first), kill the rest of
        # the node. The frozen worker keeps its connections open, as a machine that vanished
        # does: Ray's own timeout for those is 7 minutes; the run must not wait for it.
        raylet, deadline = cluster.node_raylet(), time.monotonic() + TIMEOUT_S
        busy = []
        while not busy:
            assert run.poll() is None and time.monotonic() < deadline, "no bag started on the second node"
            busy = [p for p in raylet.children(recursive=True) if _title(p).startswith(TASK_TITLES)]
            time.sleep(0.02)
        # the task tells the driver's start board its node first thing (and waits for it); frozen
        # before that, its bag would be nobody's (the run would wait for Ray's 7 minutes): a
        # machine that vanishes mid-bag has long since started it. So freeze it once it has a bag
        # open (its input or its output), which it does only after the board knows its node (a
        # fixed 0.5 s was too short on a loaded machine: the test hung once).
        while not any(_has_bag_open(p, (drives["bags"], out)) for p in busy):
            assert run.poll() is None and time.monotonic() < deadline, "the second node's task opened no bag"
            time.sleep(0.01)
        for p in busy:
            p.send_signal(signal.SIGSTOP)
        cluster.frozen.update(busy)
        cluster.kill(cluster.processes(cluster.node_dir, descendants=False))  # its agents follow their raylet
        stdout, stderr = run.communicate(timeout=TIMEOUT_S)  # the run ends: no hang on the lost bag
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
    assert run.returncode == 1, stderr
    s = _summary(out)
    lost = [e for e in s["per_bag"] if e["status"] != "ok"]
    assert s["bags"]["failed"] == len(lost) >= 1 and s["complete"] is False
    for e in lost:
        assert e["status"] == "failed" and e["node"] is None
        assert re.search(r"NodeDied|WorkerCrashed|died", e["error"]), e["error"]
        assert f"error: {e['name']} (" in stderr  # which bag, said by the command
    # the frozen worker is sometimes taken down with its node (Ray's own NodeDiedError, ~15 s), else
    # it still holds its connections and the node watch reports the bag (Ray alone: 7 minutes)
    cluster.kill(cluster.frozen)
    assert "--resume" in stderr and "Traceback" not in stderr
    assert not list(out.rglob("*partial*"))  # what the killed worker was writing is gone

    r = _evaluate(drives["bags"], out, ["--ray-address", cluster.address, "--resume"], _driver_env(cluster))
    assert r.returncode == 0, r.stderr
    s2 = _summary(out)
    assert s2["complete"] and s2["bags"]["resumed"] == 3 - len(lost)
    assert {e["name"] for e in s2["per_bag"] if not e["resumed"]} == {e["name"] for e in lost}
    assert len(s2["ray"]["nodes"]) == 1  # replayed on the head, the only node left
    assert _timeless(s2["aggregate"]) == _timeless(drives["local"]["aggregate"])


def _has_bag_open(proc, folders) -> bool:
    """True when ``proc`` has a file under one of ``folders`` open."""
    try:
        return any(Path(f.path).is_relative_to(d) for f in proc.open_files() for d in folders)
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return False


def _title(proc) -> str:
    try:
        return " ".join(proc.cmdline())
    except (psutil.NoSuchProcess, psutil.AccessDenied):
        return ""

