"""Where and how learned mappers run at inference: the torch device and CPU thread count, one
rule for every learned method (Bi-Mapper, the segmenter stage, S2G2).
"""

from __future__ import annotations

import os

import torch

from ..errors import ConfigError
from ..mapper import MapperConfig

#: Environment variable overriding the number of torch CPU threads used for inference.
THREADS_ENV = "BEV_MAPPER_TORCH_THREADS"


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask, e.g. ``taskset`` / a container's cpuset)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def inference_threads() -> int:
    """Torch (and onnxruntime / OpenVINO) CPU threads for inference: ``$BEV_MAPPER_TORCH_THREADS``,
    else ``$OMP_NUM_THREADS`` when set (a Ray task of ``bev-bag evaluate`` gets its ``num_cpus``
    there, so N tasks on a node use N cores), else every CPU but one (at least 1): the same rule
    in the node, ``bev-bag replay`` and the benchmarks.

    The CPU left over is for what feeds the model: the node's executor and the DDS threads
    receiving the next set, replay's reading and decoding. On a shared robot computer an
    oversubscribed torch collapses: its OpenMP threads spin-wait for each other while one of
    them waits for a core. Measured with ``bench/bench_backends.py --competitor`` (2 cores, one
    busy competing process) and printed there beside the quiet figures.
    """
    env = os.environ.get(THREADS_ENV)
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ConfigError(f"{THREADS_ENV} must be an integer, got {env!r}") from None
    omp = os.environ.get("OMP_NUM_THREADS", "")
    if omp.isdigit() and int(omp) >= 1:  # set by a scheduler (a Ray task: its num_cpus) or the user
        return int(omp)
    return max(1, available_cpus() - 1)


def _one_interop_thread() -> None:
    """Torch's inter-op pool to 1 thread (the models run no independent ops in parallel; a pool
    sized to the machine would only compete with the intra-op threads). Settable once, before
    any inter-op work; later calls keep what is set.
    """
    if torch.get_num_interop_threads() != 1:
        try:
            torch.set_num_interop_threads(1)
        except RuntimeError:  # already started (e.g. by the embedding program): leave it
            pass


def inference_device(config: MapperConfig) -> torch.device:
    """The torch device of ``config.device`` for inference; on the CPU, also sets torch's thread
    count (``config.threads``, else :func:`inference_threads`) and its inter-op pool to 1.

    Raises:
        ConfigError: not a torch device, or CUDA requested but not available.
    """
    try:
        device = torch.device(config.device)
    except (RuntimeError, TypeError) as e:
        raise ConfigError(f"invalid torch device {config.device!r} ({e})") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ConfigError(f"device {config.device!r} requested but CUDA is not available")
    if device.type == "cpu":
        torch.set_num_threads(config.threads or inference_threads())
        _one_interop_thread()
    return device


__all__ = ["THREADS_ENV", "available_cpus", "inference_device", "inference_threads"]
