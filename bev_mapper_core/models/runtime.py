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


def inference_threads() -> int:
    """Torch CPU threads for inference: ``$BEV_MAPPER_TORCH_THREADS`` or the CPUs we may use."""
    env = os.environ.get(THREADS_ENV)
    if env:
        try:
            return max(1, int(env))
        except ValueError:
            raise ConfigError(f"{THREADS_ENV} must be an integer, got {env!r}") from None
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def inference_device(config: MapperConfig) -> torch.device:
    """The torch device of ``config.device`` for inference; on the CPU, also sets torch's thread
    count (``config.threads``, else :func:`inference_threads`).

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
    return device


__all__ = ["THREADS_ENV", "inference_device", "inference_threads"]
