"""decode(raw, with_scores=True) of every detector family: the same lanes in the same order as without it, each
with its family's confidence, a float in [0, 1]; on constructed raw outputs, the confidence each family says it gives
(models/head.py, docs/detectors.md)."""

from __future__ import annotations

import inspect
import math

import numpy as np
import pytest
import torch
from hydra import compose

from lanevil_train.tasks.builders import build_model, model_config
from tests.models.test_families import BACKBONE, FAMILIES, NARROW, SIZE

pytestmark = pytest.mark.usefixtures("hydra_conf")  # tests/conftest.py

# the options under which a randomly initialised head decodes lanes (its default thresholds may keep none), and the
# families' other point rules (official writers), each decoded with and without scores
OPTIONS = {
    "laneatt": [{"conf_threshold": 0.0}, {"conf_threshold": 0.0, "lane_points": "official"}],
    "clrnet": [{"conf_threshold": 0.0}, {"conf_threshold": 0.0, "lane_points": "official"}],
    "clrernet": [{"conf_threshold": 0.0}, {"conf_threshold": 0.0, "lane_points": "official"}],
    "scnn": [{"exist_threshold": 0.0, "prob_threshold": 0.0, "min_points": 2},
             {"exist_threshold": 0.0, "prob_threshold": 0.0, "min_points": 2, "official_writer": "tusimple",
              "blur": 9, "max_lanes": 3},
             {"exist_threshold": 0.0, "prob_threshold": 0.0, "min_points": 2, "official_writer": "culane"}],
    "bezierlanenet": [{"conf_threshold": 0.0, "local_maximum_window": 0},
                      {"conf_threshold": 0.0, "local_maximum_window": 0, "official_writer": "tusimple", "max_lanes": 4},
                      {"conf_threshold": 0.0, "local_maximum_window": 0, "official_writer": "culane"}],
    "ganet": [{"kpt_threshold": 0.0, "root_threshold": 1e6, "min_points": 2}],
    "laneformer": [{"conf_threshold": 0.0}],
    "ufld": [{"min_points": 1}, {"min_points": 1, "official_writer": "tusimple"},
             {"min_points": 1, "official_writer": "culane"}],
}
SOFTMAX_2 = 1.0 / (1.0 + math.exp(-2.0))  # softmax of the logits [0, 2]: 0.8808
SOFTMAX_1 = 1.0 / (1.0 + math.exp(-1.0))  # of [0, 1]: 0.7311
_MODELS: dict = {}


def _model(family: str):
    """The family's model as the CLI builds it at the contract tests' size, in eval mode (built once)."""
    if family not in _MODELS:
        cfg = compose(config_name="config", overrides=[
            f"model={family}", f"backbone={BACKBONE.get(family, 'resnet18')}",
            f"data.input_size=[{SIZE[0]},{SIZE[1]}]", "data.max_lanes=4", *NARROW.get(family, [])])
        torch.manual_seed(0)
        _MODELS[family] = build_model(model_config(cfg)).eval()
    return _MODELS[family]


def _raw(family: str) -> dict[str, torch.Tensor]:
    """The model's raw output on two random images."""
    model = _model(family)
    images = torch.randn(2, 3, *SIZE, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        return {k: v.clone() for k, v in model(images).items()}


def _plausible(family: str, raw: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """An untrained head's output with lanes in it: where its geometry starts degenerate (LaneATT and CLRNet
    predict lengths near 0, BezierLaneNet curves in the top-left corner), random lengths and near-vertical
    curves; the class logits spread so that the scores differ."""
    g = torch.Generator().manual_seed(2)
    if family == "laneatt":
        head = _model(family).head
        raw["length"] = torch.rand(raw["length"].shape, generator=g) * head.n_offsets
        raw["cls_logits"] = 2 * torch.randn(raw["cls_logits"].shape, generator=g)
    elif family in ("clrnet", "clrernet"):
        raw["lines"][..., 3] = 0.2 + 0.8 * torch.rand(raw["lines"].shape[:-1], generator=g)
        raw["cls_logits"] = 2 * torch.randn(raw["cls_logits"].shape, generator=g)
    elif family == "bezierlanenet":
        b, q, n, _ = raw["curves"].shape
        x = 0.1 + 0.8 * torch.rand(b, q, 1, generator=g) + 0.05 * torch.randn(b, q, n, generator=g)
        raw["curves"] = torch.stack([x, torch.linspace(1.0, 0.3, n).expand(b, q, n)], dim=-1)
        raw["logits"] = 2 * torch.randn(raw["logits"].shape, generator=g)
    return raw


def _check_pairs(plain: list, scored: list) -> int:
    """The scored decoding is the plain one's lanes, same order, each beside one float score in [0, 1]; the count
    of lanes."""
    assert len(plain) == len(scored)
    count = 0
    for lanes, pairs in zip(plain, scored):
        assert len(lanes) == len(pairs)
        for lane, pair in zip(lanes, pairs):
            assert isinstance(pair, tuple) and len(pair) == 2
            got, score = pair
            assert isinstance(score, float) and 0.0 <= score <= 1.0, score
            assert np.array_equal(lane, got)
            count += 1
    return count


def test_every_family_is_covered():
    assert set(OPTIONS) == set(FAMILIES)


@pytest.mark.parametrize("family", FAMILIES)
def test_with_scores_is_keyword_only_and_not_a_decoding_option(family):
    head = _model(family).head
    parameter = inspect.signature(type(head).decode).parameters["with_scores"]
    assert parameter.kind is inspect.Parameter.KEYWORD_ONLY and parameter.default is False
    assert "with_scores" not in head.decode_options()
    assert set(_model(family).decode_kwargs) <= set(head.decode_options())


@pytest.mark.parametrize("family", FAMILIES)
def test_scores_leave_the_lanes_as_they_are(family):
    model = _model(family)
    raw = _plausible(family, _raw(family))
    # the family's configured options (an untrained head may decode no lane under them) ...
    _check_pairs(model.head.decode(raw, **model.decode_kwargs),
                 model.head.decode(raw, **model.decode_kwargs, with_scores=True))
    # ... and the ones under which it decodes lanes, each of its point rules
    for relaxed in OPTIONS[family]:
        options = {**model.decode_kwargs, **relaxed}
        count = _check_pairs(model.head.decode(raw, **options), model.head.decode(raw, **options, with_scores=True))
        assert count > 0, f"{family} {relaxed}: no lane decoded, nothing checked"


# ----------------------------------------------------------------------------- constructed raw outputs
def _decoded(family: str, raw: dict, **options) -> list[tuple[np.ndarray, float]]:
    """The first image's (lane, score) pairs, checked against the plain decoding."""
    head = _model(family).head
    plain = head.decode(raw, **options)
    scored = head.decode(raw, **options, with_scores=True)
    _check_pairs(plain, scored)
    return scored[0]


def _inside_anchors(head, n: int = 2) -> list[int]:
    """n LaneATT anchors starting on the bottom row that stay inside the image the longest, far apart in x."""
    xs = head.anchor_xs.numpy()
    w = head.image_size[1]
    inside = ((xs >= 0) & (xs <= w - 1)).sum(axis=1) * (head.anchor_starts.numpy() == 0)
    left = np.flatnonzero(xs[:, 0] < w / 3)
    right = np.flatnonzero(xs[:, 0] > 2 * w / 3)
    return [int(left[np.argmax(inside[left])]), int(right[np.argmax(inside[right])])][:n]


def test_laneatt_score_is_the_kept_proposals_softmax():
    head = _model("laneatt").head
    raw = _raw("laneatt")
    left, right = _inside_anchors(head)
    raw["cls_logits"][:] = torch.tensor([0.0, -10.0])
    raw["cls_logits"][0, left] = torch.tensor([0.0, 2.0])
    raw["cls_logits"][0, right] = torch.tensor([0.0, 1.0])
    raw["xs"][:] = head.anchor_xs
    raw["length"][:] = float(head.n_offsets)
    for lane_points in ("inside", "official"):
        pairs = _decoded("laneatt", raw, conf_threshold=0.5, lane_points=lane_points)
        assert len(pairs) == 2
        assert pairs[0][0][0, 0] < pairs[1][0][0, 0]
        assert pairs[0][1] == pytest.approx(SOFTMAX_2, abs=1e-6)
        assert pairs[1][1] == pytest.approx(SOFTMAX_1, abs=1e-6)


def test_clrnet_score_is_the_kept_priors_softmax_at_the_last_stage():
    head = _model("clrnet").head
    raw = _raw("clrnet")
    w = head.image_size[1]
    raw["cls_logits"][:] = torch.tensor([0.0, -10.0])
    raw["cls_logits"][0, :-1] = torch.tensor([0.0, 5.0])  # an earlier stage's score is not the one read
    # prior 3 on the right (logits [0, 1]), prior 7 on the left ([0, 2]): listed right first, returned left first
    for prior, x, logits in ((3, 0.75 * w, [0.0, 1.0]), (7, 0.25 * w, [0.0, 2.0])):
        raw["cls_logits"][0, -1, prior] = torch.tensor(logits)
        raw["lines"][0, -1, prior] = torch.tensor([0.0, x / (w - 1), 0.5, 1.0])  # from the bottom row, every row
        raw["xs"][0, -1, prior] = x
    for lane_points in ("inside", "official"):
        pairs = _decoded("clrnet", raw, conf_threshold=0.4, lane_points=lane_points)
        assert len(pairs) == 2
        assert pairs[0][0][0, 0] < w / 2 < pairs[1][0][0, 0]
        assert pairs[0][1] == pytest.approx(SOFTMAX_2, abs=1e-6)
        assert pairs[1][1] == pytest.approx(SOFTMAX_1, abs=1e-6)


def _scnn_raw(head) -> dict[str, torch.Tensor]:
    """Slot 1 a lane on column 0.7 W (existence 0.9), slot 2 one on column 0.3 W (0.6), the others absent (0.2)."""
    h, w = head.image_size
    seg = torch.zeros(1, head.max_lanes + 1, h, w)
    seg[:, 0] = 5.0
    seg[0, 2, :, int(0.7 * w) - 4:int(0.7 * w) + 5] = 10.0  # 9 columns wide: the official 9 x 9 blur keeps it
    seg[0, 3, :, int(0.3 * w) - 4:int(0.3 * w) + 5] = 10.0
    exist = torch.full((1, head.max_lanes), 0.2)
    exist[0, 1], exist[0, 2] = 0.9, 0.6
    return {"seg": seg, "exist_logits": torch.logit(exist), "exist": exist}


def test_scnn_score_is_the_slots_existence_probability():
    head = _model("scnn").head
    raw = _scnn_raw(head)
    for writer in (None, "tusimple", "culane"):
        pairs = _decoded("scnn", raw, official_writer=writer, blur=0 if writer is None else 9)
        assert len(pairs) == 2
        assert pairs[0][0][0, 0] < head.image_size[1] / 2 < pairs[1][0][0, 0]
        assert pairs[0][1] == pytest.approx(0.6, abs=1e-6)
        assert pairs[1][1] == pytest.approx(0.9, abs=1e-6)


def test_bezierlanenet_score_is_the_querys_existence_sigmoid():
    head = _model("bezierlanenet").head
    raw = _raw("bezierlanenet")
    raw["logits"][:] = -10.0
    for query, x, logit in ((2, 0.7, 1.0), (5, 0.3, 2.0)):
        raw["logits"][0, query] = logit
        ys = torch.linspace(1.0, 0.2, raw["curves"].shape[2])  # control points from the bottom up, a vertical line
        raw["curves"][0, query] = torch.stack([torch.full_like(ys, x), ys], dim=1)
    for writer in (None, "tusimple", "culane"):
        pairs = _decoded("bezierlanenet", raw, conf_threshold=0.5, local_maximum_window=0, official_writer=writer)
        assert len(pairs) == 2
        assert pairs[0][0][0, 0] < head.image_size[1] / 2 < pairs[1][0][0, 0]
        assert pairs[0][1] == pytest.approx(SOFTMAX_2, abs=1e-6)  # sigmoid(2) = softmax([0, 2])
        assert pairs[1][1] == pytest.approx(SOFTMAX_1, abs=1e-6)


def test_laneformer_score_is_the_querys_class_probability():
    head = _model("laneformer").head
    raw = _raw("laneformer")
    raw["cls_logits"][:] = torch.tensor([0.0, -10.0])
    for query, x, logits in ((1, 0.7, [0.0, 1.0]), (4, 0.3, [0.0, 2.0])):
        raw["cls_logits"][0, query] = torch.tensor(logits)
        raw["start_y"][0, query], raw["end_y"][0, query] = 1.0, 0.3
        raw["xs"][0, query] = x
    pairs = _decoded("laneformer", raw, conf_threshold=0.5)
    assert len(pairs) == 2
    assert pairs[0][0][0, 0] < head.image_size[1] / 2 < pairs[1][0][0, 0]
    assert pairs[0][1] == pytest.approx(SOFTMAX_2, abs=1e-6)
    assert pairs[1][1] == pytest.approx(SOFTMAX_1, abs=1e-6)


def test_ufld_score_is_the_mean_probability_of_the_chosen_cells():
    head = _model("ufld").head
    raw = _raw("ufld")
    logits = raw["cls_logits"]
    cells, rows = head.num_cells, logits.shape[2]
    logits[:] = 0.0
    logits[:, cells] = 10.0  # no lane anywhere ...
    # ... but slot 1 on every row (cell 3 * cells // 4 at 4.0), slot 0 on the lower half (cell cells // 4: 3.0)
    logits[0, cells, :, 1] = 0.0
    logits[0, 3 * cells // 4, :, 1] = 4.0
    logits[0, cells, rows // 2:, 0] = 0.0
    logits[0, cells // 4, rows // 2:, 0] = 3.0
    prob = {k: math.exp(k) / (math.exp(k) + cells) for k in (3.0, 4.0)}  # the chosen cell's, cells + no lane
    for writer in (None, "tusimple", "culane"):
        pairs = _decoded("ufld", raw, min_points=2, official_writer=writer)
        assert len(pairs) == 2
        assert pairs[0][0][0, 0] < head.image_size[1] / 2 < pairs[1][0][0, 0]
        assert pairs[0][1] == pytest.approx(prob[3.0], abs=1e-6)
        assert pairs[1][1] == pytest.approx(prob[4.0], abs=1e-6)
    # a lane whose rows differ: the mean over its rows
    logits[0, 3 * cells // 4, 0, 1] = 3.0
    pairs = _decoded("ufld", raw, min_points=2)
    assert pairs[1][1] == pytest.approx((prob[3.0] + (rows - 1) * prob[4.0]) / rows, abs=1e-6)


def test_ganet_score_is_the_start_keypoints_heatmap_value():
    head = _model("ganet").head
    hf, wf = head.fmap_size
    heatmap, offsets, error = torch.zeros(1, 1, hf, wf), torch.zeros(1, 2, hf, wf), torch.zeros(1, 2, hf, wf)
    # two vertical lanes of keypoints, their start (bottom) cells 0.9 (right) and 0.7 (left), the others 0.5
    for col, start_value in ((int(0.75 * wf), 0.9), (int(0.25 * wf), 0.7)):
        heatmap[0, 0, :, col] = 0.5
        heatmap[0, 0, hf - 1, col] = start_value
        offsets[0, 1, :, col] = (hf - 1) - torch.arange(hf, dtype=torch.float32)  # to the start, in cells
    raw = {"heatmap": heatmap, "offsets": offsets, "error": error}
    pairs = _decoded("ganet", raw, kpt_threshold=0.4, root_threshold=1.0, min_points=2)
    assert len(pairs) == 2
    assert pairs[0][0][0, 0] < head.image_size[1] / 2 < pairs[1][0][0, 0]
    assert pairs[0][1] == pytest.approx(0.7, abs=1e-6)
    assert pairs[1][1] == pytest.approx(0.9, abs=1e-6)
