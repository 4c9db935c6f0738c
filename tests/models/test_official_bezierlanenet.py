"""The published BezierLaneNet files of pytorch-auto-drive load as its code saved them: the official network (written
here from the facts in models/bezierlanenet/official.py: the ResNet up to layer3 as `backbone`, `dilated_blocks`,
the FeatureFlipFusion `simple_flip_2d` with its DCNv2, the height-pooling `aggregator`, the ConvProjection_1D
`regression_head`, `proj_classification`, `proj_regression`, the SimpleSegHead `segmentation_head`) and ours, given
the converted file, compute the same outputs; its decoding (the local-maximum filter, the pruning to max_lane, the
curve sampled at the TuSimple rows or at 50 points for CULane) and ours keep the same lanes at the same places;
files of another backbone, family or network are refused naming the config that fits, or why none does."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torchvision
from torch import nn
from torch.nn import functional as F

from lanevil_train.checkpoints import CheckpointError
from lanevil_train.models.bezierlanenet.head import ModulatedDeformConv3x3
from lanevil_train.models.official import load_detector_weights, official_state_dict, recognise
from lanevil_train.tasks.builders import build_model, checkpoint_model, model_config
from tests.models.official_layouts import randomise_batch_norm
from tests.tasks.cli_helpers import composed

SMALL = (64, 160)  # a small input for the forward checks: a stride-16 map of 4 x 10, 10 queries
BEZIER = "BezierLaneNet (voldemortX/pytorch-auto-drive)"


# ------------------------------------------------------------------------------------------ the official network
class OfficialDCNv2Ref(nn.Module):
    """DCN_v2_Ref (feature_flip_fusion.py l. 9-56): mmcv's ModulatedDeformConv2d (weight, bias) with conv_offset
    Conv2d(2C, 27, 3, padding 1) over cat(x, ref); offsets = channels 0-17 as they are, masks = sigmoid(18-26);
    torchvision's deform_conv2d reads them in mmcv's layout (test_torchvision_deform_conv2d_reads_as_mmcv)."""

    def __init__(self, c):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(c, c, 3, 3))
        self.bias = nn.Parameter(torch.zeros(c))
        self.conv_offset = nn.Conv2d(2 * c, 27, 3, padding=1)

    def forward(self, x, ref):
        o1, o2, mask = torch.chunk(self.conv_offset(torch.cat([x, ref], dim=1)), 3, dim=1)
        return torchvision.ops.deform_conv2d(x, torch.cat((o1, o2), dim=1), self.weight, self.bias, padding=(1, 1),
                                             mask=torch.sigmoid(mask))


class OfficialFeatureFlipFusion(nn.Module):
    """feature_flip_fusion.py l. 59-78: relu(proj1(f) + proj2_norm(proj2_conv(flip(f), proj1(f))))."""

    def __init__(self, c):
        super().__init__()
        self.proj1 = nn.Sequential(nn.Conv2d(c, c, 1), nn.BatchNorm2d(c))
        self.proj2_conv = OfficialDCNv2Ref(c)
        self.proj2_norm = nn.BatchNorm2d(c)

    def forward(self, feature):
        flipped = feature.flip(-1)
        feature = self.proj1(feature)
        return F.relu(feature + self.proj2_norm(self.proj2_conv(flipped, feature)))


class OfficialDilatedBottleneck(nn.Module):
    """dilated_bottleneck.py l. 8-42: Sequential(conv, BN) x 3 (1x1, 3x3 dilated, 1x1), a ReLU after each, then the
    input added."""

    def __init__(self, c, mid, d):
        super().__init__()
        self.conv1 = nn.Sequential(nn.Conv2d(c, mid, 1), nn.BatchNorm2d(mid))
        self.conv2 = nn.Sequential(nn.Conv2d(mid, mid, 3, padding=d, dilation=d), nn.BatchNorm2d(mid))
        self.conv3 = nn.Sequential(nn.Conv2d(mid, c, 1), nn.BatchNorm2d(c))

    def forward(self, x):
        return F.relu(self.conv3(F.relu(self.conv2(F.relu(self.conv1(x)))))) + x


class OfficialConvProjection1D(nn.Module):
    """conv_projection_1d.py l. 9-24: hidden_layers (Conv1d k, bias) and hidden_norms (BN1d), relu(norm(conv))."""

    def __init__(self, layers, c, k=3):
        super().__init__()
        self.hidden_layers = nn.ModuleList(nn.Conv1d(c, c, k, padding=(k - 1) // 2) for _ in range(layers))
        self.hidden_norms = nn.ModuleList(nn.BatchNorm1d(c) for _ in range(layers))

    def forward(self, x):
        for conv, norm in zip(self.hidden_layers, self.hidden_norms):
            x = F.relu(norm(conv(x)))
        return x


class OfficialSimpleSegHead(nn.Module):
    """simple_seg_head.py l. 35-46: conv = ConvBNReLU (conv 3x3 WITHOUT bias, bn, relu), conv_out 1x1 without bias."""

    def __init__(self, c, mid):
        super().__init__()
        self.conv = nn.Module()
        self.conv.conv = nn.Conv2d(c, mid, 3, padding=1, bias=False)
        self.conv.bn = nn.BatchNorm2d(mid)
        self.conv_out = nn.Conv2d(mid, 1, 1, bias=False)

    def forward(self, x):
        return self.conv_out(F.relu(self.conv.bn(self.conv.conv(x))))


class OfficialRESAReducer(nn.Module):
    """resa_reducer.py l. 8-24 with bn_relu=True: conv1 1x1 without bias, bn1, ReLU."""

    def __init__(self, cin, c):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, c, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(c)

    def forward(self, x):
        return F.relu(self.bn1(self.conv1(x)))


class LayerGetter(nn.ModuleDict):
    """IntermediateLayerGetter (utils/models/_utils.py l. 48-60) with return_layer='layer3': the ResNet's children
    up to layer3, run in order."""

    def __init__(self, resnet):
        super().__init__({name: getattr(resnet, name) for name in ("conv1", "bn1", "relu", "maxpool", "layer1",
                                                                   "layer2", "layer3")})

    def forward(self, x):
        for module in self.values():
            x = module(x)
        return {"out": x}


class OfficialBezierLaneNet(nn.Module):
    """bezier_lane_net.py l. 13-69 as the releases configure it (reducer only for a backbone wider than 256)."""

    def __init__(self, depth=18, image_height=360, seg_head=True):
        super().__init__()
        resnet = getattr(torchvision.models, f"resnet{depth}")()
        self.backbone = LayerGetter(resnet)
        self.reducer = OfficialRESAReducer(1024, 256) if depth >= 50 else None
        self.dilated_blocks = nn.Sequential(*[OfficialDilatedBottleneck(256, 64, d) for d in (4, 8)])
        self.simple_flip_2d = OfficialFeatureFlipFusion(256)
        self.aggregator = nn.AvgPool2d(kernel_size=((image_height - 1) // 16 + 1, 1), stride=1, padding=0)
        self.regression_head = OfficialConvProjection1D(2, 256)
        self.proj_classification = nn.Conv1d(256, 1, 1)
        self.proj_regression = nn.Conv1d(256, 8, 1)
        self.segmentation_head = OfficialSimpleSegHead(256, 64) if seg_head else None
        _away_from_init(self)

    def forward(self, x):
        x = self.backbone(x)["out"]
        if self.reducer is not None:
            x = self.reducer(x)
        segmentations = self.segmentation_head(x) if self.segmentation_head is not None else None
        x = self.simple_flip_2d(self.dilated_blocks(x))  # in float32 under autocast (l. 59-60): no autocast here
        x = self.regression_head(self.aggregator(x)[:, :, 0, :])
        curves = self.proj_regression(x)
        return {"logits": self.proj_classification(x).squeeze(1),
                "curves": curves.permute(0, 2, 1).reshape(curves.shape[0], -1, curves.shape[-2] // 2, 2),
                "segmentations": segmentations}


def _away_from_init(net):
    """Random weights of another law than either network's initialisation, BN statistics too (so a weight or buffer
    left unloaded shows), and a conv_offset giving offsets of about a pixel and masks away from 0.5 (so the
    deformable sampling, its layout and its zeros outside the map all count)."""
    for name, m in net.named_modules():
        if isinstance(m, (nn.Conv1d, nn.Conv2d)):
            gain = 1.0 if name.endswith("conv_offset") else math.sqrt(2.0)
            nn.init.normal_(m.weight, 0.0, gain / math.sqrt(m.weight[0].numel()))
            if m.bias is not None:
                nn.init.normal_(m.bias, 0.0, 0.1)
        elif isinstance(m, (nn.BatchNorm1d, nn.BatchNorm2d)):
            randomise_batch_norm(m)
        elif isinstance(m, OfficialDCNv2Ref):
            nn.init.normal_(m.weight, 0.0, math.sqrt(2.0 / m.weight[0].numel()))
            nn.init.normal_(m.bias, 0.0, 0.1)


def _save(path, net, prefix=""):
    """As utils/common.py save_checkpoint writes it (a DataParallel run adds 'module.')."""
    torch.save({"model": {prefix + k: v for k, v in net.state_dict().items()}, "optimizer": None,
                "lr_scheduler": None}, path)
    return path


def _ours(experiment, *overrides):
    cfg = composed([f"experiment={experiment}", "data.root=/unused", *overrides])
    return build_model(model_config(cfg)).eval()


def _small(*overrides):
    return (f"data.input_size=[{SMALL[0]},{SMALL[1]}]", *overrides)


@pytest.fixture(scope="module")
def small_file(tmp_path_factory):
    """A ResNet-18 file of a network built for the small input, saved under DataParallel's prefix."""
    torch.manual_seed(0)
    net = OfficialBezierLaneNet(18, image_height=SMALL[0]).eval()
    return net, _save(tmp_path_factory.mktemp("bezier") / "model.pt", net, prefix="module.")


def _assert_same_outputs(ours_model, official, x):
    with torch.no_grad():
        theirs = official(x)
        ours = ours_model(x)
        head = ours_model.head
        seg = head.seg_head(head.reducer(ours_model.features(x)[-1]))  # training-only here: called directly
    assert ours["logits"].shape == theirs["logits"].shape == (x.shape[0], x.shape[-1] // 16)
    assert ours["curves"].shape == theirs["curves"].shape == (x.shape[0], x.shape[-1] // 16, 4, 2)
    assert theirs["logits"].std() > 0.1 and theirs["curves"].std() > 0.1  # outputs that say something
    torch.testing.assert_close(ours["logits"], theirs["logits"], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ours["curves"], theirs["curves"], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(seg, theirs["segmentations"], rtol=1e-4, atol=1e-4)


# ------------------------------------------------------------------------------------------ loading
def test_the_converted_file_gives_the_official_networks_outputs(small_file):
    official, path = small_file
    model = _ours("official_bezierlanenet_tusimple", *_small())
    line = load_detector_weights(model, path, "task.init_from")
    assert f"official {BEZIER} checkpoint (resnet18: cubic curves, 256-channel branch (the file does not tell" in line
    x = torch.randn(2, 3, *SMALL)
    _assert_same_outputs(model, official, x)


def test_the_deformable_convolution_sees_offsets_and_masks_that_matter(small_file):
    """The check above would pass with a DCN ignoring its offsets if they were all zero: they are about a pixel (so
    the border taps of the 4 x 10 map read outside it) and the masks vary."""
    official, _ = small_file
    with torch.no_grad():
        f = official.dilated_blocks(official.backbone(torch.randn(1, 3, *SMALL))["out"])
        out = official.simple_flip_2d.proj2_conv.conv_offset(torch.cat([f.flip(-1), official.simple_flip_2d.proj1(f)],
                                                                        dim=1))
    assert out[:, :18].abs().mean() > 0.5 and out[:, 18:].sigmoid().std() > 0.1


def mmcv_modulated_deform_conv(x, offset, mask, weight, bias):
    """modulated_deformable_im2col_gpu_kernel and dmcn_im2col_bilinear of mmcv, written out for a 3x3 kernel,
    stride 1, padding 1: tap k = 3i + j of output (h, w) reads row h - 1 + i + offset[2k], column w - 1 + j +
    offset[2k + 1], times mask[k]; 0 outside (-1, H) x (-1, W), and a bilinear corner outside the map reads 0."""
    b, c, height, width = x.shape
    cols = torch.zeros(b, c, 9, height, width, dtype=x.dtype)
    for n in range(b):
        for h in range(height):
            for w in range(width):
                for i in range(3):
                    for j in range(3):
                        k = 3 * i + j
                        y = h - 1 + i + float(offset[n, 2 * k, h, w])
                        xx = w - 1 + j + float(offset[n, 2 * k + 1, h, w])
                        if not (-1 < y < height and -1 < xx < width):
                            continue
                        y0, x0 = math.floor(y), math.floor(xx)
                        val = torch.zeros(c, dtype=x.dtype)
                        for yy, xc, wt in ((y0, x0, (1 - (y - y0)) * (1 - (xx - x0))),
                                           (y0, x0 + 1, (1 - (y - y0)) * (xx - x0)),
                                           (y0 + 1, x0, (y - y0) * (1 - (xx - x0))),
                                           (y0 + 1, x0 + 1, (y - y0) * (xx - x0))):
                            if 0 <= yy < height and 0 <= xc < width:
                                val = val + wt * x[n, :, yy, xc]
                        cols[n, :, k, h, w] = val * mask[n, k, h, w]
    return torch.einsum("ocz,bczhw->bohw", weight.reshape(weight.shape[0], c, 9), cols) + bias.reshape(1, -1, 1, 1)


def test_torchvision_and_our_deformable_convolution_read_offsets_and_masks_as_mmcv():
    """On a 3x4 map with offsets up to 2 px (points outside, corners outside): mmcv's formula, torchvision's
    deform_conv2d (the official network of this file) and this project's plain-torch DCNv2 agree."""
    torch.manual_seed(3)
    x = torch.randn(2, 3, 3, 4, dtype=torch.float64)
    out = torch.randn(2, 27, 3, 4, dtype=torch.float64) * 1.5
    weight, bias = torch.randn(5, 3, 3, 3, dtype=torch.float64), torch.randn(5, dtype=torch.float64)
    offset, mask = out[:, :18], torch.sigmoid(out[:, 18:])
    expected = mmcv_modulated_deform_conv(x, offset, mask, weight, bias)
    torch.testing.assert_close(torchvision.ops.deform_conv2d(x, offset, weight, bias, padding=(1, 1), mask=mask),
                               expected, rtol=1e-9, atol=1e-9)
    ours = ModulatedDeformConv3x3(3).double()  # square: channels in = out
    nn.init.normal_(ours.weight)
    nn.init.normal_(ours.bias)
    got = ours.deform(x, offset[:, 0::2], offset[:, 1::2], mask)
    torch.testing.assert_close(got, mmcv_modulated_deform_conv(x, offset, mask, ours.weight.data, ours.bias.data),
                               rtol=1e-9, atol=1e-9)


def test_under_autocast_the_flip_fusion_runs_in_float32_as_the_official():
    """bezier_lane_net.py l. 59-60: autocast off and x.float() around the fusion (mmcv's DCN has no fp16); the
    rest under autocast (here CPU bfloat16)."""
    model = _ours("official_bezierlanenet_culane", *_small())
    seen = {}
    model.head.fusion.register_forward_hook(lambda module, args, out: seen.update(args=args[0].dtype, out=out.dtype))
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(torch.randn(1, 3, *SMALL))
    assert seen == {"args": torch.float32, "out": torch.float32} and out["logits"].dtype == torch.bfloat16


def test_a_file_without_the_segmentation_head_loads_too(tmp_path):
    """The segmentation head is training-only (eval(profiling=True) drops it): a file may lack it."""
    torch.manual_seed(4)
    official = OfficialBezierLaneNet(18, image_height=SMALL[0], seg_head=False).eval()
    path = _save(tmp_path / "no_seg.pt", official)
    cfg = composed(["task=evaluate", "experiment=official_bezierlanenet_culane", "data.root=/unused",
                    f"ckpt_path={path}", *_small()])
    model = checkpoint_model(cfg).eval()
    x = torch.randn(1, 3, *SMALL)
    with torch.no_grad():
        theirs, ours = official(x), model(x)
    torch.testing.assert_close(ours["logits"], theirs["logits"], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ours["curves"], theirs["curves"], rtol=1e-4, atol=1e-4)


def test_a_resnet50_file_with_the_official_channel_reducer_loads_with_a_zero_bias(tmp_path):
    """No release is on ResNet-50, but the official code builds one with reducer_cfg RESAReducer(1024, 256): its 1x1
    without bias is this project's reducer conv with a zero bias."""
    torch.manual_seed(5)
    official = OfficialBezierLaneNet(50, image_height=SMALL[0]).eval()
    path = _save(tmp_path / "r50.pt", official)
    found = recognise(official_state_dict(torch.load(path, weights_only=True)))[1]
    assert found.what.startswith("resnet50 with a channel reducer: cubic curves, 256-channel branch")
    assert found.config == "experiment=official_bezierlanenet_<tusimple|culane> backbone=resnet50"
    model = _ours("official_bezierlanenet_culane", "backbone=resnet50", *_small())
    load_detector_weights(model, path, "ckpt_path")
    assert not model.head.reducer[0][0].bias.any()
    _assert_same_outputs(model, official, torch.randn(1, 3, *SMALL))


@pytest.mark.parametrize("depth", [18, 34])
def test_the_releases_backbone_is_recognised_and_named_in_the_config(depth, tmp_path):
    official = OfficialBezierLaneNet(depth)
    path = _save(tmp_path / f"resnet{depth}.pt", official)
    release, found = recognise(official_state_dict(torch.load(path, weights_only=True)))
    assert release.family == "bezierlanenet" and not found.unsupported
    assert found.what == (f"resnet{depth}: cubic curves, 256-channel branch (the file does not tell the dataset: "
                          f"every release has the same shapes)")
    assert found.config == f"experiment=official_bezierlanenet_<tusimple|culane> backbone=resnet{depth}"
    if depth == 34:  # it loads into the backbone it names (ResNet-18: test above)
        model = _ours("official_bezierlanenet_tusimple", "backbone=resnet34", *_small())
        load_detector_weights(model, path, "ckpt_path")
        torch.testing.assert_close(model.backbone.layer3[5].bn2.running_var,
                                   official.backbone["layer3"][5].bn2.running_var, rtol=0, atol=0)
        torch.testing.assert_close(model.head.fusion.proj2_conv.conv_offset.weight,
                                   official.simple_flip_2d.proj2_conv.conv_offset.weight, rtol=0, atol=0)


def test_a_resnet34_file_with_the_resnet18_config_is_refused_naming_the_weight_and_the_config(tmp_path):
    path = _save(tmp_path / "resnet34.pt", OfficialBezierLaneNet(34))
    model = _ours("official_bezierlanenet_tusimple", *_small())
    with pytest.raises(CheckpointError) as error:
        load_detector_weights(model, path, "ckpt_path")
    message = str(error.value)
    assert "unexpected (first: backbone.layer1.2.conv1.weight" in message
    assert ("run it with experiment=official_bezierlanenet_<tusimple|culane> backbone=resnet34" in message)


def test_a_file_of_an_unpublished_head_setting_names_its_settings(tmp_path):
    state = OfficialBezierLaneNet(18).state_dict()
    state = {k: v for k, v in state.items() if not k.startswith("regression_head.hidden_")
             or k.split(".")[2] == "0"}  # a single projection layer
    found = recognise(state)[1]
    assert found.config == ("experiment=official_bezierlanenet_<tusimple|culane> backbone=resnet18 "
                            "model.head.projection_layers=1")
    assert "an unpublished setting" in found.what


@pytest.mark.parametrize("change, why", [
    ("order2", "its curves have 3 control points (a Bezier curve of order 2); this project's head predicts cubic"),
    ("layer4", "its backbone returns ResNet layer4 (stride 32)"),
    ("bare_reducer", "its channel reducer is a 1x1 convolution alone (RESAReducer bn_relu=False)"),
])
def test_a_file_of_a_network_this_head_cannot_compute_is_refused_saying_why(change, why, tmp_path):
    state = OfficialBezierLaneNet(18).state_dict()
    if change == "order2":
        state["proj_regression.weight"], state["proj_regression.bias"] = torch.zeros(6, 256, 1), torch.zeros(6)
    elif change == "layer4":
        state.update({f"backbone.{k}": v for k, v in torchvision.models.resnet18().state_dict().items()
                      if k.startswith("layer4.")})
    else:
        state["reducer.conv1.weight"] = torch.zeros(256, 256, 1, 1)
    path = tmp_path / f"{change}.pt"
    torch.save({"model": state, "optimizer": None, "lr_scheduler": None}, path)
    model = _ours("official_bezierlanenet_tusimple", *_small())
    with pytest.raises(CheckpointError) as error:
        load_detector_weights(model, path, "ckpt_path")
    assert f"an official {BEZIER} checkpoint (resnet18, an unpublished setting) that this project cannot load: " \
           f"{why}" in str(error.value)


def test_a_bezierlanenet_file_with_the_scnn_config_is_refused_naming_the_bezierlanenet_config(small_file):
    _, path = small_file
    cfg = composed(["task=evaluate", "experiment=official_scnn_culane", "data.root=/unused", f"ckpt_path={path}"])
    with pytest.raises(CheckpointError, match=r"an official BezierLaneNet .* this run builds model=scnn; run it "
                                              r"with experiment=official_bezierlanenet_<tusimple\|culane> "
                                              r"backbone=resnet18"):
        checkpoint_model(cfg)


def test_a_ufld_file_with_the_bezierlanenet_config_is_refused_naming_the_ufld_config(tmp_path):
    ufld = {"model.conv1.weight": torch.zeros(1), "pool.weight": torch.zeros(1), "cls.0.weight": torch.zeros(1),
            "cls.2.weight": torch.zeros(101 * 56 * 4, 1),
            **{f"model.layer{i}.{b}.conv1.weight": torch.zeros(1) for i in range(1, 5) for b in (0, 1)}}
    torch.save({"model": ufld}, tmp_path / "tusimple_18.pth")
    cfg = composed(["task=evaluate", "experiment=official_bezierlanenet_tusimple", "data.root=/unused",
                    f"ckpt_path={tmp_path / 'tusimple_18.pth'}", *_small()])
    with pytest.raises(CheckpointError, match="an official UFLD v1 .* this run builds model=bezierlanenet; run it "
                                              "with experiment=official_ufld_tusimple backbone=resnet18"):
        checkpoint_model(cfg)


# ------------------------------------------------------------------------------------------ decoding
def official_keep(logits, thresh, window, max_lane):
    """bezier_base.py l. 56-74: existence = sigmoid > thresh, times the local maxima of max_pool1d(window, stride 1,
    padding (window - 1) // 2, return_indices), then lane_pruning (utils.py l. 4-14): while more than max_lane, the
    least confident of all queries is dropped (its confidence set to 1.1)."""
    conf = logits.sigmoid()
    existence = conf > thresh
    _, idx = F.max_pool1d(conf.unsqueeze(1), kernel_size=window, stride=1, padding=(window - 1) // 2,
                          return_indices=True)
    existence = existence & (idx.squeeze(1) == torch.arange(conf.shape[1]).unsqueeze(0))
    conf = conf.clone()
    while (existence.sum(dim=1) > max_lane).any():
        drop = (existence.sum(dim=1, keepdim=True) > max_lane) & (conf == conf.min(dim=1, keepdim=True).values)
        existence[drop] = False
        conf[drop] = 1.1
    return existence


def official_bernstein(n):
    """curve_utils.py l. 58-62, 83-86: the cubic Bernstein matrix at n t evenly spaced in [0, 1]."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    k = np.arange(4)[None]
    return np.array([1, 3, 3, 1])[None] * t**k * (1 - t) ** (3 - k)


def official_tusimple_lanes(cps, keep, ppl=56, gap=10, size=(720, 1280)):
    """bezier_to_coordinates for TuSimple (bezier_base.py l. 28-42), H = 720 sample points (l. 85): per kept lane,
    the x (times W) of the sampled point nearest each row H - (ppl - i) gap, or -2 if it is over 5 / H away in y or
    x is outside [0, 1]."""
    big_h, big_w = size
    rows = np.array([1.0 - (ppl - i) * gap / big_h for i in range(ppl)])
    lanes = []
    for q in np.flatnonzero(keep):
        pts = official_bernstein(big_h) @ cps[q]
        dis = np.abs(rows[:, None] - pts[None, :, 1])
        near = dis.argmin(axis=1)
        xs = [(-2.0 if dis[i, near[i]] > 5.0 / big_h or not 0 <= pts[near[i], 0] <= 1 else pts[near[i], 0] * big_w)
              for i in range(ppl)]
        lanes.append(np.array(xs))
    return lanes, rows * big_h


def official_culane_lanes(cps, keep, n=50, size=(590, 1640)):
    """bezier_to_coordinates for CULane (l. 43-47): the n sampled points of each kept lane times (W, H), in or out of
    the image."""
    return [official_bernstein(n) @ cps[q] * np.array([size[1], size[0]]) for q in np.flatnonzero(keep)]


def _constructed_output(queries, rng):
    """Existence logits with lanes the filters must sort out (a neighbour within the window, an exact tie, one below
    the threshold, one more lane than max_lane) and plausible curves: from below the bottom edge (y > 1) up to about
    0.4 of the height, some leaving the image at a side."""
    logits = torch.full((1, queries), -4.0)
    for q, value in {0: 0.3, 5: 3.0, 7: 2.0, 12: 1.0, 16: -0.5, 20: 2.5, 21: 2.5, 28: 0.5, 36: 0.2}.items():
        logits[0, q] = value
    curves = np.zeros((1, queries, 4, 2))
    for q in range(queries):
        bottom_x = -0.3 + 1.6 * q / (queries - 1)  # left lanes leave the image on the left, right ones on the right
        top = (0.45 + 0.15 * (bottom_x - 0.5), rng.uniform(0.38, 0.46))
        bend = rng.uniform(-0.05, 0.05)
        bottom = (bottom_x, rng.uniform(1.0, 1.08))
        for k, t in enumerate((0.0, 1 / 3, 2 / 3, 1.0)):
            x = bottom[0] + (top[0] - bottom[0]) * t + (bend if k in (1, 2) else 0.0)
            curves[0, q, k] = (x, bottom[1] + (top[1] - bottom[1]) * t)
    return {"logits": logits, "curves": torch.tensor(curves, dtype=torch.float32)}


def test_decoding_keeps_the_official_tusimple_lanes_at_the_official_points():
    """The release's 40 queries (640 px): the same lanes kept as the official local-maximum filter, threshold 0.5 and
    pruning to 5; in the 1280x720 image each lane's points are the official writer's, at the same TuSimple rows
    (official_writer tusimple: the nearest of its 720 sampled points in y, within 5 px of the row, x in the image)."""
    cfg = composed(["experiment=official_bezierlanenet_tusimple", "data.root=/unused"])
    model = _ours("official_bezierlanenet_tusimple")
    raw = _constructed_output(40, np.random.default_rng(0))
    keep = official_keep(raw["logits"], 0.5, 9, 5)[0].numpy()
    assert np.flatnonzero(keep).tolist() == [0, 5, 12, 20, 28]  # 7 (window), 21 (tie), 36 (pruned), 16 (< 0.5) out
    cps = raw["curves"][0].double().numpy()
    theirs, rows = official_tusimple_lanes(cps, keep)
    ours = model.decode_lanes(raw, tuple(cfg.data.input_size), [(720, 1280)])[0]
    assert cfg.model.decode.max_lanes == 5 and len(ours) == len(theirs) == 5
    for mine, xs in zip(ours, sorted(theirs, key=lambda xs: xs[xs > -2][-1])):  # left to right at the bottom
        defined = xs > -2
        assert defined.sum() >= 20
        official = np.stack([xs[defined], rows[defined]], 1)
        np.testing.assert_allclose(mine[np.argsort(mine[:, 1])], official[np.argsort(official[:, 1])], atol=1e-6)


def test_decoding_keeps_the_official_culane_lanes_on_the_official_curves():
    """The release's 50 queries (800 px), threshold 0.95, window 9, 4 lanes: the same lanes as the official, each with
    its 50 sampled points in the 1640x590 image, those outside the image included (official_writer culane)."""
    cfg = composed(["experiment=official_bezierlanenet_culane", "data.root=/unused"])
    model = _ours("official_bezierlanenet_culane")
    raw = _constructed_output(50, np.random.default_rng(1))
    raw["logits"] = raw["logits"] + 3.0  # above 0.95 (logit 2.94): all the peaks but 16
    keep = official_keep(raw["logits"], 0.95, 9, 4)[0].numpy()
    assert np.flatnonzero(keep).tolist() == [5, 12, 20, 28]  # 7 (window), 21 (tie), 0 and 36 (pruned) out
    theirs = official_culane_lanes(raw["curves"][0].double().numpy(), keep)
    ours = model.decode_lanes(raw, tuple(cfg.data.input_size), [(590, 1640)])[0]
    assert len(ours) == len(theirs) == 4
    for mine, pts in zip(ours, sorted(theirs, key=lambda p: p[np.argmax(p[:, 1]), 0])):
        assert len(mine) == 50
        np.testing.assert_allclose(mine[np.argsort(mine[:, 1])], pts[np.argsort(pts[:, 1])], atol=1e-6)


@pytest.mark.slow
def test_checkpoint_model_at_the_release_size_gives_the_official_outputs(tmp_path):
    """The TuSimple release's 360x640 input (the official aggregator pooling its 23 rows) through the config the
    file names: seconds on a CPU."""
    torch.manual_seed(6)
    official = OfficialBezierLaneNet(34, image_height=360).eval()
    path = _save(tmp_path / "resnet34_tusimple.pt", official)
    cfg = composed(["task=evaluate", "experiment=official_bezierlanenet_tusimple", "backbone=resnet34",
                    "data.root=/unused", f"ckpt_path={path}"])
    # in float64: at this size the float32 sums of the two networks' random weights part by a few 1e-4
    _assert_same_outputs(checkpoint_model(cfg).eval().double(), official.double(),
                         torch.randn(1, 3, 360, 640, dtype=torch.float64))


def test_task_evaluate_scores_an_official_file_on_a_culane_folder(small_file, tmp_path):
    """`python -m lanevil_train task=evaluate experiment=official_bezierlanenet_culane ckpt_path=model.pt
    data.root=R` (at the small input the file was built for), in this process: the config check passes, the file is
    converted, the images scored and the prediction files written."""
    from lanevil_train.data.formats import write_culane
    from tests.tasks.cli_helpers import run_in_process, write_photo_dataset

    _, path = small_file
    root = tmp_path / "culane"
    names = [f"driver_00_01frame/05151640_0419.MP4/{i:05d}.jpg" for i in range(2)]
    write_culane(write_photo_dataset(root, names), root, root / "list" / "test.txt")
    run_dir = tmp_path / "run"
    run_in_process(["task=evaluate", "experiment=official_bezierlanenet_culane", f"data.root={root}",
                    f"ckpt_path={path}", *_small(), "trainer=cpu", "progress=none", "data.num_workers=0",
                    "task.predictions=true"], run_dir)
    assert (run_dir / "test_scores.json").is_file()
    listed = (run_dir / "predictions" / "culane" / "list.txt").read_text().split()
    assert listed == ["/" + name for name in names]
