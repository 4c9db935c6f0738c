"""Learning-rate schedules of the detector families (``model.scheduler``), and the batch-size rule for the rate.

A schedule config is a ``_partial_`` target called as ``schedule(optimizer, total_steps)``; it steps once per
optimizer step. ``total_steps`` is Lightning's estimate of the run's optimizer steps (max_steps, or the epochs'
steps with the devices and gradient accumulation counted).

The learning rate: each family's ``model.optimizer.lr`` is the rate at its ``model.reference_batch_size`` (the
global batch the family's paper used); a run's rate is scaled to its own global batch (data.batch_size x devices x
nodes x trainer.accumulate_grad_batches) by ``model.lr_scaling``: ``linear`` (Goyal et al. 2017: the rate in
proportion to the batch), ``sqrt`` (in proportion to its square root, common for Adam) or ``none``. So one config
gives the same per-sample schedule on 1 or N devices.
"""

from __future__ import annotations

import math

import torch

LR_SCALINGS = ("linear", "sqrt", "none")


def scaled_lr(lr: float, global_batch: int, reference_batch: int | None, rule: str) -> float:
    """`lr` (the rate at `reference_batch`) for a run whose global batch is `global_batch`."""
    if rule not in LR_SCALINGS:
        raise ValueError(f"model.lr_scaling={rule!r}: expected one of {', '.join(LR_SCALINGS)}")
    if rule == "none" or not reference_batch:
        return lr
    ratio = global_batch / reference_batch
    return lr * (ratio if rule == "linear" else math.sqrt(ratio))


def _warmup(step: int, warmup_steps: int) -> float:
    return min(1.0, (step + 1) / warmup_steps) if warmup_steps > 0 else 1.0


def cosine(optimizer: torch.optim.Optimizer, total_steps: int, warmup_steps: int = 0,
           min_factor: float = 0.0) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up, then cosine annealing from the rate to `min_factor` times it at `total_steps`."""
    total = max(int(total_steps), 1)

    def factor(step: int) -> float:
        progress = min(max(step - warmup_steps, 0) / max(total - warmup_steps, 1), 1.0)
        return _warmup(step, warmup_steps) * (min_factor + (1 - min_factor) * 0.5 * (1 + math.cos(math.pi * progress)))

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def poly(optimizer: torch.optim.Optimizer, total_steps: int, power: float = 0.9,
         warmup_steps: int = 0) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up, then (1 - step / total_steps) ** power: SCNN's and UFLD's segmentation-style decay."""
    total = max(int(total_steps), 1)
    return torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda step: _warmup(step, warmup_steps) * max(1.0 - step / total, 0.0) ** power)


def constant(optimizer: torch.optim.Optimizer, total_steps: int) -> torch.optim.lr_scheduler.LambdaLR:
    """The rate as given, every step."""
    return torch.optim.lr_scheduler.LambdaLR(optimizer, lambda step: 1.0)
