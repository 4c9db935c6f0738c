"""The published CLRerNet files load as the repository saved them: an mmdetection file ({'meta', 'state_dict'}) of the
official key names and shapes (written here from the facts in models/clrernet/official.py), random values, converts
to exactly this network's weights and loads; a CLRNet file is refused naming its first key that differs."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from lanevil_train.checkpoints import CheckpointError
from lanevil_train.models.clrernet.official import convert
from lanevil_train.models.official import load_detector_weights, load_official
from lanevil_train.tasks.builders import build_model, model_config
from tests.models.test_official_clrnet import DLAWrapper, OfficialCLRNet
from tests.tasks.cli_helpers import composed

H, W, S, P, C, NS = 320, 800, 72, 192, 64, 36
HEAD = "bbox_head."


def _conv_module(prefix, cin, cout, kernel, norm):
    """An mmcv ConvModule's keys: `conv` (biased unless normed), `bn`."""
    kh, kw = kernel
    out = {f"{prefix}.conv.weight": (cout, cin, kh, kw)}
    if norm:
        out.update({f"{prefix}.bn.{k}": (cout,) for k in ("weight", "bias", "running_mean", "running_var")})
        out[f"{prefix}.bn.num_batches_tracked"] = ()
    else:
        out[f"{prefix}.conv.bias"] = (cout,)
    return out


def official_shapes(with_seg: bool) -> dict[str, tuple]:
    """CLRerNet's state dict (clrernet_culane_dla34, base_clrernet.py): name -> shape, in the module order."""
    backbone = {k: tuple(v.shape) for k, v in DLAWrapper().state_dict().items()
                if not k.startswith(("model.level3.project.", "model.level4.project."))}  # dla.py:247: one-level only
    shapes = {f"backbone.{k}": v for k, v in backbone.items()}
    for i, cin in enumerate((128, 256, 512)):
        shapes.update(_conv_module(f"neck.lateral_convs.{i}", cin, C, (1, 1), norm=False))
    for i in range(3):
        shapes.update(_conv_module(f"neck.fpn_convs.{i}", C, C, (3, 3), norm=False))
    shapes.update({HEAD + "sample_x_indices": (NS,), HEAD + "prior_feat_ys": (NS,), HEAD + "prior_ys": (S,),
                   HEAD + "anchor_generator.prior_embeddings.weight": (P, 3)})
    attention = HEAD + "attention."
    shapes.update(_conv_module(attention + "attention.f_key", C, C, (1, 1), norm=True))
    shapes.update({attention + "attention.f_query.0.weight": (P, 1, 1), attention + "attention.f_query.0.bias": (P,),
                   attention + "attention.f_value.weight": (C, C, 1, 1), attention + "attention.f_value.bias": (C,),
                   attention + "attention.W.weight": (P, 1, 1), attention + "attention.W.bias": (P,)})
    for i in range(3):
        shapes.update(_conv_module(f"{attention}convs.{i}", C, 48, (9, 1), norm=True))
    for i in range(3):
        shapes.update(_conv_module(f"{attention}catconv.{i}", 48 * (i + 1), C, (9, 1), norm=True))
    shapes.update({attention + "fc.weight": (C, NS * C), attention + "fc.bias": (C,),
                   attention + "fc_norm.weight": (C,), attention + "fc_norm.bias": (C,)})
    if with_seg:
        shapes[HEAD + "loss_seg.criterion.weight"] = (5,)
    for part in ("reg_modules", "cls_modules"):
        for i in (0, 2):
            shapes.update({f"{HEAD}{part}.{i}.weight": (C, C), f"{HEAD}{part}.{i}.bias": (C,)})
    shapes.update({HEAD + "reg_layers.weight": (S + 4, C), HEAD + "reg_layers.bias": (S + 4,),
                   HEAD + "cls_layers.weight": (2, C), HEAD + "cls_layers.bias": (2,)})
    if with_seg:
        shapes.update({HEAD + "seg_decoder.conv.weight": (5, 3 * C, 1, 1), HEAD + "seg_decoder.conv.bias": (5,)})
    return shapes


def official_state(with_seg: bool, seed: int = 0) -> dict[str, torch.Tensor]:
    """Random values of the official shapes; the buffers as the head computes them (clrernet_head.py:66-82)."""
    g = torch.Generator().manual_seed(seed)
    state = {}
    for key, shape in official_shapes(with_seg).items():
        if key.endswith("num_batches_tracked"):
            state[key] = torch.tensor(1000)
        elif key.endswith("running_var"):
            state[key] = torch.rand(shape, generator=g) + 0.5
        else:
            state[key] = torch.randn(shape, generator=g) * 0.1
    index = (torch.linspace(0, 1, NS) * (S - 1)).long()
    state[HEAD + "sample_x_indices"] = index
    state[HEAD + "prior_feat_ys"] = torch.flip(index.float() / (S - 1), dims=[-1])
    state[HEAD + "prior_ys"] = torch.linspace(1, 0, S)
    embeddings = torch.rand(P, 3, generator=g) * torch.tensor([0.5, 1.0, 0.6]) + torch.tensor([0.5, 0.0, 0.2])
    state[HEAD + "anchor_generator.prior_embeddings.weight"] = embeddings  # y0 in [0.5, 1] (from the top), theta
    return state


@pytest.fixture(scope="module")
def model():
    cfg = composed(["experiment=official_clrernet_culane", "data.root=/unused"])
    return build_model(model_config(cfg)).eval()


def test_the_converter_round_trips_an_official_state_dict(model, tmp_path):
    """Every official tensor lands in this network (no key missing, none unexpected), unchanged but for y0, which
    becomes start_y = 1 - y0 in the embeddings and in what reg_layers adds to it: the network's stage-0 lines are
    the official anchors refined by the official regression (anchor_generator.py:81-92, clrernet_head.py:225)."""
    state = official_state(with_seg=True)
    converted = convert(state)
    own = model.state_dict()
    assert set(converted) == set(own)  # no missing or unexpected key
    assert all(converted[k].shape == own[k].shape for k in own)
    model.load_state_dict(converted, strict=True)
    y0 = state[HEAD + "anchor_generator.prior_embeddings.weight"]
    torch.testing.assert_close(model.head.prior_embeddings[:, 0].detach(), 1 - y0[:, 0])
    torch.testing.assert_close(model.backbone.state_dict()["level5.tree2.bn2.running_var"],
                               state["backbone.model.level5.tree2.bn2.running_var"])
    torch.testing.assert_close(model.head.roi_gather.f_query[0].weight,
                               state[HEAD + "attention.attention.f_query.0.weight"])
    torch.testing.assert_close(model.neck.state_dict()["output.2.weight"], state["neck.fpn_convs.2.conv.weight"])

    features = [torch.randn(1, C, H // s, W // s, generator=torch.Generator().manual_seed(s)) for s in (8, 16, 32)]
    seen = []
    hook = model.head.reg_fc.register_forward_hook(lambda module, inputs, output: seen.append(output))
    with torch.no_grad():
        raw = model.head(features)
    hook.remove()
    reg = F.linear(seen[0], state[HEAD + "reg_layers.weight"], state[HEAD + "reg_layers.bias"])  # official, stage 0
    torch.testing.assert_close(1 - raw["lines"][0, 0, :, 0], y0[:, 0] + reg[0, :, 0], rtol=1e-5, atol=1e-5)
    ys = torch.linspace(1, 0, S)  # the official anchor x at the rows, refined: (x0 (W-1) - (ys - y0) H / tan) / (W-1)
    x0, theta = state[HEAD + "anchor_generator.prior_embeddings.weight"][:, 1:].T + reg[0, :, 1:3].T
    y0_new = y0[:, 0] + reg[0, :, 0]
    rise = (ys - y0_new[:, None]) * H / torch.tan(theta[:, None] * math.pi + 1e-5)
    anchors = (x0[:, None] * (W - 1) - rise) / (W - 1)
    torch.testing.assert_close(raw["xs"][0, 0] / (W - 1), anchors + reg[0, :, 4:], rtol=1e-4, atol=1e-4)

    # the published file: mmdetection's {'meta', 'state_dict'}, no segmentation decoder nor criterion weight
    published = official_state(with_seg=False, seed=1)
    torch.save({"meta": {"mmdet_version": "2.28.2", "epoch": 15, "config": "..."}, "state_dict": published},
               tmp_path / "clrernet_culane_dla34.pth")
    line = load_detector_weights(model, tmp_path / "clrernet_culane_dla34.pth", "ckpt_path")
    assert "official CLRerNet (hirotomusiker/CLRerNet) checkpoint (the culane release (no segmentation decoder: " \
           "the published CULane files), dla34: 192 priors, 72 points, 3 refinement stages, 36 sampled rows)" in line
    torch.testing.assert_close(model.head.reg_layer.bias[1:], published[HEAD + "reg_layers.bias"][1:])


def test_a_clrnet_file_is_refused_naming_the_first_key_that_differs(model):
    clrnet = OfficialCLRNet(classes=5).state_dict()  # CLRNet's layout, 'module.' dropped as the loader does
    with pytest.raises(ValueError, match=r"not a CLRerNet state dict: its first key that differs from CLRerNet's "
                                         r"layout is heads\.sample_x_indexs "):
        convert(clrnet)
    with pytest.raises(CheckpointError) as error:
        load_official(model, clrnet, "ckpt_path=culane_r18.pth")
    message = str(error.value)
    assert "an official CLRNet (Turoad/CLRNet) checkpoint" in message and "this run builds model=clrernet" in message
    assert "its first key that differs from CLRerNet's layout is heads.sample_x_indexs" in message
    assert "run it with experiment=official_clrnet_culane backbone=resnet18" in message
