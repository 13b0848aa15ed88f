"""Exports in a child process and in the background (issue #41): a runner maps with torch from
its first call while the model is exported, then switches; a cancelled export leaves no file and
no process; part files of dead exporters (and old ``tmp*`` files of earlier versions) are removed.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import threading
import time

import numpy as np
import pytest
import torch

from bev_mapper_core.nn import backends, export_cache, export_process

pytestmark = pytest.mark.slow
BACKEND = "onnxruntime"


class Tiny(torch.nn.Module):
    """A small convolution net (exports in ~1 s); importable by the child through sys.path."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv = torch.nn.Conv2d(3, 4, 3, padding=1)

    def forward(self, x):
        return torch.sigmoid(self.conv(x))


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    if importlib.util.find_spec(BACKEND) is None:
        pytest.skip(f"{BACKEND} is not installed (the 'fast' extra)")
    monkeypatch.setenv(backends.CACHE_ENV, str(tmp_path))
    return tmp_path / "onnx"


def _complete_pairs_only(directory) -> list[str]:
    names = sorted(p.name for p in directory.iterdir())
    assert all(not n.startswith(".") for n in names), names  # no part file
    assert len(names) == 2 and {n.rsplit(".", 1)[1] for n in names} == {"onnx", "json"}, names
    return names


def test_background_runner_maps_with_torch_then_switches(cache):
    x = torch.rand(1, 3, 8, 8)
    module = Tiny().eval()
    with torch.no_grad():
        want = module(x)
    runner = backends.BackendRunner(BACKEND, torch.device("cpu"), threads=1, background=True)
    runner.reset(module)
    started = time.perf_counter()
    with torch.no_grad():
        first = runner(x)[0]
    assert time.perf_counter() - started < 1.0  # torch at once: the export runs elsewhere
    assert torch.equal(first, want)
    assert runner.state == f"torch (until the {BACKEND} model is ready)"
    assert runner.wait_ready(120)
    with torch.no_grad():
        later = runner(x)[0]
    assert runner.state == BACKEND and runner._exported is not None
    np.testing.assert_allclose(later.numpy(), want.numpy(), atol=backends.TOLERANCE)
    _complete_pairs_only(cache)


def test_a_cancelled_export_leaves_no_file_and_no_process(cache):
    cache.mkdir(parents=True)
    part = export_cache.part_path(cache / "model.onnx")
    cancel, result, children = threading.Event(), [], []

    def export():
        try:
            export_process.export_in_child(Tiny().eval(), [torch.rand(1, 3, 8, 8)], part, cancel=cancel)
        except export_process.ExportCancelled as exc:
            result.append(exc)

    t = threading.Thread(target=export)
    t.start()
    deadline = time.monotonic() + 30
    while not children and time.monotonic() < deadline:  # the child runs (importing torch)
        with export_process._LOCK:
            children = [proc for proc, _ in export_process._LIVE.values()]
        time.sleep(0.05)
    assert children
    part.write_bytes(b"")  # as if the exporter had begun writing
    cancel.set()
    t.join(10)
    assert not t.is_alive() and len(result) == 1
    assert children[0].poll() is not None  # stopped and reaped
    assert list(cache.iterdir()) == []


def test_stale_parts_and_old_tmp_files_are_removed(tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()
    stale = tmp_path / f".abc.{dead.pid}.0123456789ab.onnx.part"
    mine = export_cache.part_path(tmp_path / "abc.onnx")  # this process is alive: in progress
    old, young = tmp_path / "tmpk2j3_x.onnx", tmp_path / "tmpzz9.json"
    keep = tmp_path / "abc.onnx"
    for p in (stale, mine, old, young, keep):
        p.write_bytes(b"")
    past = time.time() - export_cache.LEGACY_TMP_AGE_S - 5
    os.utime(old, (past, past))
    assert sorted(export_cache.remove_stale_parts(tmp_path)) == sorted([stale, old])
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in (mine, young, keep))
