"""AttentionAreaMixing as a drop-in callback: a foreign LightningModule, mixing, hardness, DDP, AMP."""

from __future__ import annotations

import json
import os
import socket

import numpy as np
import pytest
import pytorch_lightning as pl
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn
from torch.utils.data import DataLoader, Dataset

from lanevil_train.callbacks import AttentionAreaMixing, BatchAdapter
from lanevil_train.callbacks.regions import HAA, LAA

H, W = 32, 48


class StripeImages(Dataset):
    """Images with a bright vertical 'lane' stripe (the mask) and a bright distractor blob elsewhere."""

    def __init__(self, n: int = 16):
        rng = np.random.default_rng(0)
        self.items = []
        for i in range(n):
            image = torch.from_numpy(rng.normal(0, 0.1, (3, H, W)).astype(np.float32))
            mask = torch.zeros(H, W)
            x = 8 + (i % 4) * 8
            mask[:, x:x + 2] = 1
            image[:, :, x:x + 2] += 1.0
            y0, x0 = rng.integers(0, H - 8), rng.integers(0, W - 8)
            image[:, y0:y0 + 8, x0:x0 + 8] += 1.5
            self.items.append((image, mask))

    def __len__(self):
        return len(self.items)

    def __getitem__(self, i):
        return self.items[i]


class TinySegmenter(pl.LightningModule):
    """A module that knows nothing of lanevil_train: (images, masks) batches, per-pixel BCE."""

    def __init__(self, seed: int = 0):
        super().__init__()
        torch.manual_seed(seed)
        self.features = nn.Sequential(nn.Conv2d(3, 8, 3, padding=1), nn.ReLU(),
                                      nn.Conv2d(8, 8, 3, stride=2, padding=1), nn.ReLU())
        self.classifier = nn.Conv2d(8, 1, 1)
        self.forward_calls = 0
        self.seen: list[torch.Tensor] = []

    def forward(self, images):
        self.forward_calls += 1
        logits = self.classifier(self.features(images))
        return nn.functional.interpolate(logits, size=images.shape[-2:], mode="bilinear", align_corners=False)[:, 0]

    def training_step(self, batch, batch_idx):
        images, masks = batch
        self.seen.append(images.detach().clone())
        per_pixel = nn.functional.binary_cross_entropy_with_logits(self(images), masks, reduction="none")
        per_sample = per_pixel.mean(dim=(1, 2))
        return {"loss": per_sample.mean(), "per_sample_loss": per_sample.detach()}

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)


def make_callback(**kwargs) -> AttentionAreaMixing:
    args = dict(layer="features", adapter=BatchAdapter(images=0, lanes=None, lane_mask=1), sigma=1.0,
                min_area=0.01, lane_width=0.05, mix_prob=0.5, hardness="loss", seed=0)
    args.update(kwargs)
    return AttentionAreaMixing(**args)


def fit(module, callback, steps=6, **trainer_kwargs):
    trainer = pl.Trainer(max_steps=steps, accelerator="cpu", logger=False, enable_checkpointing=False,
                         enable_progress_bar=False, enable_model_summary=False, callbacks=[callback], **trainer_kwargs)
    loader = DataLoader(StripeImages(), batch_size=4, shuffle=False)
    trainer.fit(module, loader)
    return trainer


def test_drop_in_on_a_foreign_module_banks_and_mixes_without_extra_forwards():
    module, callback = TinySegmenter(), make_callback()
    fit(module, callback, steps=6)
    assert module.forward_calls == 6            # the attention map costs no forward pass
    assert callback.stats["hard"] > 0 and len(callback.bank) > 0
    assert callback.stats["mixed"] > 0
    # the training steps saw mixed images: after the first step, some image differs from the dataset's
    data = StripeImages()
    originals = torch.stack([data[i][0] for i in range(16)])
    changed = []
    for step, seen in enumerate(module.seen):
        start = (step * 4) % 16
        changed.append(int((~torch.isclose(seen, originals[start:start + 4])).any(dim=(1, 2, 3)).sum()))
    assert changed[0] == 0 and sum(changed[1:]) == callback.stats["mixed"]
    assert callback._handle is None             # the hook is removed after fit


def test_mixing_blends_one_banked_region_off_the_lanes_for_haa():
    callback = make_callback(mode="aam", beta=0.5, mix_prob=1.0)
    patch = torch.full((3, 6, 10), 4.0, dtype=torch.float16)
    callback.bank.add(HAA, patch)
    images = torch.zeros(2, 3, H, W)
    masks = np.zeros((2, H, W), dtype=bool)
    masks[:, :, 20:22] = True
    mixed = callback.mix(images, masks)
    assert mixed == {0, 1}
    for image in images:
        changed = image[0] != 0
        ys, xs = np.nonzero(changed.numpy())
        assert changed.sum() == 60 and (ys.max() - ys.min() + 1, xs.max() - xs.min() + 1) == (6, 10)
        assert torch.all(image[:, changed] == 2.0)                      # (1 - 0.5) * 0 + 0.5 * 4
        assert not (masks[0] & changed.numpy()).any()                   # HAA regions stay off the lanes


def test_laa_regions_go_onto_the_lanes_and_aam_never_banks_them():
    callback = make_callback(mode="aam++", beta=0.5, mix_prob=1.0)
    callback.bank.add(LAA, torch.ones(3, 4, 4, dtype=torch.float16))
    images = torch.zeros(1, 3, H, W)
    masks = np.zeros((1, H, W), dtype=bool)
    masks[:, :, 30:32] = True
    callback.mix(images, masks)
    xs = np.nonzero((images[0, 0] != 0).numpy())[1]
    assert xs.min() <= 30 and xs.max() >= 31
    assert make_callback(mode="aam").bank.regions.keys() == {HAA}


def test_mix_prob_zero_and_start_step_leave_the_batch_alone():
    module, callback = TinySegmenter(), make_callback(start_step=100)
    fit(module, callback, steps=4)
    assert len(callback.bank) > 0 and callback.stats["mixed"] == 0
    callback = make_callback(mix_prob=0.0)
    callback.bank.add(HAA, torch.ones(3, 4, 4, dtype=torch.float16))
    images = torch.zeros(3, 3, H, W)
    assert callback.mix(images, np.zeros((3, H, W), dtype=bool)) == set() and not images.any()


def test_hardness_uses_accuracy_below_and_loss_above_the_running_mean():
    callback = make_callback(hardness="auto")
    scores, harder = callback.per_sample_scores({"loss": 0, "per_sample_accuracy": torch.tensor([0.2, 0.9]),
                                                 "per_sample_loss": torch.tensor([1.0, 0.1])})
    assert harder is False and scores.tolist() == pytest.approx([0.2, 0.9])
    scores, harder = make_callback(hardness="loss").per_sample_scores(
        {"per_sample_accuracy": torch.tensor([0.2]), "per_sample_loss": torch.tensor([1.0])})
    assert harder is True and scores.tolist() == [1.0]
    with pytest.raises(KeyError, match="per_sample_accuracy"):
        make_callback(hardness="accuracy").per_sample_scores({"loss": 0, "per_sample_loss": torch.tensor([1.0])})
    with pytest.raises(TypeError, match="per_sample"):
        callback.per_sample_scores(torch.tensor(1.0))


def test_module_that_scores_its_batches_is_switched_on():
    module = TinySegmenter()
    module.score_train_batches = False
    callback = make_callback(hardness="auto")
    callback.on_fit_start(None, module)
    assert module.score_train_batches is True
    callback.on_fit_end(None, module)


def test_bad_layer_and_bad_parameters_are_named():
    with pytest.raises(ValueError, match="layer='nope'"):
        make_callback(layer="nope").on_fit_start(None, TinySegmenter())
    with pytest.raises(ValueError, match="mode"):
        make_callback(mode="aam+++")
    with pytest.raises(ValueError, match="t_laa"):
        make_callback(t_laa=1.5)
    with pytest.raises(KeyError, match="images"):
        BatchAdapter(images="pixels").images({"images": torch.zeros(1, 3, 4, 4)})


@pytest.mark.parametrize("argument, value, expected", [
    ("layer", "", "layer: expected the dotted name of a module"),
    ("mode", "aam+++", r"mode: expected one of aam, aam\+\+, got 'aam\+\+\+'"),
    ("output_index", 0.5, "output_index: expected an integer"),
    ("t_haa", "0.6", r"t_haa: expected a number in \[0, 1\], got '0.6'"),
    ("beta", -0.1, r"beta: expected a number in \[0, 1\], got -0.1"),
    ("sigma", -1.0, "sigma: expected a number >= 0"),
    ("sigma", float("nan"), "sigma: expected a number >= 0"),
    ("lane_width", 0.0, r"lane_width: expected a fraction of the image width in \(0, 1\], got 0.0"),
    ("bank_size", 0, "bank_size: expected an integer >= 1, got 0"),
    ("start_step", -1, "start_step: expected an integer >= 0, got -1"),
])
def test_each_bad_argument_is_named_with_its_range(argument, value, expected):
    with pytest.raises(ValueError, match=f"AttentionAreaMixing.{expected}"):
        make_callback(**{argument: value})


def test_mixed_precision_bf16_still_banks_regions():
    module, callback = TinySegmenter(), make_callback()
    fit(module, callback, steps=4, precision="bf16-mixed")
    assert len(callback.bank) > 0
    assert all(p.dtype == torch.float16 for q in callback.bank.regions.values() for p in q)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def _gather_worker(rank: int, world: int, port: int, out_dir: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=world)
    callback = make_callback()
    found = [(HAA, torch.full((3, 2, 2), float(rank + 1), dtype=torch.float16))] * (rank + 1)
    for kind, patch in callback._gather(found):
        callback.bank.add(kind, patch)
    values = [float(p[0, 0, 0]) for p in callback.bank.regions[HAA]]
    with open(os.path.join(out_dir, f"rank{rank}.json"), "w") as handle:
        json.dump(values, handle)
    dist.destroy_process_group()


def test_the_region_bank_is_shared_across_ddp_ranks(tmp_path):
    mp.spawn(_gather_worker, args=(2, _free_port(), str(tmp_path)), nprocs=2, join=True)
    banks = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in range(2)]
    assert banks[0] == banks[1] == [1.0, 2.0, 2.0]  # rank 0 found one region, rank 1 two: every rank holds all


class PooledSegmenter(TinySegmenter):
    """TinySegmenter with a global-pool + fc bias branch, a frozen first conv option and a module it never calls."""

    def __init__(self, freeze_first: bool = False):
        super().__init__()
        self.pool = nn.AdaptiveAvgPool2d(1)
        self.fc = nn.Linear(8, 1)
        self.unused = nn.Conv2d(3, 8, 3)
        if freeze_first:
            self.features[0].requires_grad_(False)

    def forward(self, images):
        self.forward_calls += 1
        features = self.features(images)
        logits = self.classifier(features) + self.fc(self.pool(features).flatten(1))[:, :, None, None]
        return nn.functional.interpolate(logits, size=images.shape[-2:], mode="bilinear", align_corners=False)[:, 0]


NEEDS = r"AAM needs a 4-D \(B, C, H, W\) feature map"


@pytest.mark.parametrize("layer, freeze, expected", [
    ("fc", False, r"layer='fc' gave a \(4, 1\) tensor \(requires_grad=True\) in the training step: "
                  rf"not a 4-D feature map. {NEEDS} with H, W > 1 that receives gradients; set layer to such a module"),
    ("pool", False, r"layer='pool' gave a \(4, 8, 1, 1\) tensor \(requires_grad=True\) in the training step: "
                    rf"no spatial extent to cut regions from \(H, W must both be > 1\). {NEEDS}"),
    ("features.0", True, r"layer='features.0' gave a \(4, 8, 32, 48\) tensor \(requires_grad=False\) in the "
                         rf"training step: no gradient reaches it \(is the layer frozen.*\). {NEEDS}"),
    ("unused", False, rf"layer='unused' gave no output in the training step .*; {NEEDS}"),
])
def test_a_layer_aam_cannot_use_fails_at_the_first_step_naming_what_it_gave(layer, freeze, expected):
    module, callback = PooledSegmenter(freeze_first=freeze), make_callback(layer=layer)
    with pytest.raises(ValueError, match=f"AttentionAreaMixing: {expected}"):
        fit(module, callback, steps=3)
    assert module.forward_calls == 1 and callback._handle is None  # the first step, and the hook is gone
    fit(PooledSegmenter(), make_callback(layer="features"), steps=1)  # the same model with a usable layer trains


def test_check_model_finds_the_layer_or_names_it():
    module = TinySegmenter()
    assert make_callback(layer="features.2").check_model(module) is module.features[2]
    with pytest.raises(ValueError, match=r"AttentionAreaMixing: layer='nope' is not a module of TinySegmenter; "
                                         r"some names: \['features', 'features.0'"):
        make_callback(layer="nope").check_model(module)


def test_lane_ground_truth_for_a_different_number_of_images_is_refused():
    callback = make_callback(adapter=BatchAdapter(images=0, lanes=1))
    batch = (torch.zeros(2, 3, H, W), [[np.array([[1.0, 1.0], [1.0, 9.0]])]])
    with pytest.raises(ValueError, match="the batch has 2 images but lane ground truth for 1"):
        callback.adapter_masks(batch)
