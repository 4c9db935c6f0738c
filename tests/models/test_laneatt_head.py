import math

import numpy as np
import pytest
import torch

from lanevil_train.models.backbones import build_backbone
from lanevil_train.models.laneatt import LaneATTHead
from lanevil_train.models.laneatt.anchors import BOTTOM_ANGLES, LEFT_ANGLES, generate_anchors
from lanevil_train.models.laneatt.frequency import top_anchors
from lanevil_train.models.losses import focal_loss
from lanevil_train.models.nms import lane_nms, lane_nms_batched
from lanevil_train.models.rows import row_ys
from lanevil_train.tasks.detector.anchor_use import FREQUENCY_FILE, choose_anchors

from ._head_overfit import head_only_fit
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
    assert head.fmap_size == (image_size[0] // stride, image_size[1] // stride)  # the official fmap_h, fmap_w


def test_anchor_counts_follow_official_density():
    # 72 lateral and 128 bottom origins at 360x640, as the official: 2 * 6 * 72 + 15 * 128
    assert LaneATTHead(8, 32, (360, 640)).n_anchors == 2784
    assert LaneATTHead(8, 32, (192, 320)).n_anchors == 2 * 6 * 38 + 15 * 64
    head = LaneATTHead(8, 32, (360, 640), anchor_selection="frequency", topk_anchors=1000)
    assert head.n_anchors == 1000 and head.attention_layer.out_features == 999
    # fewer anchors than topk_anchors: nothing to choose, every anchor is kept
    small = LaneATTHead(8, 16, (112, 320), lateral_n=16, bottom_n=40, anchor_selection="frequency", topk_anchors=1000)
    assert small.n_anchors == 792 and small.anchor_selection == "all" and bool(small.anchors_chosen)


def test_official_anchor_grid_feature_map_and_order_at_360x640():
    """lucastabelini/LaneATT lib/models/laneatt.py at img 360x640, stride 32: fmap_h = 360 // 32 = 11 (not
    ceil = 12), fmap_w = 20; anchors = cat(left, bottom, right): 72 left origins (x=0, y from 1 down to 0) x 6
    angles, 128 bottom origins (y=1, x from 1 down to 0) x 15 angles, 72 right origins x 6 angles."""
    anchors = generate_anchors((360, 640), 72)
    assert len(anchors) == 432 + 1920 + 432
    assert BOTTOM_ANGLES == (165.0, 150.0, 141.0, 131.0, 120.0, 108.0, 100.0, 90.0, 80.0, 72.0,
                             60.0, 49.0, 39.0, 30.0, 15.0)
    left, bottom, right = slice(0, 432), slice(432, 2352), slice(2352, 2784)
    assert np.all(anchors.origins[left, 0] == 0.0) and np.all(anchors.origins[bottom, 1] == 1.0)
    assert np.all(anchors.origins[right, 0] == 1.0)
    # (index, origin (x, y), angle, start row) of the first and last anchor of each border
    for k, origin, angle, start in [(0, (0.0, 1.0), 72.0, 0), (431, (0.0, 0.0), 22.0, 71),
                                    (432, (1.0, 1.0), 165.0, 0), (437, (1.0, 1.0), 108.0, 0),
                                    (441, (1.0, 1.0), 72.0, 0), (2351, (0.0, 1.0), 15.0, 0),
                                    (2352, (1.0, 1.0), 108.0, 0), (2783, (1.0, 0.0), 158.0, 71)]:
        np.testing.assert_allclose(anchors.origins[k], origin, atol=1e-12)
        assert anchors.angles[k] == angle and anchors.starts[k] == start, k
    # 72 side origins over 71 strips: the k-th left origin starts at row k (anchor[2] = 1 - y, times n_strips)
    np.testing.assert_array_equal(anchors.starts[left][::6], np.arange(72))
    np.testing.assert_array_equal(anchors.angles[left][:6], LEFT_ANGLES)

    head = LaneATTHead(8, 32, (360, 640))
    assert head.fmap_size == (11, 20) and head.cut_cols.shape == (2784, 11)
    assert head.attention_layer.in_features == 64 * 11
    # anchor 0 (x=0, y=1, 72 deg), feature row r (top first) at y = r / 10: col = round((1 - r/10) cot72 * 640 / 32)
    assert head.cut_cols[0].tolist() == [6, 6, 5, 5, 4, 3, 3, 2, 1, 1, 0]
    assert head.cut_valid[0].tolist() == [1.0] * 11
    # the vertical bottom anchor at x = 1: x = 640 -> column 20 = fmap_w, kept (the official's `> fmaps_w`), clamped
    assert anchors.angles[439] == 90.0 and head.cut_cols[439].tolist() == [19] * 11
    assert head.cut_valid[439].tolist() == [1.0] * 11
    # anchor 431 (x=0, y=0, 22 deg) leaves the image at once: only its top row is inside
    assert head.cut_valid[431].tolist() == [1.0] + [0.0] * 10


class _Scenes:
    """A train split of images whose lanes are given (in a 2x larger image than the network input)."""

    def __init__(self, lane_sets, size):
        self.lane_sets, self.size = lane_sets, size
        self.unreadable = False

    def __len__(self):
        return len(self.lane_sets)

    def __getitem__(self, i):
        assert not self.unreadable, "read again: the cached counts should have been used"
        return {"image": np.zeros((*self.size, 3), np.uint8), "lanes": self.lane_sets[i]}


def _lane_on(anchors, k, image_size, scale=2.0):
    """A lane drawn exactly along anchor k, inside the image, in pixels of an image `scale` x larger."""
    ys = row_ys(image_size[0], 72)
    xs = anchors.xs[k]
    inside = (xs >= 0) & (xs <= image_size[1] - 1)
    return np.stack([xs[inside], ys[inside]], axis=1) * scale


def test_frequency_selection_keeps_the_anchors_the_lanes_use_most(tmp_path):
    image_size = (90, 160)
    anchors = generate_anchors(image_size, 72)
    a, b, c = 250, 100, 600  # a bottom anchor used in 2 images, a left one and another bottom one in 1 each
    scenes = _Scenes([[_lane_on(anchors, a, image_size), _lane_on(anchors, b, image_size)],
                      [_lane_on(anchors, a, image_size)], [_lane_on(anchors, c, image_size)], []], (180, 320))
    # a 1 px (at 640) match threshold: a lane counts only for the anchor it lies on
    head = LaneATTHead(8, 16, image_size, anchor_selection="frequency", topk_anchors=2, frequency_threshold=1.0)
    assert not bool(head.anchors_chosen)
    assert choose_anchors(head, scenes, cache_dir=tmp_path)
    assert head.anchor_index.tolist() == [a, b]  # most used first; the tie b / c goes to the earlier anchor
    np.testing.assert_allclose(head.anchor_xs.numpy(), anchors.xs[[a, b]], atol=1e-4)
    assert bool(head.anchors_chosen) and not choose_anchors(head, scenes)  # chosen once
    saved = np.load(tmp_path / FREQUENCY_FILE)["frequency"]
    assert saved[a] == 2 and saved[b] == 1 and saved[c] == 1 and saved.sum() == 4
    # top-k of counts: ties keep the official order
    assert top_anchors(np.array([0, 3, 1, 3, 2]), 3).tolist() == [1, 3, 4]

    # a checkpoint keeps the chosen anchors: a fresh head loading it has the same geometry, and is not re-chosen
    fresh = LaneATTHead(8, 16, image_size, anchor_selection="frequency", topk_anchors=2, frequency_threshold=1.0)
    assert fresh.anchor_index.tolist() != [a, b]
    fresh.load_state_dict(head.state_dict())
    assert fresh.anchor_index.tolist() == [a, b] and bool(fresh.anchors_chosen)
    assert torch.equal(fresh.anchor_xs, head.anchor_xs) and torch.equal(fresh.cut_cols, head.cut_cols)
    assert not choose_anchors(fresh, scenes)

    scenes.unreadable = True  # a rerun in the same run directory reads the counts back
    cached = LaneATTHead(8, 16, image_size, anchor_selection="frequency", topk_anchors=2, frequency_threshold=1.0)
    choose_anchors(cached, scenes, cache_dir=tmp_path)
    assert cached.anchor_index.tolist() == [a, b]


def test_anchor_selection_values_are_checked():
    with pytest.raises(ValueError, match="anchor_selection: expected one of all, frequency"):
        LaneATTHead(8, 32, (360, 640), anchor_selection="spread")
    with pytest.raises(ValueError, match="topk_anchors: anchor_selection=frequency keeps"):
        LaneATTHead(8, 32, (360, 640), anchor_selection="frequency", topk_anchors=None)
    with pytest.raises(ValueError, match="topk_anchors: 1000 of the 2784 anchors with anchor_selection=all"):
        LaneATTHead(8, 32, (360, 640), topk_anchors=1000)
    with pytest.raises(ValueError, match="train_nms_threshold"):
        LaneATTHead(8, 32, (360, 640), train_nms_threshold=0.0)


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


def test_training_nms_keeps_the_expected_proposals():
    # 4 proposals over the same 72 rows, constant x: 100, 105, 130, 112; one more (x = 100) on rows 60.. only,
    # past the others' ends (their length is 50 rows), so it shares no row with them
    xs = torch.tensor([100.0, 105.0, 130.0, 112.0, 100.0])[:, None].expand(5, 72)
    starts = torch.tensor([0, 0, 0, 0, 60])
    lengths = torch.tensor([50.0, 50.0, 50.0, 50.0, 12.0])
    scores = torch.tensor([[0.9, 0.8, 0.7, 0.95, 0.1],   # 112 first: 100 (12 px) and 105 (7 px) go, 130 (18 px) stays
                           [0.95, 0.8, 0.7, 0.9, 0.1]])  # 100 first: 105 (5) and 112 (12) go, 130 (30) stays
    keep = lane_nms_batched(xs.expand(2, 5, 72), starts, lengths.expand(2, 5), scores, threshold=15.0)
    assert keep.tolist() == [[False, False, True, True, True], [True, False, True, False, True]]
    assert lane_nms_batched(xs.expand(2, 5, 72), starts, lengths.expand(2, 5), scores, 15.0,
                            top_k=1).sum(1).tolist() == [1, 1]
    # the same kept set as the one-image NMS of decoding, on many random proposals
    gen = torch.Generator().manual_seed(0)
    xs = torch.rand(300, 1, generator=gen) * 600 + torch.randn(300, 72, generator=gen).cumsum(1)
    starts, lengths = torch.randint(0, 40, (300,), generator=gen), torch.rand(300, generator=gen) * 60
    scores = torch.rand(300, generator=gen)
    want = torch.zeros(300, dtype=torch.bool)
    want[lane_nms(xs, starts, lengths, scores, 15.0)] = True
    assert torch.equal(lane_nms_batched(xs[None], starts, lengths[None], scores[None], 15.0)[0], want)


def test_loss_parts_are_consistent():
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    image_size = (96, 160)
    bb = build_backbone("resnet18")
    head = LaneATTHead(bb.channels[-1], 32, image_size, anchor_feat_channels=16)
    _, targets = _batch(head, rng, 3, image_size)
    targets[2, :, 0] = 0  # an image without lanes: classification loss only
    raw = head(bb(torch.randn(3, 3, *image_size)))
    # an untrained head predicts length ~0: no proposal shares a row with another and the NMS keeps all
    assert head.train_nms_keep(raw).all()
    raw["length"] = raw["length"] + 40.0  # long proposals: neighbouring anchors now suppress each other
    out = head.loss(raw, {"lanes": targets})
    assert out["per_sample"].shape == (3,)
    torch.testing.assert_close(out["loss"], out["per_sample"].mean())
    torch.testing.assert_close(out["loss"], 10 * out["cls_loss"] + out["reg_loss"])
    pos, neg, _ = head.match(targets)
    assert pos[:2].sum(1).min() >= 3 and pos[2].sum() == 0 and neg[2].all()
    assert not (pos & neg).any()
    # the loss sees the proposals the training NMS keeps (15 px at 640 wide, as the official): fewer than all
    keep = head.train_nms_keep(raw)
    assert 0 < keep[2].sum() < head.n_anchors
    # the lane-free image's loss is its focal loss summed over the kept proposals (n_pos clamps to 1)
    want = focal_loss(raw["cls_logits"][2][keep[2]], torch.zeros(int(keep[2].sum()), dtype=torch.long)).sum() * 10
    torch.testing.assert_close(out["per_sample"][2], want)
    # without the training NMS, over every anchor
    head.train_nms_threshold = None
    all_anchors = head.loss(raw, {"lanes": targets})["per_sample"][2]
    torch.testing.assert_close(all_anchors,
                               focal_loss(raw["cls_logits"][2], torch.zeros(head.n_anchors).long()).sum() * 10)


def test_a_few_adam_steps_reduce_the_loss(one_thread):
    torch.manual_seed(0)
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


# Scenes of the head-only harness's seed range where every lane has a positive anchor (mean distance under the
# official 15 px at 640 wide, 7.5 px here) among the quickstart's 792 anchors at 112x320. On the others a curved
# lane may have none: the official rule then never trains the head on it and a frozen random backbone cannot make
# up for it (the head then fits 38-53 %), so they would test the anchor grid, not the head.
MATCHED_SEEDS = [4014, 4032, 4033, 4038]


def test_head_only_fit_reaches_scenes_whose_lanes_have_anchors(one_thread):
    # the head fitted alone (frozen random ResNet-18, stride 32) for 150 steps at 3e-3. Over the weights' seeds 0-4
    # (deterministic, one thread; another CPU's rounding may land anywhere in the spread): accuracy 89.7-94.9 %,
    # FP 39.6-53.8 %, FN 8.3-20.8 %, the loss falling 41-52 times; seed 0, this test: 91.1 / 39.6 / 8.3. A loss,
    # target or decoding that disagree (an anchor order the targets do not share, offsets read at the wrong rows)
    # falls far below
    head = ["model.head.anchor_selection=all", "model.head.topk_anchors=null", "model.head.train_nms_threshold=null",
            "model.head.lateral_n=16", "model.head.bottom_n=40"]
    out = head_only_fit("laneatt", head, steps=150, lr=3e-3, scene_seeds=MATCHED_SEEDS)
    assert out["accuracy"] >= 82.0 and out["fn"] <= 30.0, out
    assert out["first_loss"] >= 20 * out["final_loss"], out


@pytest.mark.filterwarnings("ignore::FutureWarning")
def test_forward_traces_without_data_dependent_control_flow():
    torch.manual_seed(0)
    head = LaneATTHead(8, 16, (64, 96), anchor_feat_channels=4).eval()
    traced = torch.jit.trace(_Wrap(head), torch.randn(2, 8, 4, 6))
    other = torch.randn(3, 8, 4, 6)  # another batch size replays the same graph
    for got, want in zip(traced(other), _Wrap(head)(other)):
        torch.testing.assert_close(got, want)


def test_a_run_chooses_its_anchors_from_its_train_split_and_evaluate_rebuilds_them(tmp_path, one_thread):
    from lanevil_train.tasks.builders import build_model
    from tests.tasks.cli_helpers import TINY, run_in_process

    run_dir = tmp_path / "train"
    # 636 anchors at 64x160: keep the 100 the 6 train scenes' lanes use most
    run_in_process([*TINY, "model.head.anchor_selection=frequency", "model.head.topk_anchors=100",
                    "trainer.max_steps=1", "trainer.limit_val_batches=0", "task.test_after_fit=false"], run_dir)
    frequency = np.load(run_dir / FREQUENCY_FILE)["frequency"]
    assert frequency.shape == (636,) and frequency.sum() > 0
    ckpt = torch.load(run_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    chosen = ckpt["state_dict"]["head.anchor_index"]
    assert chosen.tolist() == top_anchors(frequency, 100).tolist()
    model = build_model(ckpt["lanevil_model"])  # what task=evaluate builds, then loads
    model.load_state_dict(ckpt["state_dict"])
    assert torch.equal(model.head.anchor_index, chosen)
    full = generate_anchors((64, 160), 72)
    np.testing.assert_allclose(model.head.anchor_xs.numpy(), full.xs[chosen.numpy()], atol=1e-4)
