"""Data-parallel training over several processes: PyTorch DDP under `torchrun`.

`torchrun --nproc_per_node=P -m mpsim train ...` starts P copies of the same command; `torchrun` gives each
its rank through the environment (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``, ``MASTER_ADDR``/``MASTER_PORT``).
Every rank builds the same data and model (same seeds), and the trainer then splits each global batch of
trajectories (or windows, or N-body states drawn from them) into P contiguous parts, one per rank. DDP
all-reduces the gradients; each rank's loss is weighted so that the average of the ranks' gradients is the
gradient of the global batch's mean loss, exactly as one process would compute it. Evaluation is sharded the
same way and the predictions gathered, so every rank takes the same learning-rate and early-stopping decisions.
Only rank 0 writes files (metrics, checkpoints, plots, loggers).

Backend: ``gloo`` on CPU, ``nccl`` on CUDA (one GPU per local rank), chosen from the device.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import torch
import torch.distributed as torch_dist

from mpsim.errors import ConfigError

if TYPE_CHECKING:
    from mpsim.models.base import Model


def env_world() -> tuple[int, int, int]:
    """(rank, world size, local rank) from the environment `torchrun` sets; (0, 1, 0) without it."""
    return (
        int(os.environ.get("RANK", "0")),
        int(os.environ.get("WORLD_SIZE", "1")),
        int(os.environ.get("LOCAL_RANK", "0")),
    )


@dataclass(frozen=True)
class DistContext:
    """Where this process stands in a data-parallel job (a one-process job by default).

    Attributes:
        rank: this process's rank (0 writes files).
        world_size: number of processes.
        local_rank: rank on this machine (picks the GPU).
        backend: ``gloo`` or ``nccl`` (None for one process).
        device: where this rank computes.
    """

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    backend: str | None = None
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    # ---- sharding ------------------------------------------------------------------------------------
    def local_slice(self, n: int) -> slice:
        """This rank's contiguous part of n items (parts differ in size by at most one)."""
        base, extra = divmod(n, self.world_size)
        start = self.rank * base + min(self.rank, extra)
        return slice(start, start + base + (self.rank < extra))

    def shard(self, idx: torch.Tensor) -> tuple[torch.Tensor, float]:  # idx: [b] global batch of item indices
        """This rank's items of a global batch and the weight of its loss.

        The weight n_local · P / b makes DDP's mean of the ranks' gradients equal the gradient of the mean
        loss over the whole batch, also when the parts differ in size. A rank whose part is empty (a batch
        smaller than P) runs the batch's first item with weight 0: every rank must join each all-reduce.

        Returns:
            ([n_local] item indices, loss weight).
        """
        if not self.enabled:
            return idx, 1.0
        part = idx[self.local_slice(len(idx))]
        if len(part) == 0:
            return idx[:1], 0.0
        return part, len(part) * self.world_size / len(idx)

    # ---- collectives ---------------------------------------------------------------------------------
    def all_sum(self, values: Sequence[float]) -> list[float]:
        """Element-wise sums of `values` over the ranks (float64; NaN/inf on any rank reach every rank)."""
        if not self.enabled:
            return [float(v) for v in values]
        buf = torch.tensor([float(v) for v in values], dtype=torch.float64, device=self._comm_device)
        torch_dist.all_reduce(buf)
        return buf.cpu().tolist()

    def gather(self, part: torch.Tensor, n: int) -> torch.Tensor:  # part: [n_local, ...] this rank's rows
        """[n, ...] the rows of every rank's `local_slice(n)`, in order, on every rank (on `part`'s device)."""
        if not self.enabled:
            return part
        base, extra = divmod(n, self.world_size)
        sizes = [base + (r < extra) for r in range(self.world_size)]
        rows = max(sizes)
        padded = part.new_zeros((rows, *part.shape[1:])).to(self._comm_device)
        padded[: len(part)] = part.to(self._comm_device)
        out = [torch.empty_like(padded) for _ in range(self.world_size)]
        torch_dist.all_gather(out, padded)
        return torch.cat([o[:s] for o, s in zip(out, sizes, strict=True)]).to(part.device)

    def barrier(self) -> None:
        if self.enabled:
            torch_dist.barrier()

    @property
    def _comm_device(self) -> torch.device:
        return self.device if self.backend == "nccl" else torch.device("cpu")

    # ---- the model -----------------------------------------------------------------------------------
    def wrap(self, model: Model) -> Callable[..., tuple[torch.Tensor, torch.Tensor]]:
        """`model.training_loss` for this job: the method itself in one process; under several, the same call
        through `DistributedDataParallel`, so that `backward()` all-reduces (averages) the gradients.

        `static_graph`: the set of parameters a model's loss uses is the same at every step, so DDP learns it
        from the first step — also when some are unused (e.g. MP-NODE's ``zero_messages``), which would
        otherwise leave DDP waiting for their gradients — and afterwards skips the per-step graph traversal
        that `find_unused_parameters` costs. Buffers (normalisation, counters) follow rank 0's.
        """
        if not self.enabled:
            return model.training_loss
        return torch.nn.parallel.DistributedDataParallel(_TrainingLoss(model), device_ids=None, static_graph=True)


class _TrainingLoss(torch.nn.Module):
    """`model.training_loss` as a module's forward: what DDP hooks into."""

    def __init__(self, model: Model) -> None:
        super().__init__()
        self.model = model

    def forward(self, *args: Any, **kwargs: Any) -> tuple[torch.Tensor, torch.Tensor]:
        return self.model.training_loss(*args, **kwargs)


SINGLE = DistContext()


def setup(device: torch.device, timeout_s: float = 1800.0) -> DistContext:
    """Join the process group `torchrun` describes in the environment (nothing for one process).

    Args:
        device: the device the command chose (``cuda`` becomes ``cuda:<local rank>``).
        timeout_s: how long a collective waits for the other ranks.

    Raises:
        ConfigError: more ranks on this machine than GPUs.
    """
    rank, world, local = env_world()
    if world <= 1:
        return DistContext(device=device)
    if device.type == "cuda":
        if torch.cuda.device_count() <= local:
            raise ConfigError(
                f"torchrun started local rank {local} but this machine has {torch.cuda.device_count()} GPU(s). "
                "Use --nproc_per_node=<number of GPUs>, or device=cpu for CPU processes."
            )
        device = torch.device("cuda", local)
        torch.cuda.set_device(device)
        backend = "nccl"
    else:
        backend = "gloo"
    if not torch_dist.is_initialized():
        torch_dist.init_process_group(backend, timeout=datetime.timedelta(seconds=timeout_s))
    return DistContext(rank=rank, world_size=world, local_rank=local, backend=backend, device=device)


LEAVE_TIMEOUT = datetime.timedelta(days=7)  # how long ranks wait in `teardown` for rank 0's final evaluation


def teardown(ctx: DistContext, *, together: bool = True) -> None:
    """Leave the process group (after the last collective of this process).

    Args:
        together: on gloo, first wait (a barrier) until every rank has got here. Pass it on the way out of a
            job that succeeded; pass False on an error path, where a rank that failed between collectives would
            otherwise leave the others waiting in the barrier.

    Why gloo ranks leave together: gloo's worker threads free a finished collective's tensors a moment after
    the caller has its result, and freeing a tensor Python created takes the GIL. A rank that went straight
    on to exit (rank 1 does: rank 0 alone evaluates and writes) could reach interpreter shutdown while such
    a thread still held or waited for the GIL, and the process aborted ("terminate called without an active
    exception", SIGABRT; 4 of 116 two-process runs on 2 busy cores, a core dump shows the thread freeing an
    all-gather's tensors). `destroy_process_group` does not stop those threads once a DDP wrapper has been
    built (torch 2.13: the 3 extra threads of a gloo job outlive it). In the barrier the GIL is free until the
    slowest rank arrives, so the threads are done before any rank goes on to exit. The barrier waits up to
    `LEAVE_TIMEOUT` (rank 0's final evaluation may take longer than a collective's timeout).
    """
    if ctx.enabled and torch_dist.is_initialized():
        if together and ctx.backend == "gloo":
            torch_dist.monitored_barrier(timeout=LEAVE_TIMEOUT)
        torch_dist.destroy_process_group()
