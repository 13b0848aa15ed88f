"""experiments/gpu_retrain.py, the one prepared command of a GPU session (issue #26), runs end to
end on CPU with --tiny: it renders every drive the runs load (the runs render none), trains
every run, and writes weights, logs and a summary."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from real_data_helpers import write_camvid

pytestmark = [pytest.mark.slow]
pytest.importorskip("bev_mapper_core.synth")

REPO = Path(__file__).resolve().parents[2]


def test_gpu_script_runs_end_to_end_on_cpu_with_a_tiny_budget(tmp_path):
    camvid = write_camvid(tmp_path / "camvid", n=2)
    out = tmp_path / "out"
    cmd = [sys.executable, str(REPO / "experiments" / "gpu_retrain.py"), "--out", str(out), "--tiny",
           "--workers", "2", "--budget-min", "1", "--camvid", str(camvid)]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["runs"]) == {"s2g2", "s2g2_semi", "focusbev", "bimapper_rgb"}
    assert summary["rendered_by_runs"] == 0  # the script rendered what every run loads
    for name, run in summary["runs"].items():
        assert run["returncode"] == 0 and run["step"] >= 1 and "best.safetensors" in run["weights"], name
        assert (out / "runs" / name / "best.safetensors").stat().st_size > 0
    semi = (out / "logs" / "s2g2_semi.log").read_text()
    assert "2 real unlabeled frames" in semi and "--unlabeled-real" in summary["flags"]["s2g2_semi"]
    # a second call resumes: nothing rendered again, the runs continue from their checkpoints
    again = subprocess.run(cmd + ["--runs", "s2g2"], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    assert "--resume" in (out / "logs" / "s2g2.log").read_text().splitlines()[0]
    bad = subprocess.run([sys.executable, str(REPO / "experiments" / "gpu_retrain.py"), "--out", str(out),
                          "--runs", "nope"], capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.startswith("error: unknown runs")
