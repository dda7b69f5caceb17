"""Data-parallel training over several processes (PyTorch DistributedDataParallel).

One process per rank, started by ``torchrun`` (or by ``polspike train --nproc N``, which starts
``torchrun --standalone`` on this machine).  Each rank reads only its share of every global batch;
the gradients are averaged across the ranks by DDP, so a step of N ranks is the step of one process
on the whole global batch (to float rounding):

* the global batch of step s is :class:`reconstruct.net.train._BatchOrder`'s (a function of seed, epoch
  and position, not of N); rank r takes the contiguous rows ``r * b .. (r + 1) * b - 1`` with
  ``b = batch_size / N`` (a world size that does not divide the batch is a ConfigError);
* every loss term is a mean over equal-sized per-rank batches, so the mean of the per-rank gradients
  is the gradient of the whole batch; the learning rate is the config's for any N;
* per-item random draws of a step (``force_prob``'s jitter, the assumed-glass picks) are drawn for the
  whole global batch from the step's generator and sliced, as one process draws them;
* rank 0 alone writes ``last.pt``, ``best.pt``, ``log.csv``, ``config.json`` and validates; the logged
  losses are the means over the ranks.  Every rank resumes from the same ``last.pt``, whose step alone
  fixes the rest of the trajectory: a run resumes with any N.

Backends: gloo on CPU, nccl on CUDA (each rank on ``cuda:LOCAL_RANK``).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from datetime import timedelta

import torch

from polinfra.errors import ConfigError
from polinfra.faults import fault_point

__all__ = ["Ranks", "SINGLE", "world_from_env", "init_ranks", "check_world", "shutdown"]

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Ranks:
    """This process's place among the training processes (``world = 1``: the single-process run)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def active(self) -> bool:
        return self.world > 1

    @property
    def is_writer(self) -> bool:
        """Rank 0 writes checkpoints, logs and validates."""
        return self.rank == 0

    def rows(self, batch: int) -> slice:
        """This rank's rows of a global batch of ``batch`` items."""
        b = batch // self.world
        return slice(self.rank * b, (self.rank + 1) * b)

    def shard(self, indices: list[int]) -> list[int]:
        """This rank's items of a global batch (contiguous, so the ranks' shards in order are the batch)."""
        return indices if not self.active else indices[self.rows(len(indices))]

    def wrap(self, model: torch.nn.Module, device: torch.device) -> torch.nn.Module:
        """The module the training step runs: DDP (gradient averaging) over several ranks, else the model."""
        if not self.active:
            return model
        from torch.nn.parallel import DistributedDataParallel

        ids = [device.index if device.index is not None else torch.cuda.current_device()] if device.type == "cuda" else None
        return DistributedDataParallel(model, device_ids=ids)

    def mean_parts(self, parts: dict[str, float], device: torch.device) -> dict[str, float]:
        """Loss components averaged over the ranks (the global batch's, as one process logs them)."""
        if not self.active:
            return parts
        import torch.distributed as dist

        keys = sorted(parts)
        t = torch.tensor([parts[k] for k in keys], dtype=torch.float64, device=device)
        dist.all_reduce(t)
        return {k: float(v) / self.world for k, v in zip(keys, t.tolist())}

    def any_true(self, flag: bool, device: torch.device) -> bool:
        """True on every rank when ``flag`` is true on any (a stop all ranks must take together)."""
        if not self.active:
            return flag
        import torch.distributed as dist

        t = torch.tensor([1.0 if flag else 0.0], device=device)
        dist.all_reduce(t, op=dist.ReduceOp.MAX)
        return bool(t.item() > 0)

    def stepped(self) -> None:
        """After each optimizer step (test-only kill -9 point ``train.step.rank<R>``, :mod:`polinfra.faults`)."""
        if self.active:
            fault_point(f"train.step.rank{self.rank}")

    def barrier(self) -> None:
        if self.active:
            import torch.distributed as dist

            dist.barrier()


SINGLE = Ranks()
"""The single-process run."""


def world_from_env() -> Ranks:
    """The ranks torchrun describes in the environment (``RANK``, ``WORLD_SIZE``, ``LOCAL_RANK``); :data:`SINGLE` without."""
    try:
        world = int(os.environ.get("WORLD_SIZE", "1"))
        rank = int(os.environ.get("RANK", "0"))
        local = int(os.environ.get("LOCAL_RANK", str(rank)))
    except ValueError:
        raise ConfigError("WORLD_SIZE / RANK / LOCAL_RANK must be integers (set by torchrun)") from None
    if world <= 1:
        return SINGLE
    if not 0 <= rank < world:
        raise ConfigError(f"RANK {rank} outside 0 .. WORLD_SIZE - 1 = {world - 1}")
    return Ranks(rank=rank, world=world, local_rank=local)


def check_world(world: int, batch_size: int, where: str = "--nproc") -> None:
    """A world size must be >= 1 and divide the global batch (each rank takes an equal share)."""
    if world < 1:
        raise ConfigError(f"{where} {world}: the number of training processes must be >= 1")
    if batch_size % world:
        raise ConfigError(f"{where} {world} does not divide the global batch_size {batch_size}: each rank takes batch_size / N windows; choose N among the divisors of {batch_size}")


def init_ranks(ranks: Ranks, device: str, timeout_s: float = 1800.0) -> None:
    """Join the process group of ``ranks`` (nccl on CUDA, gloo on CPU); a no-op for one process."""
    if not ranks.active:
        return
    import torch.distributed as dist

    if dist.is_initialized():
        return
    cuda = device == "cuda" or (device == "auto" and torch.cuda.is_available())
    if cuda:
        torch.cuda.set_device(ranks.local_rank)
    backend = "nccl" if cuda else "gloo"
    dist.init_process_group(backend=backend, timeout=timedelta(seconds=timeout_s))
    log.info("rank %d of %d joined (%s)", ranks.rank, ranks.world, backend)


def shutdown(ranks: Ranks) -> None:
    """Leave the process group (after every rank finished)."""
    if ranks.active:
        import torch.distributed as dist

        if dist.is_initialized():
            dist.destroy_process_group()
