"""PGD adversarial training: the perturbation stays in the eps-ball and the pixel range, and raises the loss."""

import pytest
import pytorch_lightning as pl
import torch

from lanevil_train.callbacks import BatchAdapter, PGDAdversarialTraining
from lanevil_train.callbacks.pgd import IMAGENET_MEAN, IMAGENET_STD
from tests.callbacks.test_aam import TinySegmenter

MEAN = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
STD = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)


def batch(n=4, h=16, w=24):
    g = torch.Generator().manual_seed(3)
    pixels = torch.rand(n, 3, h, w, generator=g)
    pixels[0, :, 0, 0] = 0.0   # pixels at the ends of the range must stay inside it
    pixels[0, :, 0, 1] = 1.0
    masks = torch.zeros(n, h, w)
    masks[:, :, 10:12] = 1
    return ((pixels - MEAN) / STD, masks)


def loss_of(module, b):
    images, masks = b
    return torch.nn.functional.binary_cross_entropy_with_logits(module(images), masks)


def test_pgd_stays_within_eps_and_the_pixel_range_and_raises_the_loss():
    module = TinySegmenter(seed=1)
    b = batch()
    clean = b[0].clone()
    pgd = PGDAdversarialTraining(eps=8 / 255, step_size=2 / 255, steps=5,
                                 adapter=BatchAdapter(images=0, lane_mask=1, lanes=None), loss_fn=loss_of)
    adversarial = pgd.attack(module, b, b[0])
    assert torch.equal(b[0], clean)                                   # attack() leaves the batch as it was
    pixel_delta = (adversarial - clean) * STD                          # back in [0, 1] pixel units
    assert pixel_delta.abs().max() <= 8 / 255 + 1e-6
    assert pixel_delta.abs().max() > 7 / 255                           # it does use the budget
    pixels = adversarial * STD + MEAN
    assert pixels.min() >= -1e-6 and pixels.max() <= 1 + 1e-6
    with torch.no_grad():
        assert loss_of(module, (adversarial, b[1])) > loss_of(module, b) + 1e-3
    assert all(p.grad is None for p in module.parameters())           # the attack trains nothing


def test_callback_replaces_the_chosen_fraction_of_the_batch_in_place():
    module = TinySegmenter(seed=1)
    b = batch()
    clean = b[0].clone()
    pgd = PGDAdversarialTraining(eps=4 / 255, steps=2, fraction=0.5,
                                 adapter=BatchAdapter(images=0, lane_mask=1, lanes=None), loss_fn=loss_of)
    pgd.on_train_batch_start(None, module, b, 0)
    changed = (b[0] != clean).flatten(1).any(dim=1)
    assert changed.tolist() == [True, True, False, False]
    assert ((b[0] - clean) * STD).abs().max() <= 4 / 255 + 1e-6


def test_default_loss_uses_the_module_batch_loss_or_training_step():
    class WithBatchLoss(TinySegmenter):
        def batch_loss(self, b):
            return {"loss": loss_of(self, b)}

    module = WithBatchLoss(seed=1)
    b = batch()
    pgd = PGDAdversarialTraining(eps=4 / 255, steps=1, adapter=BatchAdapter(images=0, lane_mask=1, lanes=None))
    adversarial = pgd.attack(module, b, b[0])
    assert not torch.equal(adversarial, b[0])
    with pytest.raises(ValueError, match="eps"):
        PGDAdversarialTraining(eps=-1.0)


@pytest.mark.parametrize("arguments, expected", [
    ({"eps": -1.0}, "eps must be a number >= 0"),
    ({"step_size": 0.0}, "step_size must be a number > 0 "),
    ({"steps": 0}, "steps must be an integer >= 1, got 0"),
    ({"steps": 1.5}, "steps must be an integer >= 1, got 1.5"),
    ({"fraction": 1.5}, r"fraction must be a number in \[0, 1\]"),
    ({"mean": (0.5,)}, "mean and std must give one value per channel each, got 1 and 3"),
    ({"std": (0.2, 0.0, 0.2)}, "std must be numbers > 0"),
])
def test_each_bad_argument_is_named_with_its_range(arguments, expected):
    with pytest.raises(ValueError, match=f"PGDAdversarialTraining: {expected}"):
        PGDAdversarialTraining(**arguments)


def test_pgd_in_a_lightning_fit_under_bf16():
    from torch.utils.data import DataLoader, TensorDataset

    images, masks = batch(8)
    module = TinySegmenter(seed=1)
    pgd = PGDAdversarialTraining(eps=4 / 255, steps=2, adapter=BatchAdapter(images=0, lane_mask=1, lanes=None))
    trainer = pl.Trainer(max_steps=2, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, callbacks=[pgd], precision="bf16-mixed")
    trainer.fit(module, DataLoader(TensorDataset(images, masks), batch_size=4))
    assert module.forward_calls == 2 * (1 + 2)  # each step: two attack forwards and the training forward
