"""torch is imported only where a learned method runs: a replay with ``method: ipm``, temporal
fusion on or off, imports no torch (a fresh interpreter's ``sys.modules``), and listing the
methods imports none of them. The node's side (a running ``mapper_node`` with IPM maps no torch
library) is checked in tests/bev_mapper_ros/test_node.py and tests/bev_mapper_ros/test_node_temporal.py."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
from bag_helpers import synth_small

pytestmark = pytest.mark.slow

PROBE = """
import json, sys
from bags.cli.main import main
rc = main(sys.argv[1:])
print(json.dumps({"rc": rc, "torch": sorted(k for k in sys.modules if k.split(".")[0] == "torch")[:5]}))
"""


def _fresh(argv: list[str]) -> dict:
    res = subprocess.run([sys.executable, "-c", PROBE, *argv], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("window", ["1", "2"])
def test_an_ipm_replay_imports_no_torch(tmp_path, window):
    bag = synth_small(tmp_path / "bag", frames=3)
    got = _fresh(["replay", str(bag), "--out", str(tmp_path / "out"), "--quiet", "--method", "ipm",
                  "--temporal-window", window])
    assert got == {"rc": 0, "torch": []}


def test_the_probe_sees_torch_and_the_method_table_imports_none():
    res = subprocess.run([sys.executable, "-c", "import sys, torch; print('torch' in sys.modules)"],
                         capture_output=True, text=True, timeout=120)
    assert res.stdout.strip() == "True"
    code = ("import sys; from bev_mapper_core.mapper import available_methods;"
            "from bev_mapper_core.training.method import train_methods;"
            "print(available_methods(), train_methods(), 'torch' in sys.modules)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip().endswith("False"), res.stdout
