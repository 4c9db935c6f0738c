"""Inference through CUDA graphs (models/cuda_graphs.py): the plain forward wherever a graph could change the
result, and on a GPU the eager forward's outputs for every family (those tests run where CUDA is)."""

from __future__ import annotations

import pytest
import torch

from lanevil_train.models.cuda_graphs import GraphedInference, _has_hooks
from tests.models.test_families import FAMILIES, _model

pytestmark = pytest.mark.usefixtures("hydra_conf")  # tests/conftest.py
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


class TwoOutputs(torch.nn.Module):
    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 4, 3)

    def forward(self, x):
        y = self.conv(x)
        return {"mean": y.mean((2, 3)), "max": y.amax((2, 3))}


def test_cpu_inputs_run_the_plain_forward_and_record_nothing():
    net = TwoOutputs().eval()
    run = GraphedInference(net)
    x = torch.randn(2, 3, 8, 8)
    with torch.inference_mode():
        out = run(x)
        expected = net(x)
    assert run.graphs == {}
    assert all(torch.equal(out[k], expected[k]) for k in expected)


def test_a_forward_hook_or_training_mode_keeps_the_eager_forward():
    net = TwoOutputs().eval()
    run = GraphedInference(net)
    assert not run.usable(torch.randn(1, 3, 8, 8))  # CPU
    handle = net.conv.register_forward_hook(lambda *args: None)
    assert _has_hooks(net)
    handle.remove()
    assert not _has_hooks(net)


@cuda
@pytest.mark.parametrize("family", FAMILIES)
def test_graph_replay_gives_the_eager_outputs(family):
    model, _ = _model(family)
    model = model.cuda().eval()
    run = GraphedInference(model)
    with torch.inference_mode():
        for batch in (2, 1):
            first, second = (torch.randn(batch, 3, 96, 256, device="cuda") for _ in range(2))
            run(first)  # records
            for images in (second, first):  # each replay reads its own input, not the recorded one
                out, expected = run(images), model(images)
                for key in expected:
                    assert (out[key].float() - expected[key].float()).abs().max() <= 1e-4, (family, key)
        assert len(run.graphs) == 2


@cuda
def test_replays_see_weights_changed_in_place():
    net = TwoOutputs().cuda().eval()
    run = GraphedInference(net)
    x = torch.randn(1, 3, 8, 8, device="cuda")
    with torch.inference_mode():
        run(x)
        net.conv.bias.add_(1.0)
        assert torch.allclose(run(x)["mean"], net(x)["mean"])
        handle = net.conv.register_forward_hook(lambda *args: None)
        assert not run.usable(x)
        handle.remove()
