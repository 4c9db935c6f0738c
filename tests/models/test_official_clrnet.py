"""The published CLRNet files load as the official code saved them: the official network (written here from the facts
in models/clrnet/official.py: torchvision's ResNet under `backbone.model`, mmcv's ConvModules, the head's priors as
buffers the eval forward reads) and ours, given the converted file, compute the same outputs at every refinement
stage; files of another release, family, input size or backbone are refused naming the setting that fits."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import torchvision
from torch import nn

from lanevil_train.checkpoints import CheckpointError
from lanevil_train.models.official import load_detector_weights, official_state_dict, recognise
from lanevil_train.tasks.builders import build_model, checkpoint_model, model_config
from tests.models.official_layouts import ConvModule
from tests.tasks.cli_helpers import composed

H, W, S, P, C, NS, STAGES = 320, 800, 72, 192, 64, 36, 3


class Backbone(nn.Module):
    """ResNetWrapper: torchvision's ResNet under `model`, its four stages' maps."""

    def __init__(self, depth=18):
        super().__init__()
        resnet = getattr(torchvision.models, f"resnet{depth}")()
        self.model = nn.Module()
        for name in ("conv1", "bn1", "relu", "maxpool", "layer1", "layer2", "layer3", "layer4"):
            setattr(self.model, name, getattr(resnet, name))

    def forward(self, x):
        m = self.model
        x = m.maxpool(m.relu(m.bn1(m.conv1(x))))
        out = []
        for name in ("layer1", "layer2", "layer3", "layer4"):
            x = getattr(m, name)(x)
            out.append(x)
        return out


def _bn_relu_conv_level(cin, cout, stride):
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False), nn.BatchNorm2d(cout),
                         nn.ReLU())


class DLABlock(nn.Module):
    """dla34.py's BasicBlock: two 3x3 convs with BN, the residual given by the tree (or its input)."""

    def __init__(self, cin, cout, stride=1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(cout)

    def forward(self, x, residual=None):
        residual = x if residual is None else residual
        return F.relu(self.bn2(self.conv2(F.relu(self.bn1(self.conv1(x))))) + residual)


class DLARoot(nn.Module):
    def __init__(self, cin, cout):
        super().__init__()
        self.conv = nn.Conv2d(cin, cout, 1, bias=False)
        self.bn = nn.BatchNorm2d(cout)

    def forward(self, *children):
        return F.relu(self.bn(self.conv(torch.cat(children, 1))))


class DLATree(nn.Module):
    """dla34.py's Tree: a `project` whenever the channels change, used only by a one-level tree."""

    def __init__(self, levels, cin, cout, stride=1, level_root=False, root_dim=0):
        super().__init__()
        root_dim = (root_dim or 2 * cout) + (cin if level_root else 0)
        self.levels, self.level_root = levels, level_root
        if levels == 1:
            self.tree1, self.tree2 = DLABlock(cin, cout, stride), DLABlock(cout, cout)
            self.root = DLARoot(root_dim, cout)
        else:
            self.tree1 = DLATree(levels - 1, cin, cout, stride)
            self.tree2 = DLATree(levels - 1, cout, cout, root_dim=root_dim + cout)
        self.downsample = nn.MaxPool2d(stride, stride) if stride > 1 else None
        self.project = nn.Sequential(nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout)) if cin != cout \
            else None

    def forward(self, x, residual=None, children=None):
        children = [] if children is None else children
        bottom = self.downsample(x) if self.downsample is not None else x
        residual = self.project(bottom) if self.project is not None else bottom
        if self.level_root:
            children.append(bottom)
        if self.levels == 1:
            x1 = self.tree1(x, residual)
            return self.root(self.tree2(x1), x1, *children)
        x1 = self.tree1(x)  # a tree computes its own residual: the one above goes unused
        children.append(x1)
        return self.tree2(x1, children=children)


class DLA34(nn.Module):
    """dla34.py's DLA with levels [1, 1, 1, 2, 2, 1] and channels [16, 32, 64, 128, 256, 512]: levels 2-5's maps."""

    def __init__(self):
        super().__init__()
        self.base_layer = nn.Sequential(nn.Conv2d(3, 16, 7, padding=3, bias=False), nn.BatchNorm2d(16), nn.ReLU())
        self.level0 = _bn_relu_conv_level(16, 16, 1)
        self.level1 = _bn_relu_conv_level(16, 32, 2)
        self.level2 = DLATree(1, 32, 64, 2)
        self.level3 = DLATree(2, 64, 128, 2, level_root=True)
        self.level4 = DLATree(2, 128, 256, 2, level_root=True)
        self.level5 = DLATree(1, 256, 512, 2, level_root=True)

    def forward(self, x):
        x = self.level1(self.level0(self.base_layer(x)))
        out = []
        for level in (self.level2, self.level3, self.level4, self.level5):
            x = level(x)
            out.append(x)
        return out


class DLAWrapper(nn.Module):
    def __init__(self):
        super().__init__()
        self.model = DLA34()

    def forward(self, x):
        return self.model(x)


class Neck(nn.Module):
    """The FPN without norm or activation over the last three maps (the first of four dropped)."""

    def __init__(self, in_channels=(128, 256, 512)):
        super().__init__()
        self.lateral_convs = nn.ModuleList(ConvModule(c, C, 1) for c in in_channels)
        self.fpn_convs = nn.ModuleList(ConvModule(C, C, 3, padding=1) for _ in in_channels)

    def forward(self, maps):
        maps = maps[len(maps) - len(self.lateral_convs):]
        laterals = [conv(m) for conv, m in zip(self.lateral_convs, maps)]
        for i in range(len(laterals) - 1, 0, -1):
            laterals[i - 1] = laterals[i - 1] + F.interpolate(laterals[i], size=laterals[i - 1].shape[2:],
                                                              mode="nearest")
        return [conv(m) for conv, m in zip(self.fpn_convs, laterals)]


class ROIGather(nn.Module):
    def __init__(self, mid=48):
        super().__init__()
        self.f_key = ConvModule(C, C, 1, norm=True, act=True)
        self.f_query = nn.Sequential(nn.Conv1d(P, P, 1, groups=P), nn.ReLU())
        self.f_value = nn.Conv2d(C, C, 1)
        self.W = nn.Conv1d(P, P, 1, groups=P)
        self.convs = nn.ModuleList(ConvModule(C, mid, (9, 1), padding=(4, 0), norm=True, act=True)
                                   for _ in range(STAGES))
        self.catconv = nn.ModuleList(ConvModule(mid * (i + 1), C, (9, 1), padding=(4, 0), norm=True, act=True)
                                     for i in range(STAGES))
        self.fc = nn.Linear(NS * C, C)
        self.fc_norm = nn.LayerNorm(C)

    def forward(self, pooled, fmap, stage):
        """pooled: every stage's (B P, C, NS, 1) so far; fmap (B, C, h, w) -> (B, P, C)."""
        b = fmap.shape[0]
        roi = self.catconv[stage](torch.cat([self.convs[i](f) for i, f in enumerate(pooled)], dim=1))
        roi = F.relu(self.fc_norm(self.fc(roi.reshape(b * P, -1)))).reshape(b, P, -1)
        key = F.interpolate(self.f_key(fmap), size=(10, 25)).flatten(2)
        value = F.interpolate(self.f_value(fmap), size=(10, 25)).flatten(2).permute(0, 2, 1)
        attention = torch.softmax(C ** -0.5 * torch.matmul(self.f_query(roi), key), dim=-1)
        return roi + self.W(torch.matmul(attention, value))  # dropout: eval


class SegDecoder(nn.Module):
    def __init__(self, classes):
        super().__init__()
        self.dropout = nn.Dropout2d(0.1)
        self.conv = nn.Conv2d(C * STAGES, classes, 1)


class Head(nn.Module):
    """CLRHead as its file lays it out; forward as in eval (the priors from the buffers), every stage returned as
    (B, P, 6 + S): [2 logits, start_y, start_x, theta, length, x / (W-1) at the S rows, bottom first]."""

    def __init__(self, classes):
        super().__init__()
        self.register_buffer("sample_x_indexs", (torch.linspace(0, 1, NS) * (S - 1)).long())
        self.register_buffer("prior_feat_ys", torch.flip(1 - self.sample_x_indexs.float() / (S - 1), dims=[-1]))
        self.register_buffer("prior_ys", torch.linspace(1, 0, S))
        self.prior_embeddings = nn.Embedding(P, 3)
        self.register_buffer("priors", torch.zeros(P, 6 + S))
        self.register_buffer("priors_on_featmap", torch.zeros(P, NS))
        self.seg_decoder = SegDecoder(classes)
        self.reg_modules = nn.ModuleList([nn.Linear(C, C), nn.ReLU(), nn.Linear(C, C), nn.ReLU()])
        self.cls_modules = nn.ModuleList([nn.Linear(C, C), nn.ReLU(), nn.Linear(C, C), nn.ReLU()])
        self.roi_gather = ROIGather()
        self.reg_layers = nn.Linear(C, S + 4)
        self.cls_layers = nn.Linear(C, 2)
        weight = torch.ones(classes)
        weight[0] = 0.4
        self.criterion = nn.NLLLoss(weight=weight)

    def line_xs(self, lines):
        """x / (W-1) at the S rows of lines (..., 3) [start_y, start_x, theta]: over img_h pixels."""
        start_y, start_x, theta = (lines[..., i:i + 1] for i in range(3))
        rise = (1 - self.prior_ys - start_y) * H
        return (start_x * (W - 1) + rise / torch.tan(theta * math.pi + 1e-5)) / (W - 1)

    def training_priors(self):
        """What a training forward stores in the buffers: the priors of the embeddings."""
        priors = torch.zeros(P, 6 + S)
        priors[:, 2:5] = self.prior_embeddings.weight.detach()
        priors[:, 6:] = self.line_xs(priors[:, 2:5])
        self.priors.copy_(priors)
        self.priors_on_featmap.copy_(priors[:, 6 + self.sample_x_indexs])

    def pool(self, fmap, xs):
        b = fmap.shape[0]
        grid = torch.stack([xs * 2 - 1, self.prior_feat_ys.expand(b, P, NS) * 2 - 1], dim=-1)  # (B, P, NS, 2)
        return F.grid_sample(fmap, grid, align_corners=True).permute(0, 2, 1, 3).reshape(b * P, C, NS, 1)

    def forward(self, maps):
        maps = list(maps[len(maps) - STAGES:])[::-1]
        b = maps[0].shape[0]
        priors, on_featmap = self.priors.repeat(b, 1, 1), self.priors_on_featmap.repeat(b, 1, 1)
        pooled, out = [], []
        for stage in range(STAGES):
            pooled.append(self.pool(maps[stage], torch.flip(on_featmap, dims=[2])))
            feat = self.roi_gather(pooled, maps[stage], stage).reshape(b * P, C)
            cls_feat, reg_feat = feat, feat
            for layer in self.cls_modules:
                cls_feat = layer(cls_feat)
            for layer in self.reg_modules:
                reg_feat = layer(reg_feat)
            cls = self.cls_layers(cls_feat).reshape(b, P, 2)
            reg = self.reg_layers(reg_feat).reshape(b, P, S + 4)
            pred = priors.clone()
            pred[..., :2] = cls
            pred[..., 2:5] += reg[..., :3]
            pred[..., 5] = reg[..., 3]
            pred[..., 6:] = self.line_xs(pred[..., 2:5])
            lines = pred.clone()
            pred[..., 6:] += reg[..., 4:]
            out.append(pred)
            priors = lines.detach()
            on_featmap = priors[..., 6 + self.sample_x_indexs]
        return torch.stack(out, dim=1)


class OfficialCLRNet(nn.Module):
    def __init__(self, classes=5, backbone="resnet18"):
        super().__init__()
        self.backbone = DLAWrapper() if backbone == "dla34" else Backbone(int(backbone[len("resnet"):]))
        self.neck = Neck()
        self.heads = Head(classes)

    def forward(self, x):
        return self.heads(self.neck(self.backbone(x)))


def randomised(net: OfficialCLRNet) -> OfficialCLRNet:
    """Weights away from both networks' initial values (norms, running statistics, the zero-initialised W, the
    priors), the priors buffers as a training forward leaves them, the embeddings one step newer."""
    with torch.no_grad():
        for module in net.modules():
            if isinstance(module, (nn.BatchNorm2d, nn.LayerNorm)):
                module.weight.uniform_(0.5, 1.5)
                module.bias.normal_(0.0, 0.1)
                if isinstance(module, nn.BatchNorm2d):
                    module.running_mean.normal_(0.0, 0.1)
                    module.running_var.uniform_(0.5, 1.5)
            elif isinstance(module, (nn.Conv1d, nn.Conv2d, nn.Linear)) and module.bias is not None:
                module.bias.normal_(0.0, 0.1)
        head = net.heads
        head.roi_gather.W.weight.normal_(0.0, 0.5)
        head.cls_layers.weight.normal_(0.0, 0.1)
        head.reg_layers.weight.normal_(0.0, 0.01)
        head.reg_layers.bias.normal_(0.0, 0.01)
        from lanevil_train.models.clrnet.priors import init_prior_embeddings

        head.prior_embeddings.weight.copy_(init_prior_embeddings(P) + 0.01 * torch.randn(P, 3))
        head.training_priors()
        head.prior_embeddings.weight.add_(1e-3 * torch.randn(P, 3))  # the optimizer's step after that forward
    return net.eval()


def save_official(net, path, drop=()):
    """Saved as the official training saves it (net_utils.save_model), MMDataParallel's prefix on every key."""
    state = {f"module.{k}": v for k, v in net.state_dict().items() if not k.startswith(drop)}
    torch.save({"net": state, "optim": {"state": {}, "param_groups": []}, "scheduler": {"T_max": 100, "last_epoch": 9},
                "recorder": {"step": 9}, "epoch": 14}, path)
    return path


@pytest.fixture(scope="module")
def culane(tmp_path_factory):
    torch.manual_seed(0)
    net = randomised(OfficialCLRNet(classes=5))
    return net, save_official(net, tmp_path_factory.mktemp("clrnet") / "culane_r18.pth")


def _ours(experiment, *overrides):
    cfg = composed([f"experiment={experiment}", "data.root=/unused", *overrides])
    return build_model(model_config(cfg)).eval()


def assert_official_outputs(raw, official):
    """Our raw outputs (every stage) against the official predictions (B, stages, P, 6 + S)."""
    torch.testing.assert_close(raw["cls_logits"], official[..., :2], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(raw["lines"], official[..., 2:6], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(raw["xs"] / (W - 1), official[..., 6:], rtol=1e-4, atol=1e-4)


def test_the_converted_file_gives_the_official_outputs_at_every_stage(culane):
    official, path = culane
    model = _ours("official_clrnet_culane")
    line = load_detector_weights(model, path, "ckpt_path")
    assert "official CLRNet (Turoad/CLRNet) checkpoint (the culane release (or LLAMAS', of the same shapes), " \
           "resnet18: 192 priors, 72 points, 3 refinement stages, 36 sampled rows)" in line
    x = torch.rand(2, 3, H, W)
    with torch.no_grad():
        expected = official(x)
        raw = model(x)
    assert raw["xs"].shape == (2, STAGES, P, S)
    assert_official_outputs(raw, expected)
    # the refinement moved the lines (so the later stages sample elsewhere than the priors) and the scores vary
    assert (expected[:, -1, :, 6:] - official.heads.priors[:, 6:]).abs().max() > 0.01
    assert expected[..., 1].std() > 0.01
    # the evaluation's priors are the buffer's, not the (newer) embeddings'
    torch.testing.assert_close(model.head.prior_embeddings.detach(), official.heads.priors[:, 2:5])


def test_checkpoint_model_builds_the_configs_network_for_an_official_file(culane):
    official, path = culane
    cfg = composed(["task=evaluate", "experiment=official_clrnet_culane", "data.root=/unused", f"ckpt_path={path}"])
    model = checkpoint_model(cfg).eval()
    assert model.build_config["crop_top"] * 590 == pytest.approx(270, abs=1e-3)
    assert model.build_config["normalize"] == "clrnet"
    x = torch.rand(1, 3, H, W)
    with torch.no_grad():
        assert_official_outputs(model(x), official(x))


def test_release_and_backbone_are_recognised_from_keys_and_shapes(culane, tmp_path):
    official, path = culane
    state = official_state_dict(torch.load(path, weights_only=True))
    assert next(iter(state)).startswith("backbone.model.")  # 'module.' dropped
    release, found = recognise(state)
    assert release.family == "clrnet"
    assert found.config == "experiment=official_clrnet_culane backbone=resnet18"
    # TuSimple's decoder has 6 + 1 classes; a file without decoder (nor criterion) cannot tell its dataset
    tusimple = dict(state, **{"heads.seg_decoder.conv.weight": torch.zeros(7, C * STAGES, 1, 1),
                              "heads.seg_decoder.conv.bias": torch.zeros(7), "heads.criterion.weight": torch.ones(7)})
    assert recognise(tusimple)[1].config == "experiment=official_clrnet_tusimple backbone=resnet18"
    bare = {k: v for k, v in state.items() if not k.startswith(("heads.seg_decoder.", "heads.criterion."))}
    assert recognise(bare)[1].config == "experiment=official_clrnet_<tusimple|culane> backbone=resnet18"


def test_a_file_without_the_segmentation_decoder_loads_keeping_ours(culane, tmp_path):
    official, _ = culane
    path = save_official(official, tmp_path / "bare.pth", drop=("heads.seg_decoder.", "heads.criterion."))
    model = _ours("official_clrnet_tusimple")
    before = {k: v.clone() for k, v in model.state_dict().items() if k.startswith("head.seg_decoder.")}
    assert before["head.seg_decoder.1.weight"].shape[0] == 7  # 6 lane slots + background, as the official's
    load_detector_weights(model, path, "task.init_from")
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in before.items())
    x = torch.rand(1, 3, H, W)
    with torch.no_grad():
        assert_official_outputs(model(x), official(x))


def test_a_file_of_another_release_is_refused_naming_the_weight_and_the_config(culane):
    _, path = culane
    model = _ours("official_clrnet_tusimple")
    with pytest.raises(CheckpointError) as error:
        load_detector_weights(model, path, "ckpt_path")
    message = str(error.value)
    assert "head.seg_decoder.1.weight (5, 192, 1, 1) vs (7, 192, 1, 1)" in message
    assert "run it with experiment=official_clrnet_culane backbone=resnet18" in message


def test_a_file_of_another_family_is_refused_naming_the_config_that_fits(culane):
    _, path = culane
    cfg = composed(["task=evaluate", "experiment=official_ufld_tusimple", "data.root=/unused", f"ckpt_path={path}"])
    with pytest.raises(CheckpointError, match="an official CLRNet .* this run builds model=ufld; run it with "
                                              "experiment=official_clrnet_culane backbone=resnet18"):
        checkpoint_model(cfg)


@pytest.mark.parametrize("override", ["model.head.row_span=last_pixel", "data.input_size=[288,800]"])
def test_priors_drawn_for_another_input_or_row_span_are_refused_naming_the_settings(culane, override):
    _, path = culane
    model = _ours("official_clrnet_culane", override)
    with pytest.raises(CheckpointError, match=r"its priors' x \(heads.priors\[:, 6:\]\) are not those of its lines "
                                              r"for this run's .* give data.input_size=\[320, 800\] and "
                                              r"model.head.row_span=height"):
        load_detector_weights(model, path, "ckpt_path")


def test_another_backbone_is_refused_naming_the_files(culane):
    _, path = culane
    model = _ours("official_clrnet_culane", "backbone=resnet34")
    with pytest.raises(CheckpointError, match="weights .* missing .*backbone.layer1.2.*run it with "
                                              "experiment=official_clrnet_culane backbone=resnet18"):
        load_detector_weights(model, path, "ckpt_path")


def test_the_official_rows_hold_for_targets_priors_and_decoding():
    """With row_span=height (the official experiments') the rows lie at the official's y = H ... 0
    (generate_lane_line.py offsets_ys), and a straight lane's targets, the line through its (start_y, start_x,
    theta) and its decoded points agree on them, so fine-tuning trains what the official weights compute."""
    from lanevil_train.models.clrnet.head import CLRNetHead
    from lanevil_train.models.clrnet.priors import line_xs

    head = CLRNetHead([C] * 3, [8, 16, 32], (H, W), row_span="height").eval()
    rows = torch.linspace(H, 0, S).double().numpy()
    np.testing.assert_allclose(head.row_ys, rows, atol=1e-4)
    lane = np.array([[300.0, float(H)], [460.0, 0.0]])  # x = 300 + (H - y) / 2
    row = head.encode([lane])["lanes"][0]
    valid, start_y, start_x, theta, length = row[:5]
    assert (valid, start_y, length) == (1.0, 0.0, S) and start_x == pytest.approx(300.0)
    assert theta == pytest.approx(math.atan(2.0) / math.pi, abs=1e-5)  # the official's atan(i strip / dx)
    np.testing.assert_allclose(row[5:], 300.0 + (H - rows) / 2, atol=1e-3)
    line = torch.tensor([[start_y, start_x / (W - 1), theta]], dtype=torch.float64)
    xs = line_xs(line, head.fractions.double(), (H, W), head.row_span)[0].numpy() * (W - 1)
    np.testing.assert_allclose(xs, row[5:], atol=1e-2)
    cls = torch.tensor([5.0, -5.0]).repeat(1, STAGES, P, 1)
    cls[0, -1, 7] = torch.tensor([-5.0, 5.0])
    lines = torch.zeros(1, STAGES, P, 4)
    lines[0, -1, 7] = torch.tensor([0.0, start_x / (W - 1), theta, S / (S - 1)])  # 72 rows
    xs_raw = torch.zeros(1, STAGES, P, S)
    xs_raw[0, -1, 7] = torch.from_numpy(row[5:])
    (decoded,) = head.decode({"cls_logits": cls, "lines": lines, "xs": xs_raw})[0]
    np.testing.assert_allclose(decoded[:, 1], rows, atol=1e-4)  # y from H (the official's bottom row) to 0
    np.testing.assert_allclose(decoded[:, 0], 300.0 + (H - rows) / 2, atol=1e-3)


def test_a_dla34_file_loads_into_timms_dla34_its_unused_projections_dropped(tmp_path):
    """The CULane DLA-34 release: timm's dla34 keeps the official names and computes the same maps; the projections
    the official builds in its two-level trees (level3, level4) and never uses are not in it."""
    torch.manual_seed(2)
    official = randomised(OfficialCLRNet(classes=5, backbone="dla34"))
    assert "backbone.model.level3.project.0.weight" in official.state_dict()
    path = save_official(official, tmp_path / "culane_dla34.pth")
    state = official_state_dict(torch.load(path, weights_only=True))
    assert recognise(state)[1].config == "experiment=official_clrnet_culane backbone=dla34"
    model = _ours("official_clrnet_culane", "backbone=dla34")
    assert "backbone.level3.project.0.weight" not in model.state_dict()
    assert "backbone.level3.tree1.project.0.weight" in model.state_dict()
    line = load_detector_weights(model, path, "ckpt_path")
    assert "the culane release (or LLAMAS', of the same shapes), dla34" in line
    x = torch.rand(1, 3, H, W)
    with torch.no_grad():
        assert_official_outputs(model(x), official(x))


def official_points(pred, ori_h, ori_w, cut):
    """predictions_to_pred (clr_head.py l. 279-319) for one kept prediction (6 + S values, its length already
    rounded to rows, l. 477): its points (x, y) in the original image, bottom first, x as its writers scale it
    (x / (W-1) times ori_img_w: lane.py l. 35-36, tusimple.py l. 67-69)."""
    xs = pred[6:].astype(np.float64).copy()
    ys = np.linspace(1.0, 0.0, S)
    start = min(max(0, int(round(pred[2] * (S - 1)))), S - 1)
    end = min(start + int(round(pred[5])) - 1, S - 1)
    below = ((xs[:start] >= 0) & (xs[:start] <= 1))[::-1].cumprod()[::-1].astype(bool)  # extended while inside
    xs[:start][~below] = -2
    xs[end + 1:] = -2
    keep = xs >= 0
    return np.stack([xs[keep] * ori_w, ys[keep] * (ori_h - cut) + cut], axis=1)


@pytest.mark.parametrize("case", ["bottom", "side_extended", "leaves_right"])
def test_decoding_keeps_the_official_points_at_its_rows(case):
    """A constructed output with one confident lane, decoded by our detector into the 1640x590 CULane image
    (experiment=official_clrnet_culane: lane_points official): the official formula's points, rows and x, the points
    right of the image included."""
    model = _ours("official_clrnet_culane")
    ori_h, ori_w, cut = 590, 1640, 270
    fractions = np.linspace(0.0, 1.0, S)
    start_y, start_x, theta, rows = {"bottom": (0.0, 0.45, 0.4, 60), "side_extended": (0.3, 0.05, 0.3, 30),
                                     "leaves_right": (0.0, 0.7, 0.2, 60)}[case]
    xs = start_x + (fractions - start_y) * H / math.tan(theta * math.pi) / (W - 1)  # the prior line, x / (W-1)
    xs = xs + 0.01 * np.sin(np.arange(S))  # plus offsets
    cls = torch.tensor([5.0, -5.0]).repeat(1, STAGES, P, 1)
    cls[0, -1, 11] = torch.tensor([-5.0, 5.0])
    lines = torch.zeros(1, STAGES, P, 4)
    lines[0, -1, 11] = torch.tensor([start_y, start_x, theta, rows / (S - 1)])
    raw_xs = torch.zeros(1, STAGES, P, S)
    raw_xs[0, -1, 11] = torch.tensor(xs * (W - 1), dtype=torch.float32)
    (lane,) = model.decode_lanes({"cls_logits": cls, "lines": lines, "xs": raw_xs}, (H, W), [(ori_h, ori_w)])[0]
    official = official_points(np.concatenate([[0.0, 0.0, start_y, start_x, theta, rows], xs]), ori_h, ori_w, cut)
    np.testing.assert_allclose(lane, official, atol=1e-3)
    if case == "side_extended":
        assert official[0, 1] > ori_h - start_y * (ori_h - cut) + 1  # extended below its start while inside
    if case == "leaves_right":
        assert lane[:, 0].max() > ori_w  # the official keeps points past the right edge, and so do we


def test_task_evaluate_scores_an_official_file_on_a_culane_folder(culane, tmp_path):
    """`python -m lanevil_train task=evaluate experiment=official_clrnet_culane ckpt_path=culane_r18.pth
    data.root=R`, in this process: the config check passes, the file is converted, the images scored and the
    prediction files written."""
    from lanevil_train.data.formats import write_culane
    from tests.tasks.cli_helpers import run_in_process, write_photo_dataset

    _, path = culane
    root = tmp_path / "culane"
    names = [f"driver_00_01frame/05151640_0419.MP4/{i:05d}.jpg" for i in range(2)]
    write_culane(write_photo_dataset(root, names), root, root / "list" / "test.txt")
    run_dir = tmp_path / "run"
    run_in_process(["task=evaluate", "experiment=official_clrnet_culane", f"data.root={root}", f"ckpt_path={path}",
                    "trainer=cpu", "progress=none", "data.num_workers=0", "data.batch_size=2",
                    "task.predictions=true"], run_dir)
    assert (run_dir / "test_scores.json").is_file()
    listed = (run_dir / "predictions" / "culane" / "list.txt").read_text().split()
    assert listed == ["/" + name for name in names]
