"""The published LaneATT files load as the official code saved them: the official network (written here from the
facts in models/laneatt/official.py: torchvision's ResNet as `feature_extractor`, the anchors of l. 241-284 chosen
by a frequency file, the anchor cut of l. 208-238, the attention of l. 79-91) and ours, given the converted file and
the same frequency file, compute the same outputs."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torchvision
from torch import nn

from lanevil_train.checkpoints import CheckpointError
from lanevil_train.models.official import load_detector_weights, official_state_dict, recognise
from lanevil_train.tasks.builders import build_model, model_config
from tests.tasks.cli_helpers import composed

H, W, STRIDE, S, C, TOPK = 360, 640, 32, 72, 64, 1000
FMAP_H, FMAP_W = H // STRIDE, W // STRIDE
LEFT = [72.0, 60.0, 49.0, 39.0, 30.0, 22.0]
RIGHT = [108.0, 120.0, 131.0, 141.0, 150.0, 158.0]
BOTTOM = [165.0, 150.0, 141.0, 131.0, 120.0, 108.0, 100.0, 90.0, 80.0, 72.0, 60.0, 49.0, 39.0, 30.0, 15.0]


def official_anchor_xs(ys):
    """x (px) of every anchor at the rows ys (fractions, 1 = bottom), in the official order: left (x = 0, origins
    from y = 1 to 0, each with every angle), bottom (y = 1, origins from x = 1 to 0), right (x = 1)."""
    out = []
    for angles, starts in ((LEFT, [(0.0, y) for y in np.linspace(1.0, 0.0, 72)]),
                           (BOTTOM, [(x, 1.0) for x in np.linspace(1.0, 0.0, 128)]),
                           (RIGHT, [(1.0, y) for y in np.linspace(1.0, 0.0, 72)])):
        for start_x, start_y in starts:
            for angle in angles:
                out.append((start_x + (start_y - ys) / math.tan(angle * math.pi / 180.0)) * W)
    return torch.tensor(np.array(out), dtype=torch.float32)


class OfficialLaneATT(nn.Module):
    """LaneATT's network as its file lays it out, forward up to the proposals (before NMS)."""

    def __init__(self, counts):
        super().__init__()
        self.feature_extractor = nn.Sequential(*list(torchvision.models.resnet18().children())[:-2])
        self.conv1 = nn.Conv2d(512, C, 1)
        self.cls_layer = nn.Linear(2 * C * FMAP_H, 2)
        self.reg_layer = nn.Linear(2 * C * FMAP_H, S + 1)
        self.attention_layer = nn.Linear(C * FMAP_H, TOPK - 1)
        for p in self.parameters():
            nn.init.normal_(p, 0.0, 0.02)
        keep = torch.argsort(counts, descending=True)[:TOPK]
        self.anchor_xs = official_anchor_xs(np.linspace(1.0, 0.0, S))[keep]
        cut = official_anchor_xs(np.linspace(1.0, 0.0, FMAP_H))[keep]
        xs = torch.flip((cut / STRIDE).round().long(), dims=(1,))  # top row first
        self.invalid = (xs < 0) | (xs > FMAP_W)
        self.cut_xs = xs.clamp(0, FMAP_W - 1)

    def forward(self, x):
        fmap = self.conv1(self.feature_extractor(x))  # (B, C, Hf, Wf)
        rows = torch.arange(FMAP_H)[None].expand(TOPK, FMAP_H)
        rois = fmap[:, :, rows, self.cut_xs].permute(0, 2, 1, 3)  # (B, A, C, Hf)
        rois = rois * (~self.invalid)[None, :, None, :]
        feats = rois.reshape(x.shape[0], TOPK, C * FMAP_H)
        attention = torch.softmax(self.attention_layer(feats), dim=-1)  # (B, A, A - 1)
        matrix = torch.zeros(x.shape[0], TOPK, TOPK)
        off_diagonal = ~torch.eye(TOPK, dtype=torch.bool)
        matrix[:, off_diagonal] = attention.reshape(x.shape[0], -1)  # row i, columns j != i ascending
        joint = torch.cat([torch.bmm(matrix, feats), feats], dim=-1)
        reg = self.reg_layer(joint)
        return self.cls_layer(joint), reg[..., 0], self.anchor_xs + reg[..., 1:]


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    folder = tmp_path_factory.mktemp("laneatt")
    torch.manual_seed(0)
    counts = torch.randperm(2784).float()  # distinct counts: no ties to order
    torch.save(counts, folder / "tusimple_anchors_freq.pt")
    net = OfficialLaneATT(counts).eval()
    state = {f"module.{k}": v for k, v in net.state_dict().items()}
    torch.save({"epoch": 100, "model": state, "optimizer": {"state": {}}, "scheduler": {}}, folder / "model_0100.pt")
    return net, folder / "model_0100.pt", folder / "tusimple_anchors_freq.pt"


def _ours(*overrides):
    cfg = composed(["experiment=official_laneatt_tusimple", "data.root=/unused", *overrides])
    return build_model(model_config(cfg)).eval()


def test_the_converted_file_with_its_frequency_file_gives_the_official_outputs(release):
    official, path, freq = release
    model = _ours(f"model.head.anchor_frequency_file={freq}")
    line = load_detector_weights(model, path, "ckpt_path")
    assert "official LaneATT" in line and "resnet18, 1000 anchors, a 11-row feature map (352 px high input)" in line
    x = torch.randn(1, 3, H, W)
    with torch.no_grad():
        cls, length, xs = official(x)
        ours = model(x)
    torch.testing.assert_close(ours["cls_logits"], cls, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(ours["length"], length, rtol=1e-4, atol=1e-4)
    # the anchors are the official ones (fraction_scale: size), so the proposals' x are the official's too
    torch.testing.assert_close(model.head.anchor_xs, official.anchor_xs, rtol=0, atol=1e-3)
    torch.testing.assert_close(ours["xs"], xs, rtol=1e-4, atol=1e-3)


def test_without_the_frequency_file_the_load_is_refused_naming_the_setting(release):
    _, path, _ = release
    model = _ours("model.head.anchor_frequency_file=null")
    with pytest.raises(CheckpointError, match="give model.head.anchor_frequency_file=<LaneATT>/data/<dataset>_anchors"):
        load_detector_weights(model, path, "ckpt_path")


def test_the_backbone_is_recognised_and_another_one_refused(release):
    _, path, freq = release
    state = official_state_dict(torch.load(path, weights_only=True))
    found = recognise(state)[1]
    assert found.config.startswith("experiment=official_laneatt_<tusimple|culane> backbone=resnet18")
    model = _ours("backbone=resnet34", f"model.head.anchor_frequency_file={freq}")
    with pytest.raises(CheckpointError, match="weights .* missing .*backbone.layer1.2"):
        load_detector_weights(model, path, "ckpt_path")


def official_decode(xs_frac, start_frac, length, n_offsets=S):
    """LaneATT's proposals_to_pred (l. 309-341) for one proposal: x as fractions of the width per row (bottom row
    first), the anchor's start as a fraction of the height from the bottom, the predicted length; returns the points
    (x, y fractions of the image, y = 1 the bottom row) it keeps, bottom first."""
    xs = np.array(xs_frac, dtype=np.float64)
    ys = np.linspace(1.0, 0.0, n_offsets)
    start = int(round(start_frac * (n_offsets - 1)))
    end = min(start + int(round(length)) - 1, n_offsets - 1)
    below = ((xs[:start] >= 0) & (xs[:start] <= 1))[::-1].cumprod()[::-1].astype(bool)  # kept while inside
    xs[:start][~below] = -2
    xs[end + 1:] = -2
    keep = xs >= 0
    return np.stack([xs[keep], ys[keep]], axis=1)


@pytest.mark.parametrize("case", ["bottom", "side_extended", "leaves_right"])
def test_decoding_keeps_the_points_the_official_formula_keeps(case):
    """A constructed output with one confident proposal: our lane's points are the official formula's (as fractions
    of the image), except the official keeps the points right of the image, which we drop."""
    model = _ours("model.head.anchor_frequency_file=null", "model.head.anchor_selection=all",
                  "model.head.topk_anchors=null", "model.head.fraction_scale=last_pixel")
    head = model.head  # this project's own rule (fraction_scale last_pixel, lane_points inside) beside the official
    anchors = head.anchor_xs.numpy().astype(np.float64)
    starts = head.anchor_starts.numpy()
    side = {"bottom": np.nonzero(starts == 0)[0][50], "side_extended": np.nonzero(starts == 20)[0][3],
            "leaves_right": np.nonzero(starts == 0)[0][-8]}[case]
    offsets = {"bottom": np.linspace(-6.0, 9.0, S), "side_extended": np.full(S, 40.0),  # below its start: inside
               "leaves_right": np.linspace(0.0, 200.0, S)}[case]
    n = len(anchors)
    cls = torch.zeros(1, n, 2)
    cls[0, :, 0] = 10.0  # every anchor background ...
    cls[0, side] = torch.tensor([-10.0, 10.0])  # ... but one
    xs = torch.tensor(anchors, dtype=torch.float32)[None].clone()
    xs[0, side] += torch.tensor(offsets, dtype=torch.float32)
    raw = {"cls_logits": cls, "length": torch.full((1, n), 40.0), "xs": xs}
    (lane,) = head.decode(raw, conf_threshold=0.5, nms_threshold=45.0, nms_topk=5)[0]
    ours = np.stack([lane[:, 0] / (W - 1), lane[:, 1] / (H - 1)], axis=1)  # fractions of the image, 1 = bottom
    official = official_decode((anchors[side] + offsets) / (W - 1), starts[side] / (S - 1), 40.0)
    official_inside = official[official[:, 0] <= 1.0]
    rows = np.isin(np.round(ours[:, 1], 9), np.round(official_inside[:, 1], 9))
    np.testing.assert_allclose(ours[rows], official_inside, atol=1e-6)  # the same points at the same rows
    # plus, where the lane crosses the image's border between two rows, the crossing point on it
    assert (~rows).sum() <= 1 and np.all(np.isclose(ours[~rows, 0], 0.0) | np.isclose(ours[~rows, 0], 1.0))
    if case == "leaves_right":
        assert len(official) > len(official_inside)  # the official keeps points past the right edge
    if case == "side_extended":
        assert official[0, 1] > 1.0 - starts[side] / (S - 1) + 0.01  # extended below its start while inside


def test_a_laneatt_file_with_a_ufld_config_is_refused_naming_the_laneatt_config(release):
    _, path, _ = release
    cfg = composed(["task=evaluate", "experiment=official_ufld_tusimple", "data.root=/unused", f"ckpt_path={path}"])
    from lanevil_train.tasks.builders import checkpoint_model

    with pytest.raises(CheckpointError, match="an official LaneATT .* this run builds model=ufld; run it with "
                                              "experiment=official_laneatt_<tusimple|culane> backbone=resnet18"):
        checkpoint_model(cfg)
