"""PGD adversarial training: the perturbation stays in the eps-ball and the pixel range, and raises the loss."""

import numpy as np
import pytest
import pytorch_lightning as pl
import torch

from lanevil_train.callbacks import BatchAdapter, PGDAdversarialTraining
from lanevil_train.data.normalization import NORMALIZATIONS, Normalization, normalize_image
from tests.callbacks.test_aam import TinySegmenter

# a module recording no normalisation preset (TinySegmenter has no build config) is taken to be on imagenet's
MEAN, STD = (torch.tensor(v).view(1, 3, 1, 1) for v in NORMALIZATIONS["imagenet"].pixel_mean_std())


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
    ({"eps": -1.0}, r"\.eps: expected a number >= 0 \(the L-inf radius"),
    ({"eps": float("nan")}, r"\.eps: expected a number >= 0"),
    ({"step_size": 0.0}, r"\.step_size: expected a number > 0 "),
    ({"steps": 0}, r"\.steps: expected an integer >= 1, got 0"),
    ({"steps": 1.5}, r"\.steps: expected an integer >= 1, got 1.5"),
    ({"fraction": 1.5}, r"\.fraction: expected a number in \[0, 1\]"),
    ({"mean": (0.5,), "std": (0.2, 0.2, 0.2)}, ": mean and std must give one value per channel each, got 1 and 3"),
    ({"mean": (0.5, 0.5, 0.5)}, ": give mean and std together"),
    ({"mean": [0.0, 0.0, 0.0], "std": [0.2, 0.0, 0.2]},
     r"\.std: expected null or a non-empty list of numbers > 0, got \[0.2, 0.0, 0.2\]"),
])
def test_each_bad_argument_is_named_with_its_range(arguments, expected):
    with pytest.raises(ValueError, match=f"PGDAdversarialTraining{expected}"):
        PGDAdversarialTraining(**arguments)


class PresetSegmenter(TinySegmenter):
    """A module whose build config records its normalisation preset, as a LaneDetector's does."""

    def __init__(self, normalize: str):
        super().__init__(seed=1)
        self.build_config = {"normalize": normalize}


@pytest.mark.parametrize("name", ["laneatt", "ganet", "half"])
def test_the_adversarial_input_stays_within_the_model_presets_pixel_range_and_reaches_it(name, monkeypatch):
    # laneatt: BGR / 255 with no mean or std (the tensor is [0, 1] pixels); ganet: 0..255 with its own mean and
    # std; half: RGB / 255 with mean and std 0.5. ImageNet's range would let pixels go past 0 and 255 under each.
    monkeypatch.setitem(NORMALIZATIONS, "half", Normalization("RGB", 255.0, (0.5,) * 3, (0.5,) * 3))
    black, white = (torch.from_numpy(normalize_image(np.full((1, 1, 3), v, np.uint8), name)).view(1, 3, 1, 1)
                    for v in (0, 255))
    pixels = np.random.default_rng(0).integers(0, 256, (4, 16, 24, 3), dtype=np.uint8)
    images = torch.from_numpy(np.stack([normalize_image(p, name) for p in pixels]))
    masks = torch.zeros(4, 16, 24)
    masks[:, :, 10:12] = 1
    b, clean = (images, masks), images.clone()
    eps = 16 / 255
    pgd = PGDAdversarialTraining(eps=eps, step_size=4 / 255, steps=3,
                                 adapter=BatchAdapter(images=0, lane_mask=1, lanes=None), loss_fn=loss_of)
    pgd.on_train_batch_start(None, PresetSegmenter(name), b, 0)
    adversarial = b[0]
    assert not torch.equal(adversarial, clean)
    tolerance = 1e-5 * (white - black)
    assert torch.all(adversarial >= black - tolerance) and torch.all(adversarial <= white + tolerance)
    # the pixels 0 and 255 themselves are reached in every channel
    assert torch.all((adversarial - black).abs().amin(dim=(0, 2, 3), keepdim=True) <= tolerance)
    assert torch.all((adversarial - white).abs().amin(dim=(0, 2, 3), keepdim=True) <= tolerance)
    assert torch.all((adversarial - clean).abs() <= eps * (white - black) + tolerance)  # eps of the 0..255 range


def test_mean_and_std_given_override_the_models_preset():
    module = PresetSegmenter("laneatt")
    images = torch.zeros(1, 3, 2, 2)
    _, _, low, high = PGDAdversarialTraining().bounds(images, module)
    assert low.flatten().tolist() == [0.0] * 3 and high.flatten().tolist() == [1.0] * 3
    _, _, low, high = PGDAdversarialTraining(mean=(0.5,) * 3, std=(0.5,) * 3).bounds(images, module)
    assert low.flatten().tolist() == [-1.0] * 3 and high.flatten().tolist() == [1.0] * 3


def test_pgd_in_a_lightning_fit_under_bf16():
    from torch.utils.data import DataLoader, TensorDataset

    images, masks = batch(8)
    module = TinySegmenter(seed=1)
    pgd = PGDAdversarialTraining(eps=4 / 255, steps=2, adapter=BatchAdapter(images=0, lane_mask=1, lanes=None))
    trainer = pl.Trainer(max_steps=2, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, callbacks=[pgd], precision="bf16-mixed")
    trainer.fit(module, DataLoader(TensorDataset(images, masks), batch_size=4))
    assert module.forward_calls == 2 * (1 + 2)  # each step: two attack forwards and the training forward
