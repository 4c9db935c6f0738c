"""The published GANet files (Wolfwjs/GANet) load as its code saved them: the official network (written here from the
facts in models/ganet/official.py: mmdet's ResNet as `backbone`, the DeformFPN `neck` with its attention on C5, its
laterals and its lane-aware feature aggregator, a `LanePointsConv` whose deformable 1-D convolution is
torchvision's deform_conv2d, the GANetHeadFast `bbox_head`) and ours, given the converted file, compute the same
keypoint heatmap, start-point offsets, errors and LFA points; the official decoding (written here from the facts)
and ours find the same lanes; files of another release, family or network are refused naming the config that
fits, or why none does."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torchvision
from torch import nn
from torch.nn import functional as F

from lanevil_train.checkpoints import CheckpointError
from lanevil_train.models.official import is_ours, load_detector_weights, official_state_dict, recognise
from lanevil_train.tasks.builders import build_model, checkpoint_model, model_config
from tests.models.official_layouts import ConvModule, randomise_batch_norm, ufld_culane_file_keys
from tests.tasks.cli_helpers import composed

SMALL = (64, 160)  # a small input: C3 8 x 20 (the heatmap), C5 2 x 5 (the attention's 10 positions)
SMALL_S4 = (32, 96)  # the stride-4 release's: a 8 x 24 heatmap, C5 1 x 3
SMALL_SIZE = f"data.input_size=[{SMALL[0]},{SMALL[1]}]"


def official_position_embedding(dim, height, width):
    """The sine embedding (1, dim, h, w): n = dim / 2 features per axis, positions 1..h and 1..w, frequency
    10000^(2 (i // 2) / n), sin on even and cos on odd features, y's then x's (dcn_fpn.py l. 20-71)."""
    n = dim // 2
    ones = torch.ones(1, height, width)
    y, x = ones.cumsum(1), ones.cumsum(2)
    i = torch.arange(n, dtype=torch.float32)
    freq = 10000.0 ** (2 * torch.div(i, 2, rounding_mode="floor") / n)

    def encode(p):
        angle = p[..., None] / freq
        return torch.stack((angle[..., 0::2].sin(), angle[..., 1::2].cos()), dim=4).flatten(3)

    return torch.cat((encode(y), encode(x)), dim=3).permute(0, 3, 1, 2)


class OfficialAttentionLayer(nn.Module):
    """AttentionLayer (dcn_fpn.py l. 74-132)."""

    def __init__(self, cin, cout, ratio=4):
        super().__init__()
        self.pre_conv = ConvModule(cin, cout, 3, padding=1, norm=True, act=True)
        self.query_conv = nn.Conv2d(cout, cout // ratio, 1)
        self.key_conv = nn.Conv2d(cout, cout // ratio, 1)
        self.value_conv = nn.Conv2d(cout, cout, 1)
        self.final_conv = ConvModule(cout, cout, 3, padding=1, norm=True, act=True)
        self.gamma = nn.Parameter(torch.zeros(1))

    def forward(self, x, pos):
        x = self.pre_conv(x) + pos
        b, c, h, w = x.shape
        energy = torch.einsum("bcn,bcm->bnm", self.query_conv(x).flatten(2), self.key_conv(x).flatten(2))
        attention = energy.softmax(dim=-1)  # (b, query, key)
        out = torch.einsum("bcm,bnm->bcn", self.value_conv(x).flatten(2), attention).reshape(b, c, h, w)
        return self.final_conv(self.gamma * out + x)


class OfficialDeformConv1D(nn.Module):
    """DeformConv1D (mmdet/ops/dcn/deform_conv.py l. 255-317): kernel (1, K), padding (0, (K - 1) / 2), no bias;
    mmcv's deformable convolution, here torchvision's (the same offsets layout: (dy, dx) per tap)."""

    def __init__(self, cin, cout, taps):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(cout, cin, 1, taps))
        self.pad = (taps - 1) // 2

    def forward(self, x, offset):
        return torchvision.ops.deform_conv2d(x, offset, self.weight, padding=(0, self.pad))


class OfficialLanePointsConv(nn.Module):
    """LanePointsConv (lanepoints_conv.py l. 37-177) with in 64, feat 256, point_feat 64, 3 stacked convs."""

    def __init__(self, channels, taps, feat=256):
        super().__init__()
        def convs():
            return nn.ModuleList(ConvModule(channels if i == 0 else feat, feat, 3, padding=1, act=True)
                                 for i in range(3))

        self.cls_convs, self.reg_convs = convs(), convs()
        self.reppoints_cls_conv = OfficialDeformConv1D(feat, channels, taps)
        self.reppoints_pts_init_conv = nn.Conv2d(feat, channels, 3, padding=1)
        self.reppoints_pts_init_out = nn.Conv2d(channels, 2 * taps, 1)
        self.reppoints_pts_refine_conv = OfficialDeformConv1D(feat, channels, taps)  # built, never run
        self.reppoints_pts_refine_out = nn.Conv2d(channels, 2 * taps, 1)
        p = (taps - 1) // 2
        base = torch.stack([torch.zeros(taps), torch.arange(-p, p + 1, dtype=torch.float32)], dim=1)  # (y, x)
        self.dcn_base_offset = base.reshape(1, -1, 1, 1)  # a plain attribute: not in the file

    def forward(self, x):
        cls_feat, pts_feat = x, x
        for conv in self.cls_convs:
            cls_feat = conv(cls_feat)
        for conv in self.reg_convs:
            pts_feat = conv(pts_feat)
        pts_out_init = self.reppoints_pts_init_out(F.relu(self.reppoints_pts_init_conv(pts_feat)))
        features = F.relu(self.reppoints_cls_conv(cls_feat, pts_out_init - self.dcn_base_offset))
        return features, pts_out_init


class OfficialTransHead(nn.Module):
    """TransConvEncoderModule (l. 135-168): `attn_layers`, each given its position embedding."""

    def __init__(self, in_dims, out_dims):
        super().__init__()
        self.attn_layers = nn.ModuleList(OfficialAttentionLayer(i, o) for i, o in zip(in_dims, out_dims))

    def forward(self, x):
        for layer in self.attn_layers:
            dim = layer.value_conv.out_channels
            x = layer(x, official_position_embedding(dim, *x.shape[-2:]))  # the official: (1, 10, 25) at 320x800
        return x


class OfficialDeformFPN(nn.Module):
    """DeformFPN (dcn_fpn.py l. 216-378) at the releases' settings: trans_idx -1 replacing the last map,
    deconv_layer [True, False, ...], deconv_before False, dcn_only_cls True."""

    def __init__(self, in_channels, taps, attn_in, attn_out, out=64):
        super().__init__()
        self.num_ins = len(in_channels)
        self.trans_head = OfficialTransHead(attn_in, attn_out)
        in_channels = [*in_channels[:-1], attn_out[-1]]
        self.lateral_convs = nn.ModuleList(ConvModule(c, out, 1) for c in in_channels)
        self.def_convs = nn.ModuleList(OfficialLanePointsConv(out, taps - 2 * i) for i in range(len(in_channels)))
        self.fpn_convs = nn.ModuleList(ConvModule(out, out, 3, padding=1) for _ in in_channels)

    def forward(self, inputs):
        inputs = list(inputs)[-self.num_ins:]  # C2 dropped when there are more maps than in_channels
        inputs[-1] = self.trans_head(inputs[-1])
        laterals = [conv(x) for conv, x in zip(self.lateral_convs, inputs)]
        points = None
        for i in range(len(laterals) - 1, 0, -1):
            laterals[i - 1] = laterals[i - 1] + F.interpolate(laterals[i], size=laterals[i - 1].shape[2:],
                                                              mode="nearest")
            if i - 1 == 0:
                aux_feat = laterals[0]
                laterals[0], points = self.def_convs[0](laterals[0])
        outs = [conv(x) for conv, x in zip(self.fpn_convs, laterals)]
        return {"features": tuple(outs), "aux_feat": aux_feat, "deform_points": points}


class OfficialBranches(nn.Module):
    """CtnetHead (ctnet_head.py l. 36-58): an attribute named by its output, conv 3x3, ReLU, conv 1x1."""

    def __init__(self, name, classes, channels=64):
        super().__init__()
        self.name = name
        setattr(self, name, nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU(),
                                          nn.Conv2d(channels, classes, 1)))

    def forward(self, x):
        return getattr(self, self.name)(x)


class OfficialGANetHead(nn.Module):
    """GANetHeadFast (ganet_head.py l. 79-126, forward_train l. 240-263)."""

    def __init__(self):
        super().__init__()
        self.centerpts_head = OfficialBranches("hm", 1)
        self.keypts_head = OfficialBranches("hm", 1)
        self.offset_head = OfficialBranches("offset_map", 2)
        self.reg_head = OfficialBranches("offset_map", 2)

    def forward(self, features, aux_feat):
        return [self.centerpts_head(features[0]), self.keypts_head(features[0]), self.offset_head(aux_feat),
                self.reg_head(aux_feat)]


class OfficialGANet(nn.Module):
    """The GANet detector (detectors/ganet.py): `backbone` (mmdet's ResNet, style pytorch: torchvision's layers and
    names, no fc; C2..C5), `neck`, `bbox_head`."""

    def __init__(self, depth=18, stride=None):
        super().__init__()
        self.backbone = getattr(torchvision.models, f"resnet{depth}")()
        del self.backbone.fc
        channels = [64, 128, 256, 512] if depth < 50 else [256, 512, 1024, 2048]
        if (stride or (4 if depth == 101 else 8)) == 4:  # final_exp_res101_s4.py's neck (C2..C5)
            self.neck = OfficialDeformFPN(channels, 9, [channels[-1], 256], [256, 256])
        else:  # final_exp_res{18,34}_s8.py's (C3..C5)
            self.neck = OfficialDeformFPN(channels[1:], 7, [channels[-1], 64], [64, 64])
        self.bbox_head = OfficialGANetHead()
        _away_from_init(self)

    def forward(self, x):
        """kpts_hm (after the test's sigmoid and clamp), pts_offset, int_offset, the LFA's pts_out_init."""
        b = self.backbone
        x = b.maxpool(b.relu(b.bn1(b.conv1(x))))
        maps = []
        for layer in (b.layer1, b.layer2, b.layer3, b.layer4):
            x = layer(x)
            maps.append(x)
        neck = self.neck(maps)
        _, kpts_hm, pts_offset, int_offset = self.bbox_head(neck["features"], neck["aux_feat"])
        kpts_hm = torch.clamp(kpts_hm.sigmoid(), min=1e-4, max=1 - 1e-4)  # ganet_head.py l. 291
        return {"kpts_hm": kpts_hm, "pts_offset": pts_offset, "int_offset": int_offset,
                "deform_points": neck["deform_points"]}


def _away_from_init(net):
    """Random weights of another law than either network's initialisation, at scales that keep the activations of
    order one; BN statistics too, gamma non-zero (it starts at 0), so a weight or buffer left unloaded shows."""
    for name, m in net.named_modules():
        if isinstance(m, (nn.Conv2d, OfficialDeformConv1D)):
            w = m.weight
            fan_in = w.shape[1] * w.shape[2] * w.shape[3]
            gain = 0.3 if name.startswith("backbone.") else 1.0  # residual sums would grow with the depth
            nn.init.normal_(w, 0.0, gain * math.sqrt(2.0 / fan_in))
            if getattr(m, "bias", None) is not None:
                nn.init.normal_(m.bias, 0.0, 0.1)
        elif isinstance(m, nn.BatchNorm2d):
            randomise_batch_norm(m)
        elif isinstance(m, OfficialAttentionLayer):
            nn.init.uniform_(m.gamma, 0.5, 1.5)
    for lfa in net.neck.def_convs:  # points a few cells from their location, some off the map
        nn.init.normal_(lfa.reppoints_pts_init_out.weight, 0.0, 0.5 / math.sqrt(lfa.reppoints_pts_init_out.in_channels))
        nn.init.normal_(lfa.reppoints_pts_init_out.bias, 0.0, 1.5)


def _save_mmcv(path, net, config="dataset_type = 'CulaneDataset'"):
    """As mmcv 0.5.6's runner saves it: {'meta', 'state_dict', 'optimizer'} (no 'module.' prefix)."""
    torch.save({"meta": {"mmdet_version": "2.0.0", "config": config, "CLASSES": None, "epoch": 60, "iter": 1000,
                         "mmcv_version": "0.5.6", "time": "Sun Apr 24 12:00:00 2022"},
                "state_dict": net.state_dict(),
                "optimizer": {"state": {}, "param_groups": [{"lr": 1e-3, "betas": (0.9, 0.999), "eps": 1e-8,
                                                             "weight_decay": 0, "amsgrad": False, "params": [0, 1]}]}},
               path)
    return path


def _ours(experiment, *overrides):
    cfg = composed([f"experiment={experiment}", "data.root=/unused", *overrides])
    return build_model(model_config(cfg)).eval()


def _compare(model, official, x):
    """Our raw outputs (and LFA points) against the official network's on x."""
    with torch.no_grad():
        expected = official(x)
        got = model(x)
        lfa = model.head.neck(model.backbone(x), model.head.fmap_size)["points"]
    assert got["heatmap"].shape == expected["kpts_hm"].shape
    for value in (expected["pts_offset"], expected["int_offset"], expected["deform_points"]):
        assert value.abs().mean() > 0.1  # outputs that say something
    assert 0.05 < expected["kpts_hm"].mean() < 0.95
    # ours has no clamp: the official's [1e-4, 1 - 1e-4] moves values by less than the tolerance
    torch.testing.assert_close(got["heatmap"], expected["kpts_hm"], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(got["offsets"], expected["pts_offset"], rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(got["error"], expected["int_offset"], rtol=1e-4, atol=1e-4)
    b, k2, h, w = lfa.shape  # ours (dx, dy) per point, the official's (dy, dx)
    torch.testing.assert_close(lfa, expected["deform_points"].reshape(b, k2 // 2, 2, h, w).flip(2).reshape(b, k2, h, w),
                               rtol=1e-4, atol=1e-4)


@pytest.fixture(scope="module")
def small_file(tmp_path_factory):
    """A ResNet-18 file (the Small release's shapes) in mmcv's layout."""
    torch.manual_seed(0)
    net = OfficialGANet(18).eval()
    return net, _save_mmcv(tmp_path_factory.mktemp("ganet") / "ganet_culane_resnet18.pth", net)


def test_an_mmcv_file_is_read_the_official_way(small_file):
    official, path = small_file
    obj = torch.load(path, weights_only=True)
    assert {"meta", "state_dict", "optimizer"} == obj.keys() and not is_ours(obj)
    state = official_state_dict(obj)
    assert state.keys() == official.state_dict().keys()
    release, found = recognise(state)
    assert release.family == "ganet"
    assert found.what == ("the Small release (resnet18: a stride-8 heatmap from 3 levels, an LFA of 7 points, 2 "
                          "attention layers of 64 channels; TuSimple and CULane files alike)")
    assert found.config == "experiment=official_ganet_<tusimple|culane> backbone=resnet18"


def test_the_converted_file_gives_the_official_networks_outputs(small_file):
    official, path = small_file
    model = _ours("official_ganet_culane", SMALL_SIZE)
    line = load_detector_weights(model, path, "task.init_from")
    assert "official GANet (Wolfwjs/GANet) checkpoint (the Small release (resnet18" in line
    _compare(model, official, torch.randn(2, 3, *SMALL))


def test_checkpoint_model_builds_the_tusimple_configs_network_for_the_same_file(small_file):
    official, path = small_file  # the two datasets' files have the same shapes
    cfg = composed(["task=evaluate", "experiment=official_ganet_tusimple", "data.root=/unused", f"ckpt_path={path}",
                    SMALL_SIZE])
    _compare(checkpoint_model(cfg).eval(), official, torch.randn(1, 3, *SMALL))


def test_the_large_release_is_recognised_from_its_shapes():
    with torch.device("meta"):  # shapes only
        state = OfficialGANet(101).state_dict()
    release, found = recognise(state)
    assert release.family == "ganet"
    assert found.what == ("the Large release (resnet101: a stride-4 heatmap from 4 levels, an LFA of 9 points, 2 "
                          "attention layers of 256 channels; TuSimple and CULane files alike)")
    assert found.config == "experiment=official_ganet_large_<tusimple|culane> backbone=resnet101"


def test_the_large_releases_neck_on_another_backbone_loads_with_the_settings_it_names(tmp_path):
    """The stride-4 network (C2..C5, attention of 256 channels before a 64-channel lateral, an LFA of 9 points) on
    a ResNet-18: an unpublished setting, built by the settings its description names."""
    torch.manual_seed(2)
    official = OfficialGANet(18, stride=4).eval()
    path = _save_mmcv(tmp_path / "ganet_s4_resnet18.pth", official)
    found = recognise(official_state_dict(torch.load(path, weights_only=True)))[1]
    assert found.config == ("experiment=official_ganet_<tusimple|culane> backbone=resnet18 "
                            "model.feature_strides=[4,8,16,32] model.head.lfa_points=9 model.head.fpn_channels=64 "
                            "model.head.attention_layers=2 model.head.attention_channels=256")
    experiment, *settings = found.config.replace("<tusimple|culane>", "culane").split()
    model = _ours(experiment.split("=", 1)[1], *settings, f"data.input_size=[{SMALL_S4[0]},{SMALL_S4[1]}]")
    load_detector_weights(model, path, "ckpt_path")
    assert model.head.stride == 4
    _compare(model, official, torch.randn(1, 3, *SMALL_S4))


@pytest.mark.slow
def test_the_large_release_loads_into_its_config_and_gives_the_official_outputs(tmp_path):
    """ResNet-101, C2..C5, the stride-4 heatmap, attention of 256 channels, an LFA of 9 points (a 170 MB file:
    seconds to build, save and load)."""
    torch.manual_seed(1)
    official = OfficialGANet(101).eval()
    path = _save_mmcv(tmp_path / "ganet_tusimple_resnet101.pth", official)
    model = _ours("official_ganet_large_tusimple", f"data.input_size=[{SMALL_S4[0]},{SMALL_S4[1]}]")
    line = load_detector_weights(model, path, "ckpt_path")
    assert "(the Large release (resnet101" in line
    _compare(model, official, torch.randn(1, 3, *SMALL_S4))


def test_the_medium_release_is_recognised_and_loads_into_the_config_it_names(tmp_path):
    official = OfficialGANet(34)
    path = _save_mmcv(tmp_path / "ganet_tusimple_resnet34.pth", official)
    release, found = recognise(official_state_dict(torch.load(path, weights_only=True)))
    assert found.what.startswith("the Medium release (resnet34: a stride-8 heatmap")
    assert found.config == "experiment=official_ganet_<tusimple|culane> backbone=resnet34"
    model = _ours("official_ganet_tusimple", "backbone=resnet34", SMALL_SIZE)
    load_detector_weights(model, path, "ckpt_path")
    torch.testing.assert_close(model.head.neck.lfa.point_convs[4].bias,
                               official.neck.def_convs[0].reg_convs[2].conv.bias, rtol=0, atol=0)
    torch.testing.assert_close(model.backbone.layer3[5].bn2.running_var,
                               official.backbone.layer3[5].bn2.running_var, rtol=0, atol=0)


def test_a_file_of_another_release_is_refused_naming_the_weight_and_the_config(small_file):
    _, path = small_file  # the Small file with the Large release's config (on its backbone)
    model = _ours("official_ganet_large_culane", "backbone=resnet18", SMALL_SIZE)
    with pytest.raises(CheckpointError) as error:
        load_detector_weights(model, path, "ckpt_path")
    message = str(error.value)
    assert "missing (first: head.neck.lateral.3.weight" in message
    assert "of another shape (first: head.neck.attention.0.pre.0.weight (64, 512, 3, 3) vs (256, 512, 3, 3)" in message
    assert "run it with experiment=official_ganet_<tusimple|culane> backbone=resnet18" in message


def test_a_file_of_another_backbone_is_refused_naming_the_config(tmp_path):
    path = _save_mmcv(tmp_path / "ganet_culane_resnet34.pth", OfficialGANet(34))
    model = _ours("official_ganet_culane", SMALL_SIZE)  # backbone=resnet18
    with pytest.raises(CheckpointError, match=r"unexpected \(first: backbone.layer1.2.conv1.weight.*run it with "
                                              r"experiment=official_ganet_<tusimple\|culane> backbone=resnet34"):
        load_detector_weights(model, path, "ckpt_path")


def test_a_ganet_file_with_a_ufld_config_is_refused_naming_the_ganet_config(small_file):
    _, path = small_file
    cfg = composed(["task=evaluate", "experiment=official_ufld_culane", "data.root=/unused", f"ckpt_path={path}"])
    with pytest.raises(CheckpointError, match=r"an official GANet .* this run builds model=ufld; run it with "
                                              r"experiment=official_ganet_<tusimple\|culane> backbone=resnet18"):
        checkpoint_model(cfg)


def test_a_ufld_file_with_the_ganet_config_is_refused_naming_the_ufld_config(tmp_path):
    torch.save({"model": ufld_culane_file_keys()}, tmp_path / "culane_18.pth")
    cfg = composed(["task=evaluate", "experiment=official_ganet_culane", "data.root=/unused",
                    f"ckpt_path={tmp_path / 'culane_18.pth'}", SMALL_SIZE])
    with pytest.raises(CheckpointError, match="an official UFLD v1 .* this run builds model=ganet; run it with "
                                              "experiment=official_ufld_culane backbone=resnet18"):
        checkpoint_model(cfg)


@pytest.mark.parametrize("change, why", [
    ("joints", "it regresses offsets to 4 joints per keypoint (joint_nums=4), this project's head to the start "
               "point only"),
    ("upsample", "its head upsamples the features first (upsample_module)"),
])
def test_a_file_of_a_network_no_config_computes_is_refused_saying_why(small_file, tmp_path, change, why):
    official, _ = small_file
    state = dict(official.state_dict())
    if change == "joints":  # joint_nums=4: offset_map to 8 channels
        state["bbox_head.offset_head.offset_map.2.weight"] = torch.zeros(8, 64, 1, 1)
        state["bbox_head.offset_head.offset_map.2.bias"] = torch.zeros(8)
    else:  # upsample_num=1: UpSampleLayer's Conv_BN_ReLU_2
        state["bbox_head.upsample_module.0.Conv_BN_ReLU_2.0.weight"] = torch.zeros(64, 64, 3, 3)
    torch.save({"meta": {}, "state_dict": state}, tmp_path / "other.pth")
    model = _ours("official_ganet_culane", SMALL_SIZE)
    with pytest.raises(CheckpointError) as error:
        load_detector_weights(model, tmp_path / "other.pth", "ckpt_path")
    message = str(error.value)
    assert "an official GANet (Wolfwjs/GANet) checkpoint (a GANet resnet18: a stride-8 heatmap" in message
    assert "that this project cannot load: " + why in message


def test_an_unpublished_setting_names_the_settings_that_build_it(small_file):
    official, _ = small_file
    state = {k: v for k, v in official.state_dict().items() if not k.startswith("neck.trans_head.")}
    found = recognise(state)[1]
    assert found.what.startswith("an unpublished setting, resnet18: a stride-8 heatmap from 3 levels, an LFA of 7 "
                                 "points, no attention")
    assert found.config == ("experiment=official_ganet_<tusimple|culane> backbone=resnet18 "
                            "model.feature_strides=[8,16,32] model.head.lfa_points=7 model.head.fpn_channels=64 "
                            "model.head.top_attention=false")


# ---------------------------------------------------------------------------------------------------- decoding
def official_decode(kpts_hm, pts_offset, int_offset, kpt_thr, root_thr, by_center_thr, points_thr, downscale,
                    crop_bbox, img_shape):
    """The official test decoding for one image (ganet_head.py ktdet_decode_fast l. 203-238, post_process.py
    group_points_fast by centre l. 141-194 and lane_post_process l. 216-242, test_dataset.py adjust_result): lanes
    as lists of (x, y) integer points of the original image."""
    heat = kpts_hm * (F.max_pool2d(kpts_hm, (1, 3), stride=1, padding=(0, 1)) == kpts_hm).float()
    # start candidates: cells above kpt_thr whose y offset is below root_thr, (x, y), ordered by x then y
    candidate = ((pts_offset[:, 1:2] < root_thr) & (heat > kpt_thr))[0, 0].T.numpy()
    centres_xy = np.array(np.where(candidate), dtype=int).T
    # keypoints row-major: align = cell + error, root = cell + offset
    ys, xs = np.where(heat[0, 0].numpy() > kpt_thr)
    align = np.stack([xs + int_offset[0, 0].numpy()[ys, xs], ys + int_offset[0, 1].numpy()[ys, xs]], axis=1)
    root = np.stack([xs + pts_offset[0, 0].numpy()[ys, xs], ys + pts_offset[0, 1].numpy()[ys, xs]], axis=1)

    def close(p, q):
        return math.hypot(p[0] - q[0], p[1] - q[1]) <= by_center_thr

    clusters = []
    for c in centres_xy:  # a candidate joins the first cluster with a member close to it
        home = next((cluster for cluster in clusters if any(close(c, m) for m in cluster)), None)
        if home is None:
            clusters.append([c])
        else:
            home.append(c)
    centres = [np.mean(np.array(cluster).reshape(-1, 2), axis=0, dtype=int) for cluster in clusters]
    groups = [[] for _ in centres]
    for a, r in zip(align, root):  # a keypoint joins the first centre close to its root
        k = next((k for k, centre in enumerate(centres) if close(r, centre)), None)
        if k is not None:
            groups[k].append(a)
    h_img, w_img = img_shape
    ratio_x, ratio_y = (crop_bbox[2] - crop_bbox[0]) / w_img, (crop_bbox[3] - crop_bbox[1]) / h_img
    lanes = []
    for group in groups:
        if len(group) <= 1:
            continue
        points = [(int(x * downscale * ratio_x + crop_bbox[0]), int(y * downscale * ratio_y + crop_bbox[1]))
                  for x, y in group]
        if len(points) > points_thr:
            lanes.append(points)
    return lanes


def _constructed_output(h=40, w=100):
    """Heatmap, start offsets and errors (stride 8, 320x800) of three lanes (bottom x 20, 50, 80 cells, leaning
    apart), a lane of six points (too short for either config), a point of no lane and a weak peak (0.35) on a lane:
    keypoints 0.9 with 0.5 either side in their row, sub-cell errors, offsets from each keypoint (cell + error)
    to its lane's lowest one."""
    heat = np.full((1, 1, h, w), 0.01, np.float32)
    offsets = np.zeros((1, 2, h, w), np.float32)
    error = np.zeros((1, 2, h, w), np.float32)
    lanes = [(20.3, 0.45, 15), (50.6, 0.0, 12), (80.1, -0.55, 18), (5.5, 0.2, 34)]  # x at the bottom, dx per row up,
    for x0, slope, top in lanes:  # its top row
        rows = range(h - 1, top - 1, -1)
        points = [(x0 + slope * (h - 1 - y), y + 0.25) for y in rows]
        start = points[0]
        for x, y in points:
            cx, cy = int(x), int(y)
            heat[0, 0, cy, cx] = 0.9
            heat[0, 0, cy, [cx - 1, cx + 1]] = 0.5
            error[0, :, cy, cx] = (x - cx, y - cy)
            offsets[0, :, cy, cx] = (start[0] - x, start[1] - y)
    heat[0, 0, 30, [49, 50, 51]] = (0.2, 0.35, 0.2)  # weak: kept at kpt_thr 0.3, not at 0.4
    heat[0, 0, 5, 40] = 0.9  # no lane: its start lies far from every centre
    offsets[0, :, 5, 40] = (-30.0, 20.0)
    return {"heatmap": torch.tensor(heat), "offsets": torch.tensor(offsets), "error": torch.tensor(error)}


@pytest.mark.parametrize("experiment, crop_bbox, img_shape, kpt_thr, by_center_thr, points_thr", [
    ("official_ganet_culane", (0, 270, 1640, 590), (590, 1640), 0.4, 5, 10),  # configs/culane/test_common_s8.py
    ("official_ganet_tusimple", (0, 160, 1280, 720), (720, 1280), 0.3, 4, 7),  # configs/tusimple/test_common_s8.py
])
def test_decoding_finds_the_official_lanes_within_a_pixel(experiment, crop_bbox, img_shape, kpt_thr, by_center_thr,
                                                          points_thr):
    """Ours (the config's decode settings) against the official decoding on the constructed output: the same lanes
    with the same keypoints, each within 1 px of the official's in the original image (the official truncates to
    integer pixels; its keypoint roots leave out the sub-cell error, its candidates' centres are their cells: less
    than 1.5 cells apart from ours, well inside the clustering distance here)."""
    model = _ours(experiment)
    raw = _constructed_output()
    theirs = official_decode(raw["heatmap"], raw["offsets"], raw["error"], kpt_thr, 1.0, by_center_thr, points_thr,
                             8, crop_bbox, (320, 800))
    ours = model.decode_lanes(raw, (320, 800), [img_shape])[0]
    assert len(ours) == len(theirs) == 3
    for mine, official in zip(ours, sorted(theirs, key=lambda lane: max(lane, key=lambda p: p[1])[0])):
        official = np.array(sorted(official, key=lambda p: p[1]), dtype=np.float64)
        mine = mine[np.argsort(mine[:, 1])]
        assert len(mine) == len(official)
        assert np.all(mine - official > -1e-3) and np.all(mine - official < 1.0 + 1e-3)


@pytest.mark.slow
def test_checkpoint_model_at_the_release_size_gives_the_official_outputs(small_file):
    """The release's 320x800 input (C5 10 x 25: the official position table's size) through the config the file
    names (seconds on a CPU)."""
    official, path = small_file
    cfg = composed(["task=evaluate", "experiment=official_ganet_culane", "data.root=/unused", f"ckpt_path={path}"])
    _compare(checkpoint_model(cfg).eval(), official, torch.randn(1, 3, 320, 800))


def test_task_evaluate_scores_an_official_file_on_a_culane_folder(small_file, tmp_path):
    """`python -m lanevil_train task=evaluate experiment=official_ganet_culane ckpt_path=ganet_culane_resnet18.pth
    data.root=R` (at the small input), in this process: the config check passes, the file is converted, the images
    scored and the prediction files written."""
    from lanevil_train.data.formats import write_culane
    from tests.tasks.cli_helpers import run_in_process, write_photo_dataset

    _, path = small_file
    root = tmp_path / "culane"
    names = [f"driver_00_01frame/05151640_0419.MP4/{i:05d}.jpg" for i in range(2)]
    write_culane(write_photo_dataset(root, names), root, root / "list" / "test.txt")
    run_dir = tmp_path / "run"
    run_in_process(["task=evaluate", "experiment=official_ganet_culane", f"data.root={root}", f"ckpt_path={path}",
                    SMALL_SIZE, "trainer=cpu", "progress=none", "data.num_workers=0", "task.predictions=true"],
                   run_dir)
    assert (run_dir / "test_scores.json").is_file()
    listed = (run_dir / "predictions" / "culane" / "list.txt").read_text().split()
    assert listed == ["/" + name for name in names]
