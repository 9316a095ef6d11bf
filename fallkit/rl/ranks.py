"""torchrun: what the ranks of one training average, so that every rank keeps identical weights,
learning rate and observation statistics (no-ops on one process)."""

from __future__ import annotations

import logging
import os

import torch
import torch.distributed as dist

from fallkit.rl.models import RunningNorm

log = logging.getLogger(__name__)


def distributed() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def world_size() -> int:
    """The ranks that collect and learn together: 1 without torchrun."""
    return dist.get_world_size() if distributed() else 1


def average_gradients(params: list[torch.Tensor]) -> None:
    if not distributed():
        return
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat, op=dist.ReduceOp.SUM)
    flat /= dist.get_world_size()
    offset = 0
    for p, g in zip(params, grads):
        size = g.numel()
        if p.grad is None:
            p.grad = g
        p.grad.copy_(flat[offset : offset + size].view_as(g))
        offset += size


def merge_over_ranks(norm: RunningNorm) -> None:
    """Average running statistics over the ranks, so every rank normalises alike (no-op on one process)."""
    if not distributed():
        return
    stats = torch.cat([norm.mean, norm.var, norm.count.reshape(1)])
    dist.all_reduce(stats)
    stats /= dist.get_world_size()
    d = norm.mean.numel()
    norm.merge_(stats[:d], stats[d : 2 * d], stats[2 * d])


def mean_over_ranks(x: torch.Tensor) -> torch.Tensor:
    if not distributed():
        return x
    x = x.clone()
    dist.all_reduce(x, op=dist.ReduceOp.SUM)
    return x / dist.get_world_size()


def averaged_over_ranks(value: float, device: torch.device | str = "cpu") -> float:
    """A figure every rank reads on its own (a clock), averaged: the same on every rank (no-op on one process)."""
    if not distributed():
        return value
    return float(mean_over_ranks(torch.tensor(value, dtype=torch.float64, device=device)))


def any_over_ranks(flags: tuple[bool, ...], device: torch.device | str = "cpu") -> tuple[bool, ...]:
    """Each flag true on any rank, on every rank (no-op on one process).

    What ends the loop — a time budget, a signal, a diverged loss — is decided by each rank on its own
    (clocks and signals do not reach the ranks at the same iteration); a rank that stopped alone would
    leave the others waiting forever in the next collective. One all-reduce of a few bytes per iteration.
    """
    if not distributed():
        return flags
    agreed = torch.tensor(flags, dtype=torch.int32, device=device)
    dist.all_reduce(agreed, op=dist.ReduceOp.MAX)
    return tuple(bool(f) for f in agreed.tolist())


def check_ranks_in_sync(actor) -> None:
    """Every rank must end with the same weights (gradients were averaged); say so, or fail loudly."""
    flat = torch.cat([p.detach().reshape(-1).double() for p in actor.parameters()])
    mine = torch.stack([flat.sum(), flat.square().sum()])
    gathered = [torch.zeros_like(mine) for _ in range(dist.get_world_size())]
    dist.all_gather(gathered, mine)
    if any(not torch.equal(g, gathered[0]) for g in gathered):
        raise RuntimeError("distributed training: ranks ended with different weights")
    if dist.get_rank() == 0:
        log.info("distributed training: weights identical on %d ranks", dist.get_world_size())
    dist.barrier()


def init_distributed(device: str) -> int:
    """Join the torchrun group when launched by torchrun; return this process's rank."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or distributed():
        return dist.get_rank() if distributed() else 0
    backend = "nccl" if device.startswith("cuda") and torch.cuda.is_available() else "gloo"
    dist.init_process_group(backend=backend)
    return dist.get_rank()
