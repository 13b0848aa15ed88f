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
    runs = ["s2g2_semi", "focusbev", "bimapper_rgb"]  # "s2g2" is s2g2_semi's code path without unlabeled frames
    cmd = [sys.executable, str(REPO / "experiments" / "gpu_retrain.py"), "--out", str(out), "--tiny",
           "--workers", "2", "--budget-min", "1", "--camvid", str(camvid), "--runs", ",".join(runs)]
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["runs"]) == set(runs)
    assert summary["rendered_by_runs"] == 0  # the script rendered what every run loads
    for name, run in summary["runs"].items():
        assert run["returncode"] == 0 and run["step"] >= 1 and "best.safetensors" in run["weights"], name
        assert (out / "runs" / name / "best.safetensors").stat().st_size > 0
        assert "--resume" not in (out / "logs" / f"{name}.log").read_text().splitlines()[0]  # a fresh run
    semi = (out / "logs" / "s2g2_semi.log").read_text()
    assert "2 real unlabeled frames" in semi and "--unlabeled-real" in summary["flags"]["s2g2_semi"]
    bad = subprocess.run([sys.executable, str(REPO / "experiments" / "gpu_retrain.py"), "--out", str(out),
                          "--runs", "nope"], capture_output=True, text=True)
    assert bad.returncode == 2 and bad.stderr.startswith("error: unknown runs")


def test_every_run_parses_and_asks_for_the_cache_its_trainer_reads(tmp_path):
    """Each run's flags (the full and the tiny recipe) build its TrainConfig and model; its drives
    are the training, held-out and unlabeled seeds of that config."""
    sys.path.insert(0, str(REPO / "experiments"))
    try:
        import gpu_retrain as g
    finally:
        sys.path.pop(0)
    for name in g.RUNS:
        for tiny in (False, True):
            jobs = g.drive_jobs(g.run_flags(name, tiny, None, tmp_path), str(tmp_path / "cache"))
            seeds = [j[3] for j in jobs]
            assert len(seeds) == len(set(seeds)) and jobs, (name, tiny)
            assert any(s >= 900_000_000 for s in seeds) and any(s < 900_000_000 for s in seeds)
