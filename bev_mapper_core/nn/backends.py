"""Inference backends for learned mappers: torch (the reference and the fallback), or the model
exported to ONNX and run by onnxruntime or OpenVINO (optional extras:
``pip install -e ".[fast]"``).

``MapperConfig.backend``:

* ``torch``: eager PyTorch (the reference; tests that compare maps cell for cell pin it);
* ``onnxruntime`` / ``openvino``: the model is exported once (PyTorch's dynamo exporter, opset
  18, static shapes) into a cache keyed by a hash of every parameter and buffer of the model,
  calibration-dependent tables included, and of the input shapes: ``$BEV_MAPPER_CACHE`` or
  ``~/.cache/bev_mapper``, ``onnx/<key>.onnx`` with its record ``<key>.json`` (what it was made
  from, its own SHA-256): verified before every use, a stale, damaged or refused file is
  exported again (:mod:`.export_cache`). A new calibration or new weights export again
  (about 7 s for the shipped surround6 Bi-Mapper on this machine); a later start reuses the
  file. OpenVINO runs in f32 (``INFERENCE_PRECISION_HINT``: its default on CPUs with bf16 units
  differs from torch by up to 0.13 in logits); the segmenter stage may ask for bf16
  (``MapperConfig.segmenter_precision``, issue #41).
* ``auto`` (the default, issue #28): the fastest installed: OpenVINO, else onnxruntime, else
  torch. The first start with new weights or a new calibration exports (and says so in the log,
  with the time it took); later starts load the cached file.

What is exported, per method (:class:`BackendRunner`): Bi-Mapper's whole forward pass with its
calibration; S2G2's image -> logits of the inference branch; FocusBEV's image -> BEV feature
(backbone, FPN, column transformer, cycle: all but a few per cent of its time), while its
memory bank, ego-motion fusion and head stay in torch (they take the kept features and poses of
earlier frames, which change in number).

Both runtimes use the mapper's thread count (``MapperConfig.threads`` or
:func:`~.runtime.inference_threads`). Outputs equal torch's within :data:`TOLERANCE` in
probability (tested per method on real frames). Nothing is downloaded: the runtimes are Python
packages, the model is the local weights file.
"""

from __future__ import annotations

import hashlib
import importlib.util
import logging
import os
import threading
import time
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from ..errors import ConfigError
from ..mapper import BACKENDS
from .export_cache import load_cached
from .export_process import ChildCannotImport, ExportCancelled, export_in_child
from .runtime import inference_threads

log = logging.getLogger("bev_mapper.export_cache")

#: Python module of each optional backend.
_MODULES = {"onnxruntime": "onnxruntime", "openvino": "openvino"}
#: ``auto``'s order of preference (measured: OpenVINO 2.3x, onnxruntime 1.6x torch eager on the
#: shipped surround6 Bi-Mapper, 1 thread; bench/bench_backends.py).
AUTO_ORDER = ("openvino", "onnxruntime")
#: Largest difference of an exported model's probabilities from torch's (tests check it).
TOLERANCE = 1e-4
#: Environment variable of the cache directory.
CACHE_ENV = "BEV_MAPPER_CACHE"


def installed_backends() -> tuple[str, ...]:
    """The backends usable here: ``torch`` and every optional runtime that is importable."""
    return ("torch",) + tuple(b for b in AUTO_ORDER if importlib.util.find_spec(_MODULES[b]) is not None)


def resolve_backend(name: str) -> str:
    """The backend that runs for ``name``: itself when installed, ``auto``'s pick.

    Raises:
        ConfigError: an unknown name, or a runtime that is not installed.
    """
    if name not in BACKENDS:
        raise ConfigError(f"backend must be one of {BACKENDS}, got {name!r}")
    have = installed_backends()
    if name == "auto":
        return next((b for b in AUTO_ORDER if b in have), "torch")
    if name not in have:
        raise ConfigError(f"backend {name!r} is not installed: pip install {_MODULES[name]} (or the package's "
                          f"'fast' extra), or use backend 'torch' or 'auto'")
    return name


def cache_dir() -> Path:
    """Where exported models are kept."""
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "bev_mapper")


def model_key(module: torch.nn.Module, inputs: Sequence[torch.Tensor]) -> str:
    """Hash of every parameter and buffer of ``module`` (non-persistent ones included) and of
    the inputs' shapes and dtypes: two modules with the same key export to the same graph.
    """
    h = hashlib.sha256(torch.__version__.encode())
    for name, t in list(module.named_parameters()) + list(module.named_buffers()):
        h.update(name.encode())
        h.update(str((tuple(t.shape), t.dtype)).encode())
        h.update(t.detach().cpu().contiguous().numpy().tobytes())
    for t in inputs:
        h.update(str((tuple(t.shape), t.dtype)).encode())
    return h.hexdigest()[:32]


def export_onnx(module: torch.nn.Module, inputs: Sequence[torch.Tensor], path: Path) -> Path:
    """Export ``module`` (eval mode, CPU) on example ``inputs`` to ``path`` (the export cache
    gives a temporary name in its directory and renames it once the file is complete). A module
    with an ``after_export(path, inputs)`` method has it called on the written file (the int8
    segmenter: :class:`~bev_mapper_core.methods.segmenter.int8.Int8Export`).
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    quiet = logging.getLogger("torch.onnx")  # its notes (e.g. on torchvision ops) are not for users
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            program = torch.onnx.export(module, tuple(inputs), dynamo=True, opset_version=18, verbose=False)
            program.save(str(path))
    finally:
        quiet.setLevel(level)
    after = getattr(module, "after_export", None)  # e.g. the int8 segmenter: quantized in place
    if after is not None:
        after(path, inputs)
    return path


class ExportedModel:
    """``module`` exported to ONNX and run by ``backend`` (``onnxruntime`` or ``openvino``):
    call it with numpy arrays shaped as the example inputs; returns a list of numpy outputs.

    The exported file comes from the verified cache (:func:`~.export_cache.load_cached`);
    ``fresh`` exports again whatever the cache holds. ``isolated``: a needed export runs in a
    child process (:mod:`.export_process`: stopped at once by ``cancel`` or
    :func:`~.export_process.cancel_exports`), else in this thread.

    Raises (constructor):
        ExportCancelled: an isolated export was stopped.
        ConfigError: the backend is not installed, the export failed, or the runtime refuses
            even a fresh export.
    """

    def __init__(self, module: torch.nn.Module, inputs: Sequence[torch.Tensor], backend: str, threads: int,
                 fresh: bool = False, isolated: bool = False, cancel: threading.Event | None = None,
                 precision: str = "f32") -> None:
        self.backend = resolve_backend(backend)
        self.precision = precision  # OpenVINO's INFERENCE_PRECISION_HINT (f32, or bf16 where the CPU has it)
        if self.backend == "torch":
            raise ConfigError("ExportedModel runs onnxruntime or openvino; torch runs the module itself")
        self.shapes = [tuple(t.shape) for t in inputs]
        self.threads, self.fresh, self.isolated, self._cancel = threads, fresh, isolated, cancel
        # verified cache (export_cache): a stale, damaged or refused file is exported again
        self._runner, self.path = load_cached(module, inputs, self.backend, cache_dir() / "onnx", self._export,
                                              self._load, fresh=fresh)

    def _export(self, module: torch.nn.Module, inputs: Sequence[torch.Tensor], part: Path) -> Path:
        if not self.isolated:
            return export_onnx(module, inputs, part)
        try:
            return export_in_child(module, inputs, part, threads=1, cancel=self._cancel)
        except ChildCannotImport as exc:
            log.warning("export cache: the export process cannot rebuild the model (%s); exporting in this process",
                        exc)
            return export_onnx(module, inputs, part)

    def _load(self, path: Path):
        """The runtime's session (onnxruntime) or compiled model (OpenVINO) of ``path`` and its
        input names.
        """
        if self.backend == "onnxruntime":
            import onnxruntime as ort

            opts = ort.SessionOptions()
            opts.intra_op_num_threads = self.threads
            opts.inter_op_num_threads = 1
            opts.log_severity_level = 4  # its own log lines for a refused file: the cache says it once
            session = ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
            names = [i.name for i in session.get_inputs()]
        else:
            import openvino as ov

            session = ov.Core().compile_model(str(path), "CPU", {"INFERENCE_NUM_THREADS": self.threads,
                                                                 "INFERENCE_PRECISION_HINT": self.precision})
            names = [i.get_any_name() for i in session.inputs]
        if len(names) != len(self.shapes):
            raise ValueError(f"the file takes {len(names)} inputs, the model {len(self.shapes)}")
        return session, names

    def __call__(self, *arrays: np.ndarray) -> list[np.ndarray]:
        """Run on numpy inputs (the example inputs' shapes)."""
        shapes = [a.shape for a in arrays]
        if shapes != self.shapes:
            raise ValueError(f"exported model takes inputs {self.shapes}, got {shapes}")
        session, names = self._runner
        feed = dict(zip(names, arrays))
        if self.backend == "onnxruntime":
            return session.run(None, feed)
        result = session(feed)
        return [result[o] for o in session.outputs]


class BackendRunner:
    """Runs one part of a learned mapper with the configured backend: eagerly in torch, or
    exported on first use (per calibration: :meth:`reset` when the model's tables change) and
    run by onnxruntime / OpenVINO. Every learned method's mapper holds one per exported part.

    ``backend``: ``MapperConfig.backend`` resolved (:func:`resolve_backend`); ``device``: the
    model's torch device (exported backends run on the CPU only: elsewhere torch runs);
    ``threads``: the runtime's intra-op threads; ``precision``: OpenVINO's inference precision
    (``f32``; ``bf16`` for the segmenter stage where the CPU has it, issue #41).

    ``background`` (the node, issue #41): the first call starts the export (or the cached file's
    check and load) in a thread, the export itself in a child process, and runs torch until the
    exported model is ready; the call after that switches to it (:attr:`state` says which runs).
    A failed export leaves the part on torch, said in :attr:`state`; :meth:`close` stops it.
    Without ``background`` the first call waits for the export (replay, benchmarks, tests).
    """

    def __init__(self, backend: str, device: torch.device, threads: int, background: bool = False,
                 precision: str = "f32") -> None:
        self.backend, self.device, self.threads, self.precision = backend, device, threads, precision
        self.background = background
        self.module: torch.nn.Module | None = None
        self._exported: ExportedModel | None = None
        self._job: _ExportJob | None = None
        self._failed = ""

    @property
    def eager(self) -> bool:
        """True when torch runs the part itself."""
        return self.backend == "torch" or self.device.type != "cpu"

    @property
    def state(self) -> str:
        """What runs the part now: the backend's name, or ``torch (...)`` while its export is
        under way or after it failed.
        """
        if self.eager or self._exported is not None:
            return "torch" if self.eager else self.backend
        if self._failed:
            return f"torch ({self.backend} failed: {self._failed})"
        if self._job is not None:
            return f"torch (until the {self.backend} model is ready)"
        return f"{self.backend} (not loaded yet)"

    def reset(self, module: torch.nn.Module) -> None:
        """The part to run from now on, for a (new) calibration: exported again on the next
        call. ``module`` returns a tensor or a tuple of tensors.
        """
        self.close(wait=False)
        self.module = module
        self._exported = None
        self._failed = ""

    def close(self, wait: bool = True, timeout: float = 10.0) -> None:
        """Stop a background export (its child process and partial file go); ``wait``: join
        its thread (a runtime loading a model finishes that first).
        """
        job, self._job = self._job, None
        if job is not None:
            job.cancel.set()
            if wait:
                job.thread.join(timeout)

    def __call__(self, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The part (:meth:`reset`) on ``inputs`` as a tuple of tensors, by the backend (inputs
        and outputs on the CPU for exported runs).
        """
        if self.module is None:
            raise RuntimeError("BackendRunner: no part to run yet (reset(module) first)")
        if not self.eager and self._exported is None and self.background:
            self._poll_background(inputs)
        if self.eager or (self._exported is None and self.background):
            out = self.module(*inputs)
            return out if isinstance(out, tuple) else (out,)
        if self._exported is None:
            self._exported = ExportedModel(self.module.eval(), inputs, self.backend, self.threads,
                                           precision=self.precision)
        arrays = [t.numpy() for t in inputs]
        try:
            outputs = self._exported(*arrays)
        except ValueError:  # inputs of other shapes: the caller's mistake, not the file's
            raise
        except Exception as exc:  # noqa: BLE001 - a runtime failing on the cached file: export again, once
            if self._exported.fresh:
                raise ConfigError(f"backend {self.backend!r} fails on a freshly exported model "
                                  f"({' '.join(str(exc).split())[:200]}); use backend 'torch'") from None
            log.warning("export cache: %s failed at run time (%s); exporting again", self._exported.path,
                        " ".join(str(exc).split())[:200])
            self._exported = ExportedModel(self.module.eval(), inputs, self.backend, self.threads, fresh=True,
                                           precision=self.precision)
            outputs = self._exported(*arrays)
        return tuple(torch.from_numpy(o) for o in outputs)

    def _poll_background(self, inputs: Sequence[torch.Tensor]) -> None:
        """Start the background export on the first call; take its model once it is ready."""
        if self._failed:
            return
        job = self._job
        if job is None:
            self._job = _ExportJob(self.module.eval(), [t.detach().clone() for t in inputs], self.backend, self.threads,
                                   self.precision)
            return
        if job.thread.is_alive():
            return
        self._job = None
        if job.model is not None:
            self._exported = job.model
            log.warning("export cache: switched from torch to %s (ready %.1f s after the first frame)", self.backend,
                        job.seconds)
        elif not job.cancel.is_set():
            self._failed = job.error or "unknown error"
            log.warning("export cache: staying on torch: %s", self._failed)

    def wait_ready(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s for a background export to finish (tests, benchmarks);
        True when it did. The next call switches.
        """
        job = self._job
        if job is None:
            return True
        job.thread.join(timeout)
        return not job.thread.is_alive()


class _ExportJob:
    """One background export of :class:`BackendRunner`: the cache check, the export in a child
    process when needed, and the runtime's load, in a daemon thread.
    """

    def __init__(self, module: torch.nn.Module, inputs: list[torch.Tensor], backend: str, threads: int,
                 precision: str = "f32") -> None:
        self.cancel = threading.Event()
        self.model: ExportedModel | None = None
        self.error = ""
        self.seconds = 0.0
        self._started = time.perf_counter()
        self.thread = threading.Thread(target=self._run, args=(module, inputs, backend, threads, precision),
                                       name="bev-export", daemon=True)
        self.thread.start()

    def _run(self, module, inputs, backend, threads, precision) -> None:
        try:
            model = ExportedModel(module, inputs, backend, threads, isolated=True, cancel=self.cancel, precision=precision)
            if not self.cancel.is_set():
                self.model = model
        except ExportCancelled:
            pass
        except Exception as exc:  # noqa: BLE001 - reported through BackendRunner.state, never fatal
            self.error = " ".join(str(exc).split())[:300] or type(exc).__name__
        self.seconds = time.perf_counter() - self._started


def backend_runner(config, device: torch.device) -> BackendRunner:
    """The :class:`BackendRunner` of a mapper's configuration (``MapperConfig``): its backend
    resolved, its thread count or :func:`~.runtime.inference_threads`; exports wait for the
    export until :meth:`~bev_mapper_core.mapper.Mapper.export_in_background` says otherwise.
    """
    return BackendRunner(resolve_backend(config.backend), device, config.threads or inference_threads())


__all__ = ["AUTO_ORDER", "BACKENDS", "CACHE_ENV", "TOLERANCE", "BackendRunner", "backend_runner", "ExportedModel", "export_onnx",
           "installed_backends", "model_key", "resolve_backend"]
