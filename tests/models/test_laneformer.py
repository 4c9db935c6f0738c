import itertools

import numpy as np
import pytest
import torch

from lanevil_train.models.backbones import build_backbone
from lanevil_train.models.laneformer import LaneFormerHead
from lanevil_train.models.laneformer_loss import assign, encode_lanes, matching_cost

from ._lanes_fixture import assert_lanes_inside, assert_round_trip, synthetic_lanes, train_steps

SMALL = {"d_model": 16, "nhead": 2, "num_encoder_layers": 1, "num_decoder_layers": 2, "dim_feedforward": 32,
         "dropout": 0.0}


def _perfect_raw(targets: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """Raw outputs that reproduce the targets: one query per target slot, lane logits where a lane is."""
    lanes = torch.from_numpy(np.stack([t["lanes"] for t in targets]))
    valid = lanes[..., 0]
    logits = torch.stack([10 * (1 - valid), 10 * valid], dim=-1)
    return {"cls_logits": logits, "start_y": lanes[..., 1], "end_y": lanes[..., 2], "xs": lanes[..., 3:]}


@pytest.mark.parametrize("image_size", [(64, 160), (96, 256), (128, 320), (360, 640)])
def test_encode_decode_round_trip(image_size):
    rng = np.random.default_rng(0)
    head = LaneFormerHead(8, 32, image_size, max_lanes=6, num_queries=6, **SMALL)
    gts = [synthetic_lanes(rng, image_size, n_lanes=2 + i % 3, curved=bool(i % 2)) for i in range(6)]
    targets = [head.encode(lanes) for lanes in gts]
    assert targets[0]["lanes"].shape == (6, 75) and targets[0]["x_mask"].shape == (6, 72)
    decoded = head.decode(_perfect_raw(targets), conf_threshold=0.5)
    assert_round_trip(decoded, gts, image_size)
    # the end points are exact: each decoded lane spans its ground truth's y range
    for gt, pred in zip(gts, decoded):
        for g, p in zip(sorted(gt, key=lambda ln: ln[0, 0]), pred):
            assert p[0, 1] == pytest.approx(g[:, 1].max(), abs=1e-3)
            assert p[-1, 1] == pytest.approx(g[:, 1].min(), abs=1e-3)


def test_encode_layout_and_too_many_lanes():
    h, w = 96, 256
    lane = np.array([[100.0, 95.0], [140.0, 40.0]])
    t = encode_lanes([lane], (h, w), 72, max_lanes=2)
    row = t["lanes"][0]
    assert row[0] == 1 and row[1] == pytest.approx(95 / 95) and row[2] == pytest.approx(40 / 95)
    ys = np.linspace(h - 1, 0, 72)
    inside = (ys >= 40) & (ys <= 95)
    # the supervised rows: those of the lane plus one row above its top (no row below y = 95 exists)
    assert t["x_mask"][0].sum() == inside.sum() + 1
    k = np.nonzero(inside)[0][-1] + 1  # the row above the top, extrapolated along the lane
    assert row[3 + k] * (w - 1) == pytest.approx(100 + (95 - ys[k]) * 40 / 55, abs=1e-3)
    assert t["lanes"][1].sum() == 0 and t["x_mask"][1].sum() == 0
    with pytest.raises(ValueError, match="max_lanes=2"):
        encode_lanes([lane, lane + [20, 0], lane + [40, 0]], (h, w), 72, max_lanes=2)


def test_a_few_adamw_steps_reduce_the_loss(one_thread):
    torch.manual_seed(0)
    rng = np.random.default_rng(1)
    image_size = (64, 128)
    bb = build_backbone("resnet18")
    head = LaneFormerHead(bb.channels[-1], 32, image_size, d_model=32, nhead=4, num_decoder_layers=2,
                          dim_feedforward=64, dropout=0.0, num_queries=6, max_lanes=3)
    lanes = [synthetic_lanes(rng, image_size, n_lanes=3, curved=bool(i % 2)) for i in range(2)]
    enc = [head.encode(ln) for ln in lanes]
    targets = {k: torch.from_numpy(np.stack([e[k] for e in enc])) for k in enc[0]}
    images = torch.rand(2, 3, *image_size)
    opt = torch.optim.AdamW(list(bb.parameters()) + list(head.parameters()), lr=2e-3)
    outs = train_steps(lambda x: head(bb(x)), head, images, targets, opt, 30)
    assert outs[-1]["loss"] < 0.7 * outs[0]["loss"], [o["loss"] for o in outs]
    assert outs[-1]["y_loss"] < 0.6 * outs[0]["y_loss"]  # the geometry is learnt, not only the class
    assert outs[-1]["aux_loss"] < 0.7 * outs[0]["aux_loss"]  # and so are the earlier layers' predictions


def test_loss_parts_and_lane_free_image():
    torch.manual_seed(0)
    rng = np.random.default_rng(2)
    image_size = (64, 160)
    head = LaneFormerHead(8, 32, image_size, num_queries=5, max_lanes=3, **SMALL)
    enc = [head.encode(synthetic_lanes(rng, image_size, 3, curved=True)), head.encode([])]
    targets = {k: torch.from_numpy(np.stack([e[k] for e in enc])) for k in enc[0]}
    features = [torch.randn(2, 8, 2, 5)]
    head.eval()
    out = head.loss(head(features), targets)  # eval: no auxiliary outputs
    assert out["per_sample"].shape == (2,) and out["aux_loss"] == 0
    torch.testing.assert_close(out["loss"], out["per_sample"].mean())
    torch.testing.assert_close(out["loss"], out["cls_loss"] + 5 * out["x_loss"] + 5 * out["y_loss"])
    # the lane-free image pays the cross entropy of every query towards background (equal weights: the mean)
    raw = head(features)
    want = torch.nn.functional.cross_entropy(raw["cls_logits"][1], torch.zeros(5, dtype=torch.long))
    torch.testing.assert_close(out["per_sample"][1], want)
    head.train()
    raw = head(features)
    assert raw["aux_xs"].shape == (2, 1, 5, 72)
    assert head.loss(raw, targets)["aux_loss"] > 0


def test_decoded_lanes_from_random_init_lie_inside_the_image():
    torch.manual_seed(0)
    image_size = (96, 256)
    h, w = image_size
    head = LaneFormerHead(8, 32, image_size, num_queries=10, max_lanes=4, **SMALL).eval()
    with torch.no_grad():
        raw = head([torch.randn(3, 8, 3, 8)])
    raw["xs"] = raw["xs"] + 0.8 * torch.randn_like(raw["xs"])  # scattered x, many rows outside the image
    decoded = head.decode(raw, conf_threshold=0.0)
    assert_lanes_inside(decoded, (h, w), min_total=10)


def test_decode_drops_background_queries_and_rows_outside_start_end():
    image_size = (96, 256)
    h, w = image_size
    head = LaneFormerHead(8, 32, image_size, num_queries=3, max_lanes=3, num_points=12, **SMALL)
    ys = head.row_ys
    xs = torch.tensor(np.stack([(60 + 0.5 * (h - 1 - ys)) / (w - 1), (200 - 0.5 * (h - 1 - ys)) / (w - 1),
                                np.full(12, 0.5)]), dtype=torch.float32)  # every row inside the image
    raw = {"cls_logits": torch.tensor([[[0.0, 3.0], [0.0, 3.0], [3.0, 0.0]]]),  # the third is background
           "start_y": torch.tensor([[0.8, 1.0, 1.0]]), "end_y": torch.tensor([[0.3, 0.5, 0.0]]), "xs": xs[None]}
    (lanes,) = head.decode(raw, conf_threshold=0.5)
    assert len(lanes) == 2
    for lane, (s, e), x0 in zip(lanes, [(0.8, 0.3), (1.0, 0.5)], [60, 200]):
        start, end = s * (h - 1), e * (h - 1)
        assert lane[0, 1] == pytest.approx(start, abs=1e-4) and lane[-1, 1] == pytest.approx(end, abs=1e-4)
        inner = lane[1:-1]
        np.testing.assert_allclose(inner[:, 1], ys[(ys > end) & (ys < start)])  # exactly the rows between
        slope = 0.5 if x0 == 60 else -0.5
        np.testing.assert_allclose(lane[:, 0], x0 + slope * (h - 1 - lane[:, 1]), atol=1e-3)
    assert head.decode(raw, conf_threshold=0.99) == [[]]


def _perturbed(encoder, x, i, j):
    with torch.no_grad():
        rows0, cols0 = encoder.branches(x)
        x2 = x.clone()
        x2[:, :, i, j] += 1.0
        rows1, cols1 = encoder.branches(x2)
    changed = lambda a, b: (a - b).abs().amax(dim=(0, 3)) > 1e-6  # (Hf, Wf)
    return changed(rows0, rows1), changed(cols0, cols1), rows1, cols1


def test_axial_row_attention_mixes_within_rows_and_column_attention_within_columns():
    torch.manual_seed(0)
    head = LaneFormerHead(8, 32, (128, 192), row_column="axial", **SMALL).eval()
    x = torch.randn(2, 16, 4, 6)
    row_changed, col_changed, _, _ = _perturbed(head.encoder, x, 1, 2)
    want_row = torch.zeros(4, 6, dtype=torch.bool)
    want_row[1] = True  # every position of row 1 (its row attention saw the change), nothing else
    want_col = torch.zeros(4, 6, dtype=torch.bool)
    want_col[:, 2] = True
    assert torch.equal(row_changed, want_row) and torch.equal(col_changed, want_col)


def test_paper_row_and_column_tokens():
    torch.manual_seed(0)
    x = torch.randn(2, 16, 4, 6)
    # without encoder layers a row token is a function of its own row only, a column token of its own column
    bare = LaneFormerHead(8, 32, (128, 192), **{**SMALL, "num_encoder_layers": 0}).eval()
    row_changed, col_changed, rows, cols = _perturbed(bare.encoder, x, 1, 2)
    assert torch.equal(row_changed, torch.zeros(4, 6, dtype=torch.bool).index_fill_(0, torch.tensor([1]), True))
    assert torch.equal(col_changed, torch.zeros(4, 6, dtype=torch.bool).index_fill_(1, torch.tensor([2]), True))
    # row self-attention then mixes the rows (a row gathers the other rows), column attention the columns;
    # each branch stays one value per row (broadcast over the columns) / per column
    head = LaneFormerHead(8, 32, (128, 192), **SMALL).eval()
    row_changed, col_changed, rows, cols = _perturbed(head.encoder, x, 1, 2)
    assert row_changed.all() and col_changed.all()
    torch.testing.assert_close(rows, rows[:, :, :1].expand_as(rows))
    torch.testing.assert_close(cols, cols[:, :1].expand_as(cols))
    assert head.encoder.row_proj.in_features == 6 * 16 and head.encoder.col_proj.in_features == 4 * 16


@pytest.mark.parametrize("seed", range(4))
def test_matching_is_the_brute_force_optimum_of_its_cost(seed):
    g = torch.Generator().manual_seed(seed)
    b, q, m, n = 2, 5, 4, 6
    logits, start, end = torch.randn(b, q, 2, generator=g), torch.rand(b, q, generator=g), torch.rand(b, q, generator=g)
    xs = torch.rand(b, q, n, generator=g)
    targets = torch.rand(b, m, 3 + n, generator=g)
    targets[..., 0] = torch.tensor([[1.0, 0.0, 1.0, 1.0], [1.0, 1.0, 0.0, 0.0]])  # valid slots, one gap
    x_mask = (torch.rand(b, m, n, generator=g) > 0.3).float()
    cost = matching_cost(logits, start, end, xs, targets, x_mask, 1.0, 5.0, 5.0)
    assert cost.shape == (b, q, m)
    # the cost as the paper: -p(lane) + 5 mean |dx| over the lane's rows + 5 (|ds| + |de|)
    p = torch.softmax(logits[0, 3], -1)[1]
    dx = ((xs[0, 3] - targets[0, 2, 3:]).abs() * x_mask[0, 2]).sum() / x_mask[0, 2].sum()
    dy = (start[0, 3] - targets[0, 2, 1]).abs() + (end[0, 3] - targets[0, 2, 2]).abs()
    torch.testing.assert_close(cost[0, 3, 2], -p + 5 * dx + 5 * dy)
    for i, (pred, slots) in enumerate(assign(cost, targets[..., 0])):
        valid = torch.nonzero(targets[i, :, 0]).flatten().tolist()
        assert sorted(slots.tolist()) == valid and len(set(pred.tolist())) == len(valid)
        got = sum(cost[i, p_, s_].item() for p_, s_ in zip(pred, slots))
        best = min(sum(cost[i, p_, s_].item() for p_, s_ in zip(perm, valid))
                   for perm in itertools.permutations(range(q), len(valid)))
        assert got == pytest.approx(best, abs=1e-5)


def test_loss_does_not_depend_on_the_order_of_the_lanes():
    torch.manual_seed(0)
    rng = np.random.default_rng(3)
    image_size = (64, 160)
    head = LaneFormerHead(8, 32, image_size, num_queries=6, max_lanes=4, **SMALL).train()
    gts = [synthetic_lanes(rng, image_size, 3, curved=True), synthetic_lanes(rng, image_size, 2, curved=False)]
    raw = head([torch.randn(2, 8, 2, 5)])
    assert "aux_cls_logits" in raw

    def loss_of(lane_lists):
        enc = [head.encode(ln) for ln in lane_lists]
        return head.loss(raw, {k: torch.from_numpy(np.stack([e[k] for e in enc])) for k in enc[0]})

    a = loss_of(gts)
    b = loss_of([gts[0][::-1], [gts[1][1], gts[1][0]]])
    for key in ("loss", "cls_loss", "x_loss", "y_loss", "aux_loss", "per_sample"):
        torch.testing.assert_close(a[key], b[key])


@pytest.mark.parametrize("kwargs,match", [
    ({"num_queries": 3, "max_lanes": 4}, "num_queries"),
    ({"row_column": "diagonal"}, "row_column"),
    ({"d_model": 18, "nhead": 4}, "d_model"),
    ({"num_decoder_layers": 0}, "num_decoder_layers"),
    ({"eos_coef": -1.0}, "eos_coef"),
    ({"dropout": 1.0}, "dropout"),
])
def test_bad_arguments_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        LaneFormerHead(8, 32, (64, 160), **{**SMALL, **kwargs})


def test_decode_options_and_max_lanes():
    assert LaneFormerHead.decode_options() == ("conf_threshold",)
    assert LaneFormerHead(8, 32, (64, 160), max_lanes=5, num_queries=7, **SMALL).max_lanes == 5
