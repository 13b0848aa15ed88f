"""The ONNX export cache is verified before use (issue #29): a damaged file (truncated,
emptied, text, bit-flipped, a directory in its place) and a stale one (another model's file under
this key, a record of other weights) are exported again, said once in the log; the outputs are
this module's, never the stale model's; a file the runtime refuses, per runtime; a mapper started on a damaged
cache maps."""

from __future__ import annotations

import importlib.util
import json
import logging

import numpy as np
import pytest
import torch

from bev_mapper_core.nn import backends, export_cache

pytestmark = pytest.mark.slow
RUNTIMES = ["onnxruntime", "openvino"]


class Tiny(torch.nn.Module):
    """A small convolution net (exports in ~1 s) with a buffer standing for calibration tables."""

    def __init__(self, seed: int) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.conv = torch.nn.Conv2d(3, 4, 3, padding=1)
        self.register_buffer("table", torch.linspace(0, 1, 4).view(1, 4, 1, 1))

    def forward(self, x):
        return torch.softmax(self.conv(x) + self.table, dim=1)


def _need(backend: str) -> None:
    if importlib.util.find_spec(backend) is None:
        pytest.skip(f"{backend} is not installed (the 'fast' extra)")


def _run(module: torch.nn.Module, x: torch.Tensor, backend: str) -> tuple[np.ndarray, backends.ExportedModel]:
    model = backends.ExportedModel(module.eval(), [x], backend, threads=1)
    return model(x.numpy())[0], model


def _damage(path, how: str, other=None) -> None:
    data = path.read_bytes()
    if how == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "text":
        path.write_text("this is not a model\n" * 50)
    elif how == "bitflip":
        b = bytearray(data)
        for i in range(64, len(b), max(1, len(b) // 40)):
            b[i] ^= 0x5A
        path.write_bytes(bytes(b))
    elif how == "directory":
        path.unlink()
        path.mkdir()
        (path / "junk").write_text("x")
    elif how == "other_model":  # the same net exported with other weights, put under this key
        path.write_bytes(other.read_bytes())
    elif how == "record_of_other_weights":  # the other model's file and record under this key
        path.write_bytes(other.read_bytes())
        export_cache.record_path(path).write_bytes(export_cache.record_path(other).read_bytes())
    elif how == "record_missing":
        export_cache.record_path(path).unlink()
    elif how == "refused":  # junk with a record that vouches for it: only the runtime can tell
        path.write_bytes(b"\x08\x07" + b"junk" * 100)
        rec = json.loads(export_cache.record_path(path).read_text())
        rec.update(onnx_sha256=export_cache.file_sha256(path), onnx_bytes=path.stat().st_size)
        export_cache.record_path(path).write_text(json.dumps(rec))
    elif how == "record_damaged":
        rec = json.loads(export_cache.record_path(path).read_text())
        del rec["onnx_sha256"]
        export_cache.record_path(path).write_text(json.dumps(rec)[:-9])
    else:  # pragma: no cover
        raise AssertionError(how)


CASES = ["truncated", "empty", "text", "bitflip", "directory", "other_model", "record_of_other_weights",
         "record_missing", "record_damaged", "refused"]
#: The file and record checks come before any runtime reads the file (export_cache.check_cached), so
#: each runtime takes half of them (each export costs seconds); both take "refused", where the
#: runtime itself is the check.
CASES_OF = {"onnxruntime": CASES[0:9:2] + ["refused"], "openvino": CASES[1:9:2] + ["refused"]}
assert sorted(set(sum(CASES_OF.values(), []))) == sorted(CASES)


@pytest.mark.parametrize("backend", RUNTIMES)
def test_damaged_and_stale_cache_files_are_exported_again(backend, tmp_path, monkeypatch, caplog):
    _need(backend)
    monkeypatch.setenv(backends.CACHE_ENV, str(tmp_path))
    x = torch.rand(1, 3, 8, 8)
    mine, other = Tiny(1), Tiny(2)
    with torch.no_grad():
        want, other_want = mine(x).numpy(), other(x).numpy()
    got, model = _run(mine, x, backend)
    np.testing.assert_allclose(got, want, atol=backends.TOLERANCE)
    path = model.path
    record = json.loads(export_cache.record_path(path).read_text())
    made = record["made_from"]
    assert record["onnx_sha256"] == export_cache.file_sha256(path) and record["backend"] == backend
    assert set(made) >= {"weights_sha256", "calibration_sha256", "inputs", "exporter", "package"}
    assert record["runtimes"][backend] == export_cache.runtime_version(backend)
    _, other_model = _run(other, x, backend)
    assert other_model.path != path
    for how in CASES_OF[backend]:
        _damage(path, how, other_model.path)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="bev_mapper.export_cache"):
            got, again = _run(mine, x, backend)
        said = [r.getMessage() for r in caplog.records if "exporting again" in r.getMessage()]
        assert len(said) == 1 and str(path) in said[0], (how, said)
        if how == "refused":
            assert f"{backend} refused to load it" in said[0], said
        np.testing.assert_allclose(got, want, atol=backends.TOLERANCE, err_msg=how)
        assert np.abs(got - other_want).max() > 1e-3, how  # never the other weights' outputs
        assert again.path == path and path.is_file()
        assert export_cache.check_cached(path, made) is None, how  # the cache is good again
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="bev_mapper.export_cache"):
        _run(mine, x, backend)  # a good cache: used without a word
    assert not caplog.records


def test_calibration_and_input_size_change_the_cache_entry(tmp_path, monkeypatch):
    """The key is made from the module and inputs alone (export_cache.made_from): one runtime tells."""
    backend = next((b for b in RUNTIMES if importlib.util.find_spec(b) is not None), RUNTIMES[0])
    _need(backend)
    monkeypatch.setenv(backends.CACHE_ENV, str(tmp_path))
    mine = Tiny(1)
    x = torch.rand(1, 3, 8, 8)
    _, a = _run(mine, x, backend)
    mine.table.add_(0.5)  # a new calibration table, same weights
    _, b = _run(mine, x, backend)
    _, c = _run(mine, torch.rand(1, 3, 8, 12), backend)
    assert len({a.path, b.path, c.path}) == 3
    ra, rb = (json.loads(export_cache.record_path(p).read_text())["made_from"] for p in (a.path, b.path))
    assert ra["weights_sha256"] == rb["weights_sha256"] and ra["calibration_sha256"] != rb["calibration_sha256"]


@pytest.mark.parametrize("backend", RUNTIMES)
def test_runner_recovers_from_a_damaged_cache_after_a_reset(backend, tmp_path, monkeypatch):
    """What a node does on a new calibration (BackendRunner.reset): a cache file damaged
    meanwhile is exported again and the runner maps; it never keeps failing."""
    _need(backend)
    monkeypatch.setenv(backends.CACHE_ENV, str(tmp_path))
    mine, x = Tiny(3), torch.rand(1, 3, 8, 8)
    runner = backends.BackendRunner(backend, torch.device("cpu"), threads=1)
    runner.reset(mine.eval())
    first = runner(x)[0]
    path = next((tmp_path / "onnx").glob("*.onnx"))
    path.write_bytes(path.read_bytes()[:100])
    runner.reset(mine.eval())
    np.testing.assert_allclose(runner(x)[0].numpy(), first.numpy(), atol=backends.TOLERANCE)
