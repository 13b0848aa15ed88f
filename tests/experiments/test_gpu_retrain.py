"""experiments/gpu_retrain.py, the one prepared command of a GPU session (issue #26), runs end to
end on CPU with --tiny: it renders every drive the runs load (the runs render none), trains
every run, and writes weights, logs and a summary."""

from __future__ import annotations

import json
import subprocess
import sys
import tarfile
from pathlib import Path

import pytest
from real_data_helpers import write_camvid

pytestmark = [pytest.mark.slow]
pytest.importorskip("bev_mapper_core.synth")

REPO = Path(__file__).resolve().parents[2]


def test_gpu_script_runs_end_to_end_on_cpu_with_a_tiny_budget(tmp_path):
    camvid = write_camvid(tmp_path / "camvid", n=2)
    out = tmp_path / "out"
    runs = ["s2g2_semi", "focusbev", "bimapper_rgb", "focusbev_prior", "bimapper_prior"]  # "s2g2": s2g2_semi without unlabeled frames
    cmd = [sys.executable, str(REPO / "experiments" / "gpu_retrain.py"), "--out", str(out), "--tiny",
           "--workers", "2", "--no-plan", "--deadline-min", "3", "--reserve-s", "10", "--camvid", str(camvid),
           "--runs", ",".join(runs), "--pack", str(tmp_path / "pack")]  # --no-plan: the probes' plan has its own test
    proc = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr + proc.stdout
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["runs"]) == set(runs)
    assert summary["rendered_by_runs"] == 0  # the script rendered what every run loads
    for name, run in summary["runs"].items():
        assert run["returncode"] == 0 and run["step"] >= 1 and "best.safetensors" in run["weights"], name
        assert (out / "runs" / name / "best.safetensors").stat().st_size > 0
        assert "--resume" not in (out / "logs" / f"runs_{name}.log").read_text().splitlines()[0]  # a fresh run
        assert (tmp_path / "pack" / f"gpu_{name}.safetensors").stat().st_size > 0
    with tarfile.open(tmp_path / "pack" / "gpu_runs.tar.gz") as tar:
        assert {"summary.json", "runs/focusbev/best.json", "logs/runs_focusbev.log"} <= set(tar.getnames())
    semi = (out / "logs" / "runs_s2g2_semi.log").read_text()
    assert "EfficientNet trunk from" in (out / "logs" / "runs_focusbev.log").read_text()  # the shipped backbone
    assert "encoders from" in (out / "logs" / "runs_bimapper_rgb.log").read_text()
    prior = (out / "logs" / "runs_focusbev_prior.log").read_text()  # issue #39's recipe: prior, memory bank
    assert "segipm prior of" in prior and "window 2" in prior and "feature cache" not in prior
    prior = (out / "logs" / "runs_bimapper_prior.log").read_text()  # the six cameras' prior, ImageNet encoders
    assert "segipm prior of" in prior and "efficientnet-lite0" in prior
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


def test_the_plan_fills_the_budget_at_the_probed_rate():
    """Epochs and frames per epoch follow the probe's rate: a fast run sees every frame each epoch
    and more epochs, a slow one fewer frames; validation stays a small share; the learning-rate
    step keeps the recipe's fraction."""
    sys.path.insert(0, str(REPO / "experiments"))
    try:
        import gpu_retrain as g
    finally:
        sys.path.pop(0)

    def plan(s_step, val_s, budget_s=300.0, run="s2g2"):
        probe = {"seconds": 20.0 + 30 * s_step + val_s, "history": [{"train_s": 30 * s_step, "batches": 30,
                                                                       "val_s": val_s}]}
        out = g.plan_epochs(g.RUNS[run], probe, budget_s)
        return int(out[1]), int(out[3]) // 8, int(out[5])

    epochs, steps, lr_step = plan(0.01, 0.5)  # fast: all 800 frames (100 steps) an epoch, more epochs
    assert steps == 100 and epochs > 30 and lr_step == round(epochs * 22 / 30)
    epochs, steps, _ = plan(0.3, 4.0)  # slow: fewer steps, validation under 15 % of the time
    assert steps < 100 and epochs * 4.0 <= 0.15 * 280 + 4.0
    total = epochs * (steps * 0.3 + 4.0)
    assert 0.8 * 280 <= total <= 280  # the budget (less the start-up) is used, not exceeded
