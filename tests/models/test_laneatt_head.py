import math

import numpy as np
import pytest
import torch

from lanevil_train.models.backbones import build_backbone
from lanevil_train.models.laneatt import LaneATTHead
from lanevil_train.models.losses import focal_loss

from ._lanes_fixture import synthetic_lanes, train_steps


@pytest.mark.parametrize("image_size", [(64, 160), (96, 160)])
@pytest.mark.parametrize("out_index,stride", [(3, 16), (4, 32)])
def test_forward_shapes_resnet18(image_size, out_index, stride):
    torch.manual_seed(0)
    bb = build_backbone("resnet18", out_indices=(out_index,))
    assert bb.strides == [stride]
    head = LaneATTHead(bb.channels[-1], stride, image_size, anchor_feat_channels=16)
    raw = head(bb(torch.randn(2, 3, *image_size)))
    a = head.n_anchors
    assert raw["cls_logits"].shape == (2, a, 2)
    assert raw["length"].shape == (2, a)
    assert raw["xs"].shape == (2, a, 72)
    assert head.fmap_size == (math.ceil(image_size[0] / stride), math.ceil(image_size[1] / stride))


def test_anchor_counts_follow_official_density():
    # 72 lateral and 128 bottom origins at 360x640, as the official: 2 * 6 * 72 + 15 * 128
    assert LaneATTHead(8, 32, (360, 640)).n_anchors == 2784
    assert LaneATTHead(8, 32, (192, 320)).n_anchors == 2 * 6 * 38 + 15 * 64
    assert LaneATTHead(8, 32, (360, 640), topk_anchors=1000).n_anchors == 1000
    freq = np.zeros(2784)
    freq[[5, 17, 2000]] = [3, 9, 1]
    head = LaneATTHead(8, 32, (360, 640), topk_anchors=2, anchor_frequency=freq)
    full = LaneATTHead(8, 32, (360, 640))
    assert torch.equal(head.anchor_xs, full.anchor_xs[[5, 17]])


def test_attention_is_a_softmax_over_the_other_anchors():
    torch.manual_seed(0)
    head = LaneATTHead(4, 32, (64, 96), anchor_feat_channels=2, lateral_n=2, bottom_n=2)
    a = head.n_anchors
    captured = {}
    orig_bmm = torch.bmm

    def spy(att, feats):
        captured["att"] = att
        return orig_bmm(att, feats)

    torch.bmm = spy
    try:
        head([torch.randn(3, 4, 2, 3)])
    finally:
        torch.bmm = orig_bmm
    att = captured["att"]
    assert att.shape == (3, a, a)
    assert torch.all(torch.diagonal(att, dim1=1, dim2=2) == 0)
    torch.testing.assert_close(att.sum(-1), torch.ones(3, a))
    assert torch.all(att + torch.eye(a) > 0)


def test_focal_loss_hand_computed():
    logits = torch.tensor([[2.0, 0.0], [0.5, 1.5]])
    target = torch.tensor([0, 0])
    p0 = 1 / (1 + math.exp(-2.0))  # softmax prob of class 0 in the first row
    q0 = 1 / (1 + math.exp(1.0))  # and in the second
    want = torch.tensor([-0.25 * (1 - p0) ** 2 * math.log(p0), -0.25 * (1 - q0) ** 2 * math.log(q0)])
    torch.testing.assert_close(focal_loss(logits, target), want)
    assert focal_loss(torch.tensor([[0.0, 0.0]]), torch.tensor([1])).item() == pytest.approx(0.25 * 0.25 * math.log(2))


def _batch(head, rng, n, image_size):
    lanes = [synthetic_lanes(rng, image_size, n_lanes=3, curved=bool(i % 2)) for i in range(n)]
    return lanes, torch.from_numpy(np.stack([head.encode(ln)["lanes"] for ln in lanes]))


def test_loss_parts_are_consistent():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    image_size = (96, 160)
    bb = build_backbone("resnet18")
    head = LaneATTHead(bb.channels[-1], 32, image_size, anchor_feat_channels=16)
    _, targets = _batch(head, rng, 3, image_size)
    targets[2, :, 0] = 0  # an image without lanes: classification loss only
    raw = head(bb(torch.randn(3, 3, *image_size)))
    out = head.loss(raw, {"lanes": targets})
    assert out["per_sample"].shape == (3,)
    torch.testing.assert_close(out["loss"], out["per_sample"].mean())
    torch.testing.assert_close(out["loss"], 10 * out["cls_loss"] + out["reg_loss"])
    pos, neg, _ = head.match(targets)
    assert pos[:2].sum(1).min() >= 3 and pos[2].sum() == 0 and neg[2].all()
    assert not (pos & neg).any()
    # the lane-free image's loss is its focal loss summed over all anchors (n_pos clamps to 1)
    want = focal_loss(raw["cls_logits"][2], torch.zeros(head.n_anchors, dtype=torch.long)).sum() * 10
    torch.testing.assert_close(out["per_sample"][2], want)


def test_a_few_adam_steps_reduce_the_loss():
    torch.manual_seed(0)
    torch.set_num_threads(2)
    rng = np.random.default_rng(1)
    image_size = (64, 160)
    bb = build_backbone("resnet18")
    head = LaneATTHead(bb.channels[-1], 32, image_size)
    _, targets = _batch(head, rng, 4, image_size)
    images = torch.rand(4, 3, *image_size)
    params = list(bb.parameters()) + list(head.parameters())
    opt = torch.optim.Adam(params, lr=1e-3)
    history = train_steps(lambda x: head(bb(x)), head, images, {"lanes": targets}, opt, 30)
    losses = [step["loss"] for step in history]
    assert losses[-1] < 0.5 * losses[0], losses


class _Wrap(torch.nn.Module):
    def __init__(self, head):
        super().__init__()
        self.head = head

    def forward(self, f):
        raw = self.head([f])
        return raw["cls_logits"], raw["length"], raw["xs"]


@pytest.mark.filterwarnings("ignore::FutureWarning")
def test_forward_traces_without_data_dependent_control_flow():
    torch.manual_seed(0)
    head = LaneATTHead(8, 16, (64, 96), anchor_feat_channels=4).eval()
    traced = torch.jit.trace(_Wrap(head), torch.randn(2, 8, 4, 6))
    other = torch.randn(3, 8, 4, 6)  # another batch size replays the same graph
    for got, want in zip(traced(other), _Wrap(head)(other)):
        torch.testing.assert_close(got, want)
