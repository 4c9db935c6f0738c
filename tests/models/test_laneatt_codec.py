"""Ground truth -> encode -> perfect raw outputs -> decode reproduces the lanes (TuSimple rule)."""

import numpy as np
import pytest
import torch

from lanevil_train.models.laneatt import LaneATTHead
from lanevil_train.models.laneatt.anchors import TARGET_META
from lanevil_train.models.rows import UNDEFINED_X, encode_lane, row_ys

from ._lanes_fixture import assert_round_trip, synthetic_lanes


def _perfect_raw(head: LaneATTHead, targets: np.ndarray) -> dict[str, torch.Tensor]:
    """Raw outputs where each GT's closest anchor regresses it exactly with a high score."""
    t = torch.from_numpy(targets)
    b, a = t.shape[0], head.n_anchors
    cls = torch.tensor([4.0, -4.0]).repeat(b, a, 1)
    length = torch.zeros(b, a)
    xs = head.anchor_xs.repeat(b, 1, 1).clone()
    from lanevil_train.models.losses import anchor_target_distances

    dist = anchor_target_distances(head.anchor_xs, head.anchor_starts, t[..., 0], t[..., 1], t[..., 2],
                                   t[..., TARGET_META:])
    for i in range(b):
        for j in range(t.shape[1]):
            if t[i, j, 0] == 0:
                continue
            k = int(dist[i, :, j].argmin())
            end = int(t[i, j, 1] + t[i, j, 2] - 1)
            cls[i, k] = torch.tensor([-4.0, 4.0])
            length[i, k] = end - int(head.anchor_starts[k]) + 1
            defined = t[i, j, TARGET_META:] > UNDEFINED_X / 2
            xs[i, k, defined] = t[i, j, TARGET_META:][defined]
    return {"cls_logits": cls, "length": length, "xs": xs}


@pytest.mark.parametrize("image_size,stride", [((360, 640), 32), ((96, 160), 16), ((64, 160), 32)])
def test_encode_decode_round_trip_tusimple_accuracy(image_size, stride):
    rng = np.random.default_rng(7)
    head = LaneATTHead(in_channels=8, in_strides=stride, image_size=image_size, max_lanes=6)
    gts, targets = [], []
    for i in range(8):
        gt = synthetic_lanes(rng, image_size, n_lanes=int(rng.integers(2, 6)), curved=bool(i % 2))
        gts.append(gt)
        targets.append(head.encode(gt)["lanes"])
    targets = np.stack(targets)
    assert targets.shape == (8, 6, TARGET_META + 72) and targets.dtype == np.float32
    decoded = head.decode(_perfect_raw(head, targets), conf_threshold=0.5)
    assert_round_trip(decoded, gts, image_size)


def test_encode_lane_values():
    h, w, s = 360, 640, 72
    lane = np.array([[320.0, 359.0], [320.0 + 100, 159.0]])  # x = 320 + (359 - y) / 2
    start, length, xs = encode_lane(lane, (h, w), s)
    ys = row_ys(h, s)
    assert start == 0
    top_row = int(np.sum(ys >= 159.0 - (h - 1) / (s - 1) + 1e-9))  # rows down to one strip above y=159
    assert length == top_row
    np.testing.assert_allclose(xs[:length], 320 + (359 - ys[:length]) / 2, atol=1e-6)
    assert np.all(xs[length:] == UNDEFINED_X)
    # a lane starting mid-image is extended straight to the bottom; one leaving left starts later
    start, length, xs = encode_lane(np.array([[100.0, 250.0], [150.0, 150.0]]), (h, w), s)
    np.testing.assert_allclose(xs[0], 100 - (359 - 250) / 2, atol=1e-6)
    assert start == 0
    start, length, xs = encode_lane(np.array([[10.0, 250.0], [60.0, 150.0]]), (h, w), s)
    assert xs[start] >= 0 and xs[start - 1] < 0 and ys[start] < 280
    assert encode_lane(np.array([[700.0, 300.0], [800.0, 100.0]]), (h, w), s) is None


def test_encode_rejects_too_many_lanes():
    head = LaneATTHead(in_channels=8, in_strides=32, image_size=(64, 160), max_lanes=2)
    lanes = [np.array([[x, 63.0], [x, 20.0]]) for x in (20.0, 60.0, 100.0)]
    with pytest.raises(ValueError, match="max_lanes=2"):
        head.encode(lanes)
    empty = head.encode([])["lanes"]
    assert empty.shape == (2, TARGET_META + 72) and np.all(empty[:, 0] == 0)


@pytest.mark.usefixtures("hydra_conf")
@pytest.mark.parametrize("overrides,want", [
    # cfgs/laneatt_tusimple_resnet18.yml test_parameters: conf 0.2, nms_thres 45, nms_topk = max_lanes 5
    (["model=laneatt"], {"conf_threshold": 0.2, "nms_threshold": 45.0, "nms_topk": 5, "lane_points": "inside"}),
    # cfgs/laneatt_culane_resnet18.yml: conf 0.5, nms_thres 50, nms_topk = max_lanes 4
    (["experiment=paper_laneatt"],
     {"conf_threshold": 0.5, "nms_threshold": 50.0, "nms_topk": 4, "lane_points": "inside"}),
    # the quickstart keeps the values it was tuned with
    (["experiment=quickstart"], {"conf_threshold": 0.3, "nms_threshold": 50.0, "nms_topk": 6, "lane_points": "inside"}),
])
def test_decoding_values_per_dataset_in_the_configs(overrides, want):
    from hydra import compose
    from omegaconf import OmegaConf

    cfg = compose(config_name="config", overrides=overrides)
    assert OmegaConf.to_container(cfg.model.decode, resolve=True) == want
    head = cfg.model.head
    if overrides != ["experiment=quickstart"]:  # the official anchors and training NMS (every cfgs/*.yml)
        assert (head.anchor_selection, head.topk_anchors, head.frequency_threshold) == ("frequency", 1000, 30.0)
        assert (head.train_nms_threshold, head.train_nms_topk) == (15.0, 3000)
