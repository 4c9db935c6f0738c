"""The published SCNN files of pytorch-auto-drive load as its code saved them: the official network (written here from
the facts in models/scnn/official.py: DeepLabV1 with the dilated vgg16_bn as `encoder.net`, `fc67`, the SpatialConv
`scnn`, `fc8`, the SimpleLaneExist `lane_classifier`) and ours, given the converted file, compute the same outputs;
files of another release, family or network are refused naming the config that fits, or why none does."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torchvision
from torch import nn
from torch.nn import functional as F

from lanevil_train.checkpoints import CheckpointError
from lanevil_train.models.official import load_detector_weights, official_state_dict, recognise
from lanevil_train.tasks.builders import build_model, checkpoint_model, model_config
from tests.models.official_layouts import randomise_batch_norm, ufld_culane_file_keys
from tests.models.test_official_decoding_scnn import official_points
from tests.tasks.cli_helpers import composed

SMALL = (64, 160)  # a small input for the forward checks: a stride-8 map of 8 x 20, 5 x 4 x 10 = 200 exist inputs
VGG16 = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]


def official_vgg16_net() -> nn.Sequential:
    """vgg_encoder.py VGG16's `net`: vgg16_bn's features (conv with bias, BN, ReLU per conv; max-pools) with conv5
    (indices 34, 37, 40) dilated by 2 and the pools at 33 and 43 removed, the other indices kept."""
    layers, cin = [], 3
    for v in VGG16:
        if v == "M":
            layers.append(nn.MaxPool2d(2, 2))
            continue
        layers += [nn.Conv2d(cin, v, 3, padding=1), nn.BatchNorm2d(v), nn.ReLU(inplace=True)]
        cin = v
    net = nn.Sequential(*layers)
    for i in (34, 37, 40):
        net._modules[str(i)] = nn.Conv2d(512, 512, 3, padding=2, dilation=2)
    net._modules.pop("33")
    net._modules.pop("43")
    return net


class OfficialSpatialConv(nn.Module):
    """SpatialConv(128): down, up, right, left; a slice adds ReLU(conv(the previous slice, updated)); the up and left
    passes stop at slice 1 (spatial_conv.py l. 51-72)."""

    def __init__(self, c=128):
        super().__init__()
        self.conv_d = nn.Conv2d(c, c, (1, 9), padding=(0, 4))
        self.conv_u = nn.Conv2d(c, c, (1, 9), padding=(0, 4))
        self.conv_r = nn.Conv2d(c, c, (9, 1), padding=(4, 0))
        self.conv_l = nn.Conv2d(c, c, (9, 1), padding=(4, 0))

    def forward(self, x):
        for conv, dim, reverse in ((self.conv_d, 2, False), (self.conv_u, 2, True), (self.conv_r, 3, False),
                                   (self.conv_l, 3, True)):
            slices = list(x.split(1, dim=dim))
            order = list(range(len(slices)))
            order = order[::-1][:-1] if reverse else order  # up / left: from the last slice down to slice 1
            out = dict(enumerate(slices))
            for prev, i in zip(order, order[1:]):
                out[i] = slices[i] + F.relu(conv(out[prev]))
            x = torch.cat([out[i] for i in range(len(slices))], dim=dim)
        return x


class OfficialDeepLabV1(nn.Module):
    """deeplab_vgg.py DeepLabV1 with SpatialConv and SimpleLaneExist; forward gives {'out': stride-8 logits, 'lane':
    existence logits}."""

    def __init__(self, classes, flattened, legacy=False):
        super().__init__()
        self.encoder = nn.Module()
        self.encoder.net = official_vgg16_net()
        self.fc67 = nn.Sequential(nn.Conv2d(512, 1024, 3, padding=4, dilation=4, bias=False), nn.BatchNorm2d(1024),
                                  nn.ReLU(), nn.Conv2d(1024, 128, 1, bias=False), nn.BatchNorm2d(128), nn.ReLU())
        self.scnn = OfficialSpatialConv()
        self.fc8 = nn.Sequential(nn.Dropout2d(0.1), nn.Conv2d(128, classes, 1))
        exist = nn.Module()
        exist.linear1 = nn.Linear(flattened, 128)
        exist.linear2 = nn.Linear(128, classes - 1)
        self.exist_name = "aux_head" if legacy else "lane_classifier"  # before ac9d815: aux_head
        setattr(self, self.exist_name, exist)
        _away_from_init(self)

    def forward(self, x):
        out = self.fc8(self.scnn(self.fc67(self.encoder.net(x))))
        pooled = F.avg_pool2d(out.softmax(dim=1), 2, 2).flatten(1)
        exist = getattr(self, self.exist_name)
        return {"out": out, "lane": exist.linear2(F.relu(exist.linear1(pooled)))}


def _away_from_init(net):
    """Random weights of another law than either network's initialisation, at scales that keep the activations
    finite; BN statistics too, so a weight or buffer left unloaded shows."""
    for name, m in net.named_modules():
        if isinstance(m, nn.Conv2d):
            fan_in = m.in_channels * m.kernel_size[0] * m.kernel_size[1]
            std = 0.3 / math.sqrt(fan_in) if name.startswith("scnn.") else math.sqrt(2.0 / fan_in)
            nn.init.normal_(m.weight, 0.0, std)
            if m.bias is not None:
                nn.init.normal_(m.bias, 0.0, 0.05)
        elif isinstance(m, nn.BatchNorm2d):
            randomise_batch_norm(m)
        elif isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, 0.0, 1.0 / math.sqrt(m.in_features))
            nn.init.normal_(m.bias, 0.0, 0.1)


def official_inference_logits(official, x):
    """lane_det_utils.py l. 99-102: the stride-8 logits upsampled to the input size, align_corners=True."""
    out = official(x)
    return F.interpolate(out["out"], size=x.shape[-2:], mode="bilinear", align_corners=True), out["lane"]


def _save(path, net, prefix=""):
    """As utils/common.py save_checkpoint writes it (a DataParallel run adds 'module.')."""
    torch.save({"model": {prefix + k: v for k, v in net.state_dict().items()},
                "optimizer": None, "lr_scheduler": None}, path)
    return path


def _ours(experiment, *overrides):
    cfg = composed([f"experiment={experiment}", "data.root=/unused", *overrides])
    return build_model(model_config(cfg)).eval()


def _exist_inputs(classes, h, w):
    return classes * (math.ceil(h / 8) // 2) * (math.ceil(w / 8) // 2)


@pytest.fixture(scope="module")
def small_file(tmp_path_factory):
    """A CULane-layout file (5 classes) of a network built for the small input."""
    torch.manual_seed(0)
    net = OfficialDeepLabV1(5, _exist_inputs(5, *SMALL)).eval()
    return net, _save(tmp_path_factory.mktemp("scnn") / "model.pt", net, prefix="module.")


@pytest.fixture(scope="module")
def culane_file(tmp_path_factory):
    """The CULane release's shapes (288x800: 4500 exist inputs)."""
    torch.manual_seed(1)
    net = OfficialDeepLabV1(5, 4500).eval()
    return net, _save(tmp_path_factory.mktemp("scnn_culane") / "model.pt", net)


def test_the_converted_file_gives_the_official_networks_outputs(small_file):
    official, path = small_file
    model = _ours("official_scnn_culane", f"data.input_size=[{SMALL[0]},{SMALL[1]}]")
    line = load_detector_weights(model, path, "task.init_from")
    assert "official SCNN (voldemortX/pytorch-auto-drive) checkpoint (an unpublished setting, vgg16_bn: 5 " in line
    found = recognise(official_state_dict(torch.load(path, weights_only=True)))[1]  # 'module.' dropped
    assert found.config.startswith("model=scnn backbone=vgg16_bn model.head.align_corners=true data.max_lanes=4 and "
                                   "a data.input_size")
    x = torch.randn(2, 3, *SMALL)
    with torch.no_grad():
        seg, lane = official_inference_logits(official, x)
        ours = model(x)
    assert ours["seg"].shape == seg.shape == (2, 5, *SMALL)
    assert seg.abs().mean() > 0.1 and lane.abs().mean() > 0.1  # outputs that say something
    torch.testing.assert_close(ours["seg"], seg, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ours["exist_logits"], lane, rtol=1e-4, atol=1e-4)


def test_a_file_of_the_code_before_the_rename_aux_head_loads_too(tmp_path):
    torch.manual_seed(2)
    official = OfficialDeepLabV1(7, _exist_inputs(7, *SMALL), legacy=True).eval()
    path = _save(tmp_path / "legacy.pt", official)
    assert any(k.startswith("aux_head.linear1.") for k in torch.load(path, weights_only=True)["model"])
    cfg = composed(["task=evaluate", "experiment=official_scnn_tusimple", "data.root=/unused", f"ckpt_path={path}",
                    f"data.input_size=[{SMALL[0]},{SMALL[1]}]"])
    model = checkpoint_model(cfg).eval()
    x = torch.randn(1, 3, *SMALL)
    with torch.no_grad():
        seg, lane = official_inference_logits(official, x)
        ours = model(x)
    torch.testing.assert_close(ours["seg"], seg, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ours["exist_logits"], lane, rtol=1e-4, atol=1e-4)


def test_the_culane_release_is_recognised_and_loads_into_its_config(culane_file):
    official, path = culane_file
    state = official_state_dict(torch.load(path, weights_only=True))
    release, found = recognise(state)
    assert release.family == "scnn"
    assert found.what == "the culane release, vgg16_bn: 4 lanes, 288x800 input"
    assert found.config == "experiment=official_scnn_culane backbone=vgg16_bn"
    model = _ours("official_scnn_culane")
    load_detector_weights(model, path, "ckpt_path")
    torch.testing.assert_close(model.head.exist_fc[0].weight, official.lane_classifier.linear1.weight, rtol=0, atol=0)
    torch.testing.assert_close(model.backbone.features_41.running_var, official.encoder.net._modules["41"].running_var,
                               rtol=0, atol=0)


def test_the_tusimple_and_llamas_releases_are_recognised_and_load_into_the_configs_they_name(tmp_path):
    for (classes, inputs), config, what in (
            ((7, 6160), "experiment=official_scnn_tusimple backbone=vgg16_bn",
             "the tusimple release, vgg16_bn: 6 lanes"),
            ((5, 4400), "experiment=official_scnn_culane backbone=vgg16_bn data.input_size=[360,640]",
             "the llamas release, vgg16_bn: 4 lanes, 360x640 input (this project reads no LLAMAS data)")):
        official = OfficialDeepLabV1(classes, inputs)
        path = _save(tmp_path / f"{classes}_{inputs}.pt", official)
        found = recognise(official_state_dict(torch.load(path, weights_only=True)))[1]
        assert found.config == config and found.what.startswith(what)
        words = config.split()
        model = _ours(words[0].split("=", 1)[1], *words[1:])
        load_detector_weights(model, path, "ckpt_path")
        torch.testing.assert_close(model.head.classifier.bias, official.fc8[1].bias, rtol=0, atol=0)


def test_a_file_of_another_release_is_refused_naming_the_weight_and_the_config(culane_file):
    _, path = culane_file
    model = _ours("official_scnn_tusimple")
    with pytest.raises(CheckpointError) as error:
        load_detector_weights(model, path, "ckpt_path")
    message = str(error.value)
    assert "head.classifier.weight (5, 128, 1, 1) vs (7, 128, 1, 1)" in message
    assert "run it with experiment=official_scnn_culane backbone=vgg16_bn" in message


def test_an_scnn_file_with_a_ufld_config_is_refused_naming_the_scnn_config(culane_file):
    _, path = culane_file
    cfg = composed(["task=evaluate", "experiment=official_ufld_culane", "data.root=/unused", f"ckpt_path={path}"])
    with pytest.raises(CheckpointError, match="an official SCNN .* this run builds model=ufld; run it with "
                                              "experiment=official_scnn_culane backbone=vgg16_bn"):
        checkpoint_model(cfg)


def test_a_ufld_file_with_the_scnn_config_is_refused_naming_the_ufld_config(tmp_path):
    torch.save({"model": ufld_culane_file_keys()}, tmp_path / "culane_18.pth")
    cfg = composed(["task=evaluate", "experiment=official_scnn_culane", "data.root=/unused",
                    f"ckpt_path={tmp_path / 'culane_18.pth'}", f"data.input_size=[{SMALL[0]},{SMALL[1]}]"])
    with pytest.raises(CheckpointError, match="an official UFLD v1 .* this run builds model=scnn; run it with "
                                              "experiment=official_ufld_culane backbone=resnet18"):
        checkpoint_model(cfg)


def _official_resnet_scnn(depth):
    """standard_segmentation_model's keys and shapes: backbone (the ResNet up to layer4), channel_reducer (1x1 conv,
    BN), scnn_layer, classifier.0.conv (3x3 to the classes), lane_classifier."""
    resnet = getattr(torchvision.models, f"resnet{depth}")()
    channels = 512 if depth < 50 else 2048
    state = {f"backbone.{k}": v for k, v in resnet.state_dict().items() if not k.startswith("fc.")}
    state.update({"channel_reducer.conv1.weight": torch.zeros(128, channels, 1, 1),
                  **{f"channel_reducer.bn1.{k}": torch.zeros(128) for k in ("weight", "bias", "running_mean",
                                                                             "running_var")},
                  **{f"scnn_layer.{k}": v for k, v in OfficialSpatialConv().state_dict().items()},
                  "classifier.0.conv.weight": torch.zeros(5, 128, 3, 3), "classifier.0.conv.bias": torch.zeros(5),
                  "lane_classifier.linear1.weight": torch.zeros(128, 4500),
                  "lane_classifier.linear2.weight": torch.zeros(4, 128)})
    return state


@pytest.mark.parametrize("depth", [18, 50])
def test_a_resnet_scnn_file_is_refused_saying_why_no_config_computes_it(depth, tmp_path):
    path = tmp_path / f"resnet{depth}_scnn_culane.pt"
    torch.save({"model": _official_resnet_scnn(depth), "optimizer": None, "lr_scheduler": None}, path)
    model = _ours("official_scnn_culane", f"data.input_size=[{SMALL[0]},{SMALL[1]}]")
    with pytest.raises(CheckpointError) as error:
        load_detector_weights(model, path, "ckpt_path")
    message = str(error.value)
    assert f"an official SCNN (voldemortX/pytorch-auto-drive) checkpoint (the resnet{depth} SCNN " in message
    assert "that this project cannot load: its network is not this project's SCNN: a 1x1 channel reducer" in message
    assert "a 3x3 classifier (classifier.0.conv)" in message
    assert ("dilates only the first 3x3 convolution" in message) == (depth == 18)


def test_decoding_finds_the_official_points():
    """Constructed CULane logits with two lanes (bands along straight lines, up to row 120 of 288): our
    decoding (the config's decode settings) against the official prob_to_lines, at the official rows of the 1640x590
    image: the same points (official_writer culane: the blurred map's first argmax column, floored to whole pixels;
    the official formula as test_official_decoding_scnn.py writes it out)."""
    cfg = composed(["experiment=official_scnn_culane", "data.root=/unused"])
    model = _ours("official_scnn_culane")
    h, w = cfg.data.input_size
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    logits = np.full((5, h, w), -3.0)
    logits[0] = 0.0  # background
    lines = {2: (300.0, -0.6), 4: (520.0, 0.7)}  # class (slot + 1): x at the bottom row, dx per row upwards
    for k, (x0, slope) in lines.items():
        centre = x0 + slope * (h - 1 - ys)
        logits[k] += 9.0 * np.exp(-0.5 * ((xs - centre) / 3.0) ** 2) * (ys > 120)
    raw = {"seg": torch.tensor(logits, dtype=torch.float32)[None],
           "exist": torch.tensor([[0.1, 0.9, 0.2, 0.8]])}
    ours = model.head.decode(raw, **cfg.model.decode)[0]
    probs = torch.softmax(raw["seg"][0], dim=0).numpy()
    official = [np.array([(x, y) for x, y in lane if x >= 0])  # the CULane writer keeps the points only
                for lane in official_points(probs, raw["exist"][0].numpy() > 0.5, "culane")]
    assert len(ours) == len(official) == 2
    for mine, theirs in zip(ours, sorted(official, key=lambda lane: lane[0, 0])):
        mine = np.asarray(mine, dtype=np.float64) * [1640 / w, 590 / h]  # input px -> the 1640x590 image
        assert len(theirs) >= 8
        np.testing.assert_allclose(mine[np.argsort(-mine[:, 1])], theirs[np.argsort(-theirs[:, 1])], atol=1e-6)


@pytest.mark.slow
def test_checkpoint_model_at_the_release_size_gives_the_official_outputs(culane_file):
    """The release's 288x800 input through the config the file names (two VGG-16 forwards: seconds on a CPU)."""
    official, path = culane_file
    cfg = composed(["task=evaluate", "experiment=official_scnn_culane", "data.root=/unused", f"ckpt_path={path}"])
    model = checkpoint_model(cfg).eval()
    x = torch.randn(1, 3, 288, 800)
    with torch.no_grad():
        seg, lane = official_inference_logits(official, x)
        ours = model(x)
    torch.testing.assert_close(ours["seg"], seg, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ours["exist_logits"], lane, rtol=1e-4, atol=1e-4)


def test_task_evaluate_scores_an_official_file_on_a_culane_folder(small_file, tmp_path):
    """`python -m lanevil_train task=evaluate experiment=official_scnn_culane ckpt_path=model.pt data.root=R` (at the
    small input the file was built for), in this process: the config check passes, the file is converted, the
    images scored and the prediction files written."""
    from lanevil_train.data.formats import write_culane
    from tests.tasks.cli_helpers import run_in_process, write_photo_dataset

    _, path = small_file
    root = tmp_path / "culane"
    names = [f"driver_00_01frame/05151640_0419.MP4/{i:05d}.jpg" for i in range(2)]
    write_culane(write_photo_dataset(root, names), root, root / "list" / "test.txt")
    run_dir = tmp_path / "run"
    run_in_process(["task=evaluate", "experiment=official_scnn_culane", f"data.root={root}", f"ckpt_path={path}",
                    f"data.input_size=[{SMALL[0]},{SMALL[1]}]", "trainer=cpu", "progress=none",
                    "data.num_workers=0", "task.predictions=true"], run_dir)
    assert (run_dir / "test_scores.json").is_file()
    listed = (run_dir / "predictions" / "culane" / "list.txt").read_text().split()
    assert listed == ["/" + name for name in names]
