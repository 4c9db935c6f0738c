"""PGD adversarial training (Madry et al. 2018) as a drop-in Lightning callback.

Before each training step the batch images are replaced, in place, by L-inf PGD adversarial examples
of the module's own loss: `steps` signed-gradient steps of `step_size` from a random start inside the
eps-ball, projected back onto the ball and onto the valid pixel range. eps and step_size are in [0, 1]
pixel units; `mean`/`std` say how the batch images were normalised ((pixel - mean) / std per channel),
so the ball is eps / std wide in the tensor the model sees. Without them they are the model's own: the
normalisation preset of its build config (data/normalization.py; `imagenet` for a module that records none).
"""

from __future__ import annotations

from contextlib import nullcontext
from typing import Any, Callable, Sequence

import pytorch_lightning as pl
import torch

from lanevil_train.callbacks.adapter import BatchAdapter
from lanevil_train.data.normalization import normalization, spec_normalization
from lanevil_train.rules import Rule, check_settings, integer, null_or, number, number_list


def default_loss(module: pl.LightningModule, batch: Any) -> torch.Tensor:
    """The module's training loss on `batch`: `module.batch_loss(batch)` if it has one, else its training_step; a
    per-sample loss vector (a VLM's batch_loss) is averaged."""
    if hasattr(module, "batch_loss"):
        out = module.batch_loss(batch)
    else:
        out = module.training_step(batch, 0)
    loss = out["loss"] if isinstance(out, dict) else out
    if isinstance(loss, torch.Tensor) and loss.ndim == 1:
        loss = loss.mean()
    if not isinstance(loss, torch.Tensor) or loss.ndim != 0:
        raise TypeError("PGDAdversarialTraining: the loss function must return a scalar tensor, a per-sample loss "
                        "vector (or a dict with either as 'loss')")
    return loss


class PGDAdversarialTraining(pl.Callback):
    """Train on PGD adversarial examples of a `fraction` of each batch (all of it by default)."""

    SETTINGS = {
        "eps": Rule("a number >= 0 (the L-inf radius, in [0, 1] pixel units: 4/255 = 0.0157)", number(0).test),
        "step_size": Rule("a number > 0 (in [0, 1] pixel units)", number(0, low_open=True).test),
        "steps": integer(1),
        "fraction": Rule("a number in [0, 1] (the share of each batch replaced)", number(0, 1).test),
        "mean": null_or(number_list()),
        "std": null_or(number_list(0, low_open=True)),
    }

    def __init__(self, eps: float = 4 / 255, step_size: float = 1 / 255, steps: int = 3, random_start: bool = True,
                 fraction: float = 1.0, mean: Sequence[float] | None = None, std: Sequence[float] | None = None,
                 adapter: BatchAdapter | None = None,
                 loss_fn: Callable[[pl.LightningModule, Any], torch.Tensor] | None = None, seed: int = 0):
        check_settings(self.SETTINGS, locals(), "PGDAdversarialTraining")
        if (mean is None) != (std is None):
            raise ValueError("PGDAdversarialTraining: give mean and std together (how the images were normalised, "
                             "in [0, 1] pixel units), or neither (the model's own normalisation preset)")
        if mean is not None and len(mean) != len(std):
            raise ValueError(f"PGDAdversarialTraining: mean and std must give one value per channel each, got "
                             f"{len(mean)} and {len(std)} values")
        self.eps, self.step_size, self.steps = eps, step_size, steps
        self.random_start = random_start
        self.fraction = fraction
        self.mean = None if mean is None else tuple(float(m) for m in mean)
        self.std = None if std is None else tuple(float(s) for s in std)
        self.adapter = adapter or BatchAdapter()
        self.loss_fn = loss_fn or default_loss
        self.generator = torch.Generator().manual_seed(seed)

    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch, batch_idx: int) -> None:
        images = self.adapter.images(batch)
        count = int(round(self.fraction * images.shape[0]))
        if count == 0 or self.eps == 0:
            return
        adversarial = self.attack(pl_module, batch, images, trainer)
        with torch.no_grad():
            images[:count] = adversarial[:count]

    def mean_std(self, pl_module: pl.LightningModule) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(mean, std) per channel of the image tensor, in [0, 1] pixel units: the constructor's, else those of the
        normalisation preset `pl_module`'s build config records (`imagenet` for a module that records none)."""
        if self.mean is not None:
            return self.mean, self.std
        return normalization(spec_normalization(getattr(pl_module, "build_config", None))).pixel_mean_std()

    def bounds(self, images: torch.Tensor, pl_module: pl.LightningModule
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(eps, step, low, high) per channel, in the units of the image tensor, shaped (1, C, 1, 1): low and high
        are the tensor's values of pixels 0 and 255."""
        mean, std = (torch.tensor(v, dtype=torch.float32, device=images.device).view(1, -1, 1, 1)
                     for v in self.mean_std(pl_module))
        if images.shape[1] != std.shape[1]:
            raise ValueError(f"PGDAdversarialTraining: images have {images.shape[1]} channels but mean/std "
                             f"give {std.shape[1]}")
        return self.eps / std, self.step_size / std, (0 - mean) / std, (1 - mean) / std

    def attack(self, pl_module: pl.LightningModule, batch, images: torch.Tensor, trainer: pl.Trainer | None = None):
        """The PGD adversarial images for `batch` (the batch itself is left as it was)."""
        clean = images.detach().clone().float()
        eps, step, low, high = self.bounds(clean, pl_module)
        delta = torch.zeros_like(clean)
        if self.random_start:
            noise = torch.rand(clean.shape, generator=self.generator).to(clean.device)
            delta = (2 * noise - 1) * eps
        delta = torch.max(torch.min(clean + delta, high), low) - clean
        for _ in range(self.steps):
            delta.requires_grad_(True)
            with torch.no_grad():
                images.copy_((clean + delta).to(images.dtype))
            images.requires_grad_(True)
            # the forward runs under the trainer's precision (autocast under mixed precision)
            with trainer.precision_plugin.forward_context() if trainer is not None else nullcontext():
                loss = self.loss_fn(pl_module, batch)
            (grad,) = torch.autograd.grad(loss, images)
            images.requires_grad_(False)
            with torch.no_grad():
                delta = delta.detach() + step * grad.float().sign()
                delta = torch.max(torch.min(delta, eps), -eps)
                delta = torch.max(torch.min(clean + delta, high), low) - clean
        with torch.no_grad():
            images.copy_(clean.to(images.dtype))
        return (clean + delta).detach()
