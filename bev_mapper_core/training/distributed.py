"""Data-parallel training: ``bev-train --nproc N`` or ``torchrun --nproc-per-node N bev-train ...``.

Every process (rank) builds the same model from the same seed, loads the same frames and walks
the same seeded batch order; of each global batch of ``cfg.batch`` frames it takes its own
contiguous part (:func:`~.data.shard_slice`), and torch's ``DistributedDataParallel`` averages
the gradients over the ranks (gloo on CPU, nccl on CUDA). Each rank's loss is scaled by
``n_rank * world / n_batch`` so that the averaged gradient is the gradient of the mean over the
whole batch also when a short last batch splits unevenly.

What is the same as one process, and what is not:

* **BatchNorm** layers normalize with the statistics of the whole global batch: on CUDA torch's
  ``SyncBatchNorm``; on CPU (where torch's ``SyncBatchNorm`` refuses to run) :class:`GlooSyncBatchNorm`,
  which all-reduces the per-channel sums over the process group. Running statistics are the
  global batch's too, so every rank holds the same buffers.
* A loss that is a **mean over the batch's frames** (or over a number of elements that is the
  same for every frame: the segmenter's unweighted cross-entropy, Bi-Mapper's terms when every
  cell is labeled) gives the loss and gradient of one process, to float rounding (tested).
  Losses normalized by **counts that vary per frame** (visible cells: Bi-Mapper's and S2G2's
  masked BCE, ASL; the segmenter's class-weighted cross-entropy, FocusBEV's weighted BCE) are
  per rank normalized by that rank's count and then averaged over ranks: the same estimator as
  with a smaller batch, close to, but not exactly, the single-process loss.
* Random layers (dropout, stochastic depth, augmentation) draw from a per-rank seeded stream:
  the same distribution as one process, not the same numbers.
* A method's after-step state (S2G2's EMA passive branch) is updated by every rank from the
  same parameters, so it stays the same on every rank.

Rank 0 alone logs, validates and writes the run directory (checkpoints, optimizer state,
``metrics.jsonl``); the other ranks wait at a barrier. Threads: each rank takes
``max(1, cfg.threads // local processes)``. A failing rank ends the whole run: the ``--nproc``
launcher stops every process and raises :class:`DistributedError` with the rank's message
(torchrun does the same for its workers); collectives time out after
:data:`COLLECTIVE_TIMEOUT_S`.
"""

from __future__ import annotations

import os
import queue as queue_mod
import socket
import sys
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from datetime import timedelta
from typing import TYPE_CHECKING, Any

import torch
import torch.distributed as dist
from torch.nn.modules.batchnorm import _BatchNorm

from ..errors import BevMapperError, ConfigError

if TYPE_CHECKING:
    from .config import TrainConfig
    from .method import TrainMethod

#: Seconds a collective (a barrier while rank 0 validates, a gradient all-reduce) may wait for
#: the other ranks before the run fails.
COLLECTIVE_TIMEOUT_S = 1800.0
#: How often (s) the ``--nproc`` launcher looks at its processes and forwards rank 0's log.
POLL_S = 0.2
#: Offset between the per-epoch torch seeds of consecutive ranks (rank 0 keeps the one-process seed).
RANK_SEED_STRIDE = 1_000_003


class DistributedError(BevMapperError):
    """A data-parallel run failed in one of its processes (or could not start)."""


# --------------------------------------------------------------------- the ranks
@dataclass(frozen=True)
class Ranks:
    """This process's place in a data-parallel run (the default: the only process).

    Args:
        rank, world: global rank and number of processes.
        local_rank, local_world: the same on this machine (threads, CUDA device).
        cuda: the run trains on CUDA (nccl; a device per local rank).
    """

    rank: int = 0
    world: int = 1
    local_rank: int = 0
    local_world: int = 1
    cuda: bool = False

    @property
    def is_main(self) -> bool:
        """Rank 0: the one that logs, validates and writes."""
        return self.rank == 0

    @property
    def shard(self) -> tuple[int, int]:
        """``(rank, world)`` for :meth:`~.sources.TrainData.batches`."""
        return self.rank, self.world

    def threads(self, total: int) -> int:
        """Torch threads of this rank: ``total`` shared by the processes on this machine."""
        return max(1, total // self.local_world)

    def device(self, name: str) -> torch.device:
        """The torch device of this rank: ``cuda:<local rank>`` for a CUDA run of several processes."""
        if self.world > 1 and self.cuda:
            return torch.device("cuda", self.local_rank)
        return torch.device(name)

    def epoch_seed(self, seed: int) -> int:
        """Per-rank torch seed of an epoch whose one-process seed is ``seed``."""
        return seed + self.rank * RANK_SEED_STRIDE

    def init(self, init_method: str) -> None:
        """Join the process group (gloo, nccl for CUDA) of this run."""
        if self.world > 1:
            dist.init_process_group("nccl" if self.cuda else "gloo", init_method=init_method, rank=self.rank,
                                    world_size=self.world, timeout=timedelta(seconds=COLLECTIVE_TIMEOUT_S))

    def close(self) -> None:
        """Leave the process group (after every rank is done with its collectives)."""
        if self.world > 1 and dist.is_initialized():
            dist.barrier()
            dist.destroy_process_group()

    def barrier(self) -> None:
        """Wait for every rank."""
        if self.world > 1:
            dist.barrier()

    def in_turn(self, fn: Callable[[], Any]) -> Any:
        """``fn()`` on rank 0 first, then on the others (rank 0 renders and caches drives, the
        others read its cache instead of writing the same files at the same time).
        """
        if self.world == 1:
            return fn()
        if self.is_main:
            out = fn()
            self.barrier()
            return out
        self.barrier()
        return fn()

    def any(self, flag: bool) -> bool:
        """True on every rank if ``flag`` is true on some rank (a time budget all ranks obey)."""
        if self.world == 1:
            return flag
        t = torch.tensor([float(flag)], device=self._comm_device())
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return bool(t.item() > 0)

    def reduce_parts(self, parts: dict[str, float], n: int) -> tuple[dict[str, float], float]:
        """Loss parts of a rank's ``n`` frames -> ``(mean over the global batch, loss scale)``:
        the frame-weighted mean of every rank's parts, and ``n * world / n_global``, the factor
        that makes DDP's gradient average the gradient of the global batch's mean.
        """
        if self.world == 1:
            return parts, 1.0
        keys = list(parts)
        t = torch.tensor([float(n)] + [n * float(parts[k]) for k in keys], dtype=torch.float64,
                         device=self._comm_device())
        dist.all_reduce(t)
        total = float(t[0])
        return {k: float(t[i + 1]) / total for i, k in enumerate(keys)}, n * self.world / total

    def wrap(self, method: "TrainMethod") -> Callable[..., tuple[torch.Tensor, dict[str, float]]]:
        """``method.loss`` as this run computes it: as is for one process; else with synchronized
        BatchNorm, through DistributedDataParallel (which averages the gradients in backward).
        """
        if self.world == 1:
            return method.loss
        import warnings

        from torch.nn.parallel import DistributedDataParallel

        # a gradient laid out unlike its bucket costs a copy, nothing else (depthwise convolutions)
        warnings.filterwarnings("ignore", message="Grad strides do not match bucket view strides")

        if self.cuda:
            method.model = torch.nn.SyncBatchNorm.convert_sync_batchnorm(method.model)
        else:
            method.model = convert_batchnorm(method.model)
        return DistributedDataParallel(_LossModule(method), device_ids=[self.local_rank] if self.cuda else None,
                                       find_unused_parameters=True)

    def _comm_device(self) -> torch.device:
        return torch.device("cuda", self.local_rank) if self.cuda else torch.device("cpu")


class _LossModule(torch.nn.Module):
    """The module DDP wraps: the method's model as its submodule, ``method.loss`` as forward."""

    def __init__(self, method: "TrainMethod") -> None:
        super().__init__()
        self.model = method.model
        self.method_loss = method.loss

    def forward(self, batch: dict, epoch: int, step: int):  # noqa: D102 - see TrainMethod.loss
        return self.method_loss(batch, epoch, step)


def batch_frames(batch: dict) -> int:
    """Frames in a training batch (a FrameSet batch, or S2G2's ``{"labeled", "unlabeled"}``)."""
    return len(batch["labeled"]["target"] if "labeled" in batch else batch["target"])


# ------------------------------------------------------- BatchNorm across ranks (CPU)
class _SumOverRanks(torch.autograd.Function):
    """All-reduce (sum) whose gradient is the all-reduced gradient (every rank's output depends
    on every rank's input).
    """

    @staticmethod
    def forward(ctx, t: torch.Tensor) -> torch.Tensor:  # noqa: D102
        t = t.clone()
        dist.all_reduce(t)
        return t

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> torch.Tensor:  # noqa: D102
        grad = grad.clone()
        dist.all_reduce(grad)
        return grad


class GlooSyncBatchNorm(_BatchNorm):
    """BatchNorm with the statistics of the whole global batch over the default process group,
    on any backend (gloo: CPU), in training mode; eval mode (or one process) is plain BatchNorm.
    Same parameters and buffers as the BatchNorm it replaces (:func:`convert_batchnorm`).
    """

    def _check_input_dim(self, input: torch.Tensor) -> None:
        if input.dim() < 2:
            raise ValueError(f"expected at least 2-D input (N, C, ...), got {input.dim()}-D")

    def forward(self, input: torch.Tensor) -> torch.Tensor:  # noqa: D102
        if not (self.training and dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(input)
        self._check_input_dim(input)
        C = input.shape[1]
        dims = [0, *range(2, input.dim())]
        shape = (1, C, *([1] * (input.dim() - 2)))  # per-channel values broadcast over (N, C, ...)
        count = input.new_tensor([input.numel() / C])
        sums = _SumOverRanks.apply(torch.cat([input.sum(dims), count]))  # (C + 1,): sums, frames x cells
        n = sums[C].detach()
        mean = sums[:C] / n
        centered = input - mean.view(shape)
        var = _SumOverRanks.apply((centered * centered).sum(dims)) / n  # biased, as BatchNorm normalizes
        out = centered * torch.rsqrt(var + self.eps).view(shape)
        if self.affine:
            out = out * self.weight.view(shape) + self.bias.view(shape)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                f = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked)
                self.running_mean.mul_(1 - f).add_(mean.detach(), alpha=f)
                self.running_var.mul_(1 - f).add_(var.detach() * (n / (n - 1).clamp(min=1)), alpha=f)
        return out


def convert_batchnorm(module: torch.nn.Module) -> torch.nn.Module:
    """``module`` with every BatchNorm layer replaced by a :class:`GlooSyncBatchNorm` holding the
    same parameter and buffer tensors (an optimizer built before keeps working).
    """
    out = module
    if isinstance(module, _BatchNorm) and not isinstance(module, GlooSyncBatchNorm):
        out = GlooSyncBatchNorm(module.num_features, module.eps, module.momentum, module.affine,
                                module.track_running_stats)
        if module.affine:
            out.weight, out.bias = module.weight, module.bias
        if module.track_running_stats:
            out.running_mean, out.running_var = module.running_mean, module.running_var
            out.num_batches_tracked = module.num_batches_tracked
        out.train(module.training)
    for name, child in module.named_children():
        out.add_module(name, convert_batchnorm(child))
    return out


# --------------------------------------------------------------------- launching
def torchrun_ranks(cfg: "TrainConfig") -> Ranks | None:
    """The ranks of a run started by ``torchrun`` (``RANK`` / ``WORLD_SIZE`` / ``LOCAL_RANK`` set,
    world > 1), else None.
    """
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1 or "RANK" not in os.environ:
        return None
    if cfg.nproc not in (1, world):
        raise ConfigError(f"nproc {cfg.nproc} under torchrun, whose world size is {world}: leave nproc at 1")
    if cfg.batch % world:
        raise ConfigError(f"batch {cfg.batch} is the global batch of torchrun's {world} processes: it must be a "
                          "multiple of the world size")
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", str(world)))
    return Ranks(int(os.environ["RANK"]), world, int(os.environ.get("LOCAL_RANK", "0")), local_world,
                 cfg.device.startswith("cuda"))


def is_main_process() -> bool:
    """False in a torchrun worker of rank > 0 (it prints no results)."""
    return int(os.environ.get("RANK", "0")) == 0


def free_port() -> int:
    """A TCP port free on localhost now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def launch(cfg: "TrainConfig", log: Callable[[str], None], data: Any, run: Callable[..., dict]) -> dict:
    """Run ``run(cfg, log, data, ranks)`` in ``cfg.nproc`` fresh local processes (spawned: ``data``
    must pickle); rank 0's log lines reach ``log`` here; returns rank 0's result.

    Raises:
        DistributedError: a rank failed (the others are stopped): its message.
    """
    import torch.multiprocessing as tmp

    cuda = cfg.device.startswith("cuda")
    if cuda and torch.cuda.device_count() < cfg.nproc:
        raise ConfigError(f"nproc {cfg.nproc} on CUDA needs a GPU per process; {torch.cuda.device_count()} visible")
    q = tmp.get_context("spawn").Queue()
    init = f"tcp://127.0.0.1:{free_port()}"
    ctx = tmp.start_processes(_worker, args=(cfg.nproc, init, cfg, data, q, run), nprocs=cfg.nproc, join=False,
                              start_method="spawn")
    result: dict[str, Any] = {}
    errors: list[tuple[int, str, bool]] = []
    finished: set[int] = set()  # ranks that completed their run and left the group

    def drain(wait: float = 0.0) -> None:
        while True:
            try:
                msg = q.get(timeout=wait) if wait else q.get_nowait()
            except queue_mod.Empty:
                return
            if msg[0] == "log":
                log(msg[1])
            elif msg[0] == "done":
                result["doc"] = msg[1]
            elif msg[0] == "finished":
                finished.add(msg[1])
            else:
                errors.append(msg[1:])

    try:
        while True:
            drain()
            try:
                if ctx.join(timeout=POLL_S):
                    break
            except Exception as e:  # torch's ProcessExitedException / ProcessRaisedException
                drain(wait=0.5)
                if not errors and len(finished) == cfg.nproc and "doc" in result:
                    break  # every rank had finished: a crash in the interpreter's teardown loses nothing
                if errors:  # the rank's own error first, then errors of ranks that lost a peer
                    rank, msg, _ = sorted(errors, key=lambda x: not x[2])[0]
                    raise DistributedError(f"rank {rank}: {msg}") from None
                raise DistributedError(f"a training process failed ({e})") from None
        drain(wait=0.5)
    finally:
        for p in ctx.processes:
            if p.is_alive():
                p.terminate()
        q.close()
    if "doc" not in result:
        raise DistributedError("rank 0 ended without a result")
    return result["doc"]


def _worker(rank: int, world: int, init: str, cfg: "TrainConfig", data: Any, q, run: Callable[..., dict]) -> None:
    """One spawned rank: join the group, train, report (result or error) through ``q``."""
    ranks = Ranks(rank, world, rank, world, cfg.device.startswith("cuda"))
    try:
        ranks.init(init)
        doc = run(cfg, (lambda m: q.put(("log", m))) if ranks.is_main else no_log, data, ranks)
        ranks.close()
        if ranks.is_main:
            q.put(("done", doc))
        q.put(("finished", rank))
        q.close()
        q.join_thread()
    except BaseException as e:  # noqa: BLE001 - every failure must reach the launcher
        own = isinstance(e, (BevMapperError, OSError))
        if not own and not isinstance(e, KeyboardInterrupt):
            traceback.print_exc(file=sys.stderr)
        q.put(("error", rank, str(e) if own else f"{type(e).__name__}: {e}", own))
        q.close()
        q.join_thread()
        raise SystemExit(1) from None


def no_log(_msg: str) -> None:
    """The log of ranks other than 0."""


__all__ = ["COLLECTIVE_TIMEOUT_S", "DistributedError", "GlooSyncBatchNorm", "Ranks", "batch_frames",
           "convert_batchnorm", "free_port", "is_main_process", "launch", "no_log", "torchrun_ranks"]
