"""torchrun: what the ranks of one training average, so that every rank keeps identical weights,
learning rate and observation statistics (no-ops on one process)."""

from __future__ import annotations

import torch
import torch.distributed as dist

from fallkit.rl.models import RunningNorm


def distributed() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


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
