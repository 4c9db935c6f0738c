"""SCNN's official decoding (experiment=official_scnn_*): constructed logits and existences decoded by our head with
the experiment's decode settings, mapped to the original image as LaneDetector does and written as the prediction
files write them, against pytorch-auto-drive's decoding written out here from the facts (models/scnn/codec.py:
utils/lane_det_utils.py at 137e63a): per existing slot (sigmoid > 0.5, at most max_lane, the least confident dropped)
the probability map box-blurred 9x9 with the border replicated; on row ``int(h - (56 - i) * 10 / 720 * h)``
(TuSimple) or ``int(h - i * 20 / 590 * h - 1)`` (CULane) the first argmax column ``c`` is the point ``int(c / w * W)``
when the blurred value there is above 0.3; x = 0 is no point; a lane needs 2 points; written at y = 160 + 10 i
(TuSimple, -2 where none) or 589 - 20 i (CULane, points only)."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch

from lanevil_train.evaluation.prediction_files import prediction_fields, tusimple_line
from lanevil_train.lanes import culane_lanes
from lanevil_train.models.detector import LaneDetector
from lanevil_train.models.nms import prune_lanes
from lanevil_train.models.scnn import SCNNHead
from lanevil_train.models.scnn.codec import OFFICIAL_WRITERS, official_rows
from tests.tasks.cli_helpers import composed

TUSIMPLE = {"experiment": "official_scnn_tusimple", "input": (360, 640), "original": (720, 1280), "slots": 6}
CULANE = {"experiment": "official_scnn_culane", "input": (288, 800), "original": (590, 1640), "slots": 4}


# ---------------------------------------------------------------------------------------------- the official side
def official_existing(conf: np.ndarray, max_lane: int) -> np.ndarray:
    """sigmoid > 0.5; while more than max_lane exist, set every slot at the lowest confidence of all (absent ones
    included, those first) to absent and its confidence to 1.1."""
    exist, conf = conf > 0.5, conf.astype(np.float64).copy()
    while exist.sum() > max_lane:
        lowest = conf == conf.min()
        exist[lowest] = False
        conf[lowest] = 1.1
    return exist


def official_points(probs: np.ndarray, exist: np.ndarray, dataset: str) -> list[list[tuple[float, float]]]:
    """probs (classes, h, w) after the softmax: per lane, its (x, y) per row in the original image, x = -2 where
    it has no point (the CULane writer keeps only the points)."""
    _, h, w = probs.shape
    if dataset == "tusimple":
        big_h, big_w, gap, ppl = 720, 1280, 10, 56
    else:
        big_h, big_w, gap, ppl = 590, 1640, 20, 18
    lanes = []
    for k in range(1, probs.shape[0]):
        if not exist[k - 1]:
            continue
        blurred = cv2.blur(probs[k], (9, 9), borderType=cv2.BORDER_REPLICATE)
        xs = np.zeros(ppl)
        for i in range(ppl):
            row = int(h - (ppl - i) * gap / big_h * h) if dataset == "tusimple" else int(h - i * gap / big_h * h - 1)
            column = int(np.argmax(blurred[row]))
            if blurred[row, column] > 0.3:
                xs[i] = int(column / w * big_w)
        if (xs > 0).sum() < 2:
            continue
        ys = [big_h - (ppl - i) * gap if dataset == "tusimple" else big_h - i * gap - 1 for i in range(ppl)]
        lanes.append([(float(x) if x > 0 else -2.0, float(y)) for x, y in zip(xs, ys)])
    return lanes


# ----------------------------------------------------------------------------------------------------- our side
def _setting(dataset: dict):
    cfg = composed([f"experiment={dataset['experiment']}", "data.root=/unused"])
    head = SCNNHead([8], [8], dataset["input"], max_lanes=dataset["slots"], hidden_channels=4, mp_channels=4,
                    exist_hidden=4)
    return cfg, SimpleNamespace(head=head, decode_kwargs=dict(cfg.model.decode), crop_top=float(cfg.data.crop_top))


def ours_tusimple(probs: torch.Tensor, conf: torch.Tensor) -> list[list[list[float]]]:
    """Per image, the lanes of the TuSimple prediction file (x per h_sample, -2 where none)."""
    cfg, model = _setting(TUSIMPLE)
    raw = {"seg": torch.log(probs), "exist": conf}
    lanes = LaneDetector.decode_lanes(model, raw, TUSIMPLE["input"], [TUSIMPLE["original"]] * len(probs))
    meta = {"height": 720, "width": 1280, "h_samples": list(range(160, 720, 10))}
    return [tusimple_line({**prediction_fields(pred, meta, 0.0, cfg.model.row_sampling), "key": "x"})["lanes"]
            for pred in lanes]


def ours_culane(probs: torch.Tensor, conf: torch.Tensor) -> list[list[list[tuple[float, float]]]]:
    """Per image, the lanes of the .lines.txt (points bottom first, original pixels, as the records keep them)."""
    cfg, model = _setting(CULANE)
    raw = {"seg": torch.log(probs), "exist": conf}
    lanes = LaneDetector.decode_lanes(model, raw, CULANE["input"], [CULANE["original"]] * len(probs))
    out = []
    for pred in lanes:
        fields = prediction_fields(pred, {"height": 590, "width": 1640, "h_samples": []}, 0.0)
        written = culane_lanes([np.asarray(p) for p in fields["pred_points"]], cfg.model.culane_rows,
                               cfg.model.row_sampling, 590, 1640)
        out.append([[(float(x), float(y)) for x, y in lane] for lane in written])
    return out


# ------------------------------------------------------------------------------------------------ the maps
def band(h: int, w: int, centre, sigma: float = 3.0, peak: float = 0.9, rows=None) -> np.ndarray:
    """A lane's probability: a Gaussian across x around centre(y) on the given rows (all by default)."""
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    p = peak * np.exp(-0.5 * ((xs - centre(ys)) / sigma) ** 2)
    if rows is not None:
        p *= rows(ys)
    return p


def softmax(probs: torch.Tensor) -> np.ndarray:
    """The probabilities both sides decode: the softmax of the logits log(probs) (the network's output here)."""
    return torch.softmax(torch.log(probs), dim=1)[0].numpy()


def as_probs(lanes: list[np.ndarray]) -> torch.Tensor:
    """(1, 1 + L, h, w) class probabilities: the lanes' maps (scaled to sum below 1), the background the rest."""
    stack = np.stack(lanes)
    total = stack.sum(0)
    stack = stack / np.maximum(1.0, total / 0.98)
    background = 1.0 - stack.sum(0)
    return torch.tensor(np.concatenate([background[None], stack]), dtype=torch.float32).clamp_min(1e-6)[None]


def tusimple_cases() -> torch.Tensor:
    h, w = TUSIMPLE["input"]
    top, bottom = (lambda y: y < 200), (lambda y: y >= 200)
    return as_probs([
        # leaving at the left edge: the argmax reaches column 0 (no point), then the lane is gone
        band(h, w, lambda y: 150.0 - 0.9 * (y - 80.0), sigma=4.0),
        # dashed: no probability on rows 200-229 (no point inside the lane)
        band(h, w, lambda y: 260.0 - 0.3 * (y - 80.0), rows=lambda y: (y < 200) | (y >= 230)),
        # above row 200 a wide band at 380 beside a 1 px spike at 410: the unblurred argmax is the spike, the blurred
        # one the band; below, a line one column wide: its peak 0.9 is 0.1 blurred, under the threshold: no points
        band(h, w, lambda y: 380.0 + 0.0 * y, sigma=6.0, peak=0.55, rows=top)
        + 0.4 * ((np.arange(w) == 410)[None, :] & top(np.arange(h))[:, None])
        + 0.9 * ((np.arange(w) == 470)[None, :] & bottom(np.arange(h))[:, None]),
        # a clear lane in a slot that does not exist
        band(h, w, lambda y: 330.0 + 0.1 * y),
        # past the right edge: the argmax at the last column, x = 1278
        band(h, w, lambda y: 560.0 + 0.5 * (y - 80.0)),
        # a step between rows 139 and 140: y = 280 reads row 139 (the float arithmetic), x = 2 * 500, not 2 * 530
        band(h, w, lambda y: np.where(y <= 139, 500.0, 530.0), sigma=3.0),
    ])


# ----------------------------------------------------------------------------------------------------- tests
def test_the_official_rows():
    rows, ys = official_rows(OFFICIAL_WRITERS["tusimple"], 360)
    expected = [80 + 5 * i for i in range(56)]
    expected[12] = 139  # 360 - 44 * 10 / 720 * 360 = 139.99999999999997
    assert rows.tolist() == expected and ys.tolist() == list(range(160, 720, 10))
    rows, ys = official_rows(OFFICIAL_WRITERS["culane"], 288)
    assert rows.tolist()[:6] == [287, 277, 267, 257, 247, 238] and len(rows) == 18
    assert ys.tolist() == [589 - 20 * i for i in range(18)]


def test_tusimple_rows_equal_the_official_writer():
    probs = tusimple_cases()
    conf = torch.tensor([[0.9, 0.8, 0.7, 0.3, 0.85, 0.75]])
    ours = ours_tusimple(probs, conf)[0]
    official = official_points(softmax(probs), official_existing(conf[0].numpy(), 5), "tusimple")
    assert sorted(ours) == sorted([x for x, _ in lane] for lane in official)
    assert len(ours) == 5
    by_start = {next(x for x in lane if x >= 0): lane for lane in ours}
    left = by_start[300.0]  # 150 * 2 at y = 160
    blurred = cv2.blur(softmax(probs)[1], (9, 9), borderType=cv2.BORDER_REPLICATE)
    rows = official_rows(OFFICIAL_WRITERS["tusimple"], 360)[0]
    at_edge = [i for i, row in enumerate(rows) if blurred[row].argmax() == 0 and blurred[row, 0] > 0.3]
    assert at_edge and all(left[i] == -2 for i in at_edge)  # the argmax at column 0 is no point
    assert left[at_edge[0] - 1] > 0 and left[-1] == -2
    dashed = by_start[520.0]
    assert dashed[24] == -2 and dashed[23] >= 0 and dashed[30] >= 0  # y = 400 (row 200) inside the dash's gap
    spike = by_start[760.0]  # the blurred band's centre (380), not the spike (410)
    assert set(x for x in spike if x >= 0) == {760.0} and spike[24:] == [-2] * 32  # the thin line gives none
    assert 1278.0 in by_start[1120.0]  # past the right edge
    step = by_start[1000.0]
    assert step[12] == 1000.0 and step[13] == 1060.0  # y = 280 reads row 139


@pytest.mark.parametrize("conf, kept", [
    ([0.9, 0.8, 0.7, 0.95, 0.85, 0.75], 5),  # six exist: max_lane 5 drops the least confident
    ([0.9, 0.6, 0.6, 0.95, 0.85, 0.75], 4),  # two at the lowest: both dropped
])
def test_tusimple_max_lane_drops_the_least_confident(conf, kept):
    probs = tusimple_cases()
    conf = torch.tensor([conf])
    assert prune_lanes(conf.numpy(), conf.numpy() > 0.5, 5).sum() == kept
    ours = ours_tusimple(probs, conf)[0]
    official = official_points(softmax(probs), official_existing(conf[0].numpy(), 5), "tusimple")
    assert sorted(ours) == sorted([x for x, _ in lane] for lane in official)
    assert len(ours) == kept


def test_culane_points_equal_the_official_writer():
    h, w = CULANE["input"]
    probs = as_probs([
        band(h, w, lambda y: 460.0 + 0.0 * y),  # column 460: int(460 / 800 * 1640) = 942, not 943
        band(h, w, lambda y: 120.0 - 0.8 * (287.0 - y), sigma=4.0),  # leaves at the left edge
        band(h, w, lambda y: 700.0 + 0.6 * (287.0 - y)),  # past the right edge: 1637
        band(h, w, lambda y: 300.0 + 0.2 * y, rows=lambda y: (y > 150) & (y < 170)),  # 2 rows: a lane
    ])
    conf = torch.tensor([[0.9, 0.8, 0.7, 0.6]])
    ours = ours_culane(probs, conf)[0]
    official = [[(x, y) for x, y in lane if x > 0]
                for lane in official_points(softmax(probs), conf[0].numpy() > 0.5, "culane")]
    assert sorted(ours) == sorted(official) and len(ours) == 4
    assert next(lane for lane in ours if lane[0][0] == 942.0)[0] == (942.0, 589.0)
    assert any(x == 1637.0 for lane in ours for x, _ in lane)  # int(799 / 800 * 1640)
    assert sorted(len(lane) for lane in ours)[0] == 2


@pytest.mark.parametrize("blur", [0, 9])
def test_our_own_decoding_stays_an_option(blur):
    """official_writer null (the project's configs): every row_step-th row from the bottom, sub-pixel x."""
    _, model = _setting(TUSIMPLE)
    probs = tusimple_cases()
    raw = {"seg": torch.log(probs), "exist": torch.tensor([[0.9, 0.8, 0.7, 0.95, 0.85, 0.75]])}
    lanes = model.head.decode(raw, row_step=5, min_points=2, blur=blur)[0]
    assert lanes and all(lane[0, 1] == 359.0 for lane in lanes if len(lane) > 50)
    assert any(not float(x).is_integer() for lane in lanes for x in lane[:, 0])
