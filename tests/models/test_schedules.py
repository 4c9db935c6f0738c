"""The learning rate follows the global batch (so one config trains alike on 1 or N devices), the schedules'
closed forms, and the optimizer / schedule config forms (current `_partial_` targets and older checkpoints')."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from lanevil_train.models.detector import LaneDetector
from lanevil_train.models.factory import _optimizer_and_schedule
from lanevil_train.models.laneatt import LaneATTHead
from lanevil_train.models.schedules import cosine, poly, scaled_lr


def test_scaled_lr_rules():
    assert scaled_lr(1e-3, 32, 8, "linear") == pytest.approx(4e-3)
    assert scaled_lr(1e-3, 32, 8, "sqrt") == pytest.approx(2e-3)
    assert scaled_lr(1e-3, 32, 8, "none") == 1e-3
    assert scaled_lr(1e-3, 32, None, "linear") == 1e-3  # no reference batch: the rate as given
    with pytest.raises(ValueError, match="model.lr_scaling='cubic'"):
        scaled_lr(1e-3, 32, 8, "cubic")


def _detector(**kwargs) -> LaneDetector:
    head = LaneATTHead([8], [32], (64, 96), anchor_feat_channels=2, lateral_n=2, bottom_n=2)
    return LaneDetector(torch.nn.Identity(), head, **kwargs)


def _configured(model: LaneDetector, devices: int, batch: int, accumulate: int = 1, steps: int = 100):
    model._trainer = SimpleNamespace(world_size=devices, accumulate_grad_batches=accumulate,
                                     datamodule=SimpleNamespace(batch_size=batch), estimated_stepping_batches=steps)
    out = model.configure_optimizers()
    return out["optimizer"], out["lr_scheduler"]["scheduler"]


def _rates(optimizer, schedule, steps: int) -> list[float]:
    rates = []
    for _ in range(steps):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        schedule.step()
    return rates


def test_the_same_global_batch_gets_the_same_schedule_on_1_or_n_devices():
    make = lambda: _detector(optimizer=lambda p: torch.optim.Adam(p, lr=3e-4), reference_batch_size=8,  # noqa: E731
                             lr_scaling="linear")
    one = _rates(*_configured(make(), devices=1, batch=16), 100)
    four = _rates(*_configured(make(), devices=4, batch=4), 100)
    accumulated = _rates(*_configured(make(), devices=2, batch=4, accumulate=2), 100)
    assert one[0] == pytest.approx(6e-4)  # 3e-4 at batch 8, doubled for a global batch of 16
    assert one == pytest.approx(four) and one == pytest.approx(accumulated)
    bigger = _rates(*_configured(make(), devices=4, batch=16), 100)  # a global batch of 64: 8x the reference
    assert bigger[0] == pytest.approx(2.4e-3) and bigger[50] == pytest.approx(4 * one[50])
    unscaled = _configured(_detector(optimizer=lambda p: torch.optim.Adam(p, lr=3e-4), reference_batch_size=8,
                                     lr_scaling="none"), devices=4, batch=16)[0]
    assert unscaled.param_groups[0]["lr"] == pytest.approx(3e-4)


def test_cosine_and_poly_closed_forms():
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    rates = _rates(opt, cosine(opt, total_steps=100, warmup_steps=10, min_factor=0.1), 101)
    assert rates[0] == pytest.approx(0.1) and rates[4] == pytest.approx(0.5)  # linear warm-up over 10 steps
    assert rates[10] == pytest.approx(1.0)
    assert rates[55] == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * 45 / 90)))
    assert rates[100] == pytest.approx(0.1)
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=0.01)
    rates = _rates(opt, poly(opt, total_steps=50, power=0.9), 51)
    assert rates[0] == pytest.approx(0.01) and rates[25] == pytest.approx(0.01 * 0.5 ** 0.9) and rates[50] == 0.0


def test_optimizer_and_schedule_configs_new_and_old():
    params = [torch.nn.Parameter(torch.zeros(2))]
    make_opt, make_schedule = _optimizer_and_schedule({
        "optimizer": {"_target_": "torch.optim.SGD", "_partial_": True, "lr": 0.01, "momentum": 0.9},
        "scheduler": {"_target_": "lanevil_train.models.schedules.poly", "_partial_": True, "power": 0.9}})
    opt = make_opt(params)
    assert isinstance(opt, torch.optim.SGD) and opt.param_groups[0]["momentum"] == 0.9
    assert make_schedule(opt, 10).lr_lambdas[0](5) == pytest.approx(0.5 ** 0.9)
    # a checkpoint written before these were targets: {lr, weight_decay} and "cosine" / "none"
    make_opt, make_schedule = _optimizer_and_schedule({"optimizer": {"lr": 1e-3, "weight_decay": 0.0},
                                                       "scheduler": "cosine"})
    opt = make_opt(params)
    assert isinstance(opt, torch.optim.Adam) and opt.param_groups[0]["lr"] == 1e-3
    assert make_schedule(opt, 10).lr_lambdas[0](10) == pytest.approx(0.0)
    assert _optimizer_and_schedule({"optimizer": {"lr": 1e-3}, "scheduler": "none"})[1] is None


def test_lr_multipliers_give_parts_of_the_network_their_own_rate():
    backbone = torch.nn.Conv2d(3, 8, 1)
    head = LaneATTHead([8], [32], (64, 96), anchor_feat_channels=2, lateral_n=2, bottom_n=2)
    model = LaneDetector(backbone, head, optimizer=lambda p: torch.optim.AdamW(p, lr=1e-4), scheduler=None,
                         lr_multipliers={"backbone.*": 0.1, "head.cls_layer.weight": 0.0})
    optimizer = model.configure_optimizers()
    rate = {id(p): group["lr"] for group in optimizer.param_groups for p in group["params"]}
    assert rate[id(backbone.weight)] == pytest.approx(1e-5) and rate[id(backbone.bias)] == pytest.approx(1e-5)
    assert rate[id(head.cls_layer.weight)] == 0.0 and rate[id(head.cls_layer.bias)] == pytest.approx(1e-4)
    assert len(rate) == sum(1 for p in model.parameters() if p.requires_grad)  # every parameter, once
    with pytest.raises(ValueError, match=r"the pattern 'bakbone\.\*' names no parameter; .*backbone\.\*"):
        LaneDetector(backbone, head, lr_multipliers={"bakbone.*": 0.1})
    with pytest.raises(ValueError, match=r"lr_multipliers.backbone.\*: expected a rate factor >= 0, got -1"):
        LaneDetector(backbone, head, lr_multipliers={"backbone.*": -1})


def test_gradient_clip_norm_applies_unless_the_trainer_sets_its_own(monkeypatch):
    model = _detector(gradient_clip_norm=0.1)
    calls = []
    monkeypatch.setattr(model, "clip_gradients", lambda optimizer, gradient_clip_val, gradient_clip_algorithm:
                        calls.append((gradient_clip_val, gradient_clip_algorithm)))
    model.configure_gradient_clipping(None, None, None)  # trainer.gradient_clip_val null: the family's clipping
    model.configure_gradient_clipping(None, 5.0, "value")  # the trainer's own setting wins
    assert calls == [(0.1, "norm"), (5.0, "value")]
    with pytest.raises(ValueError, match="gradient_clip_norm: expected null or a positive maximum norm, got 0"):
        _detector(gradient_clip_norm=0)
