"""UFLD v1: constructed classifier outputs decoded by our head (model.decode.official_writer) and by the official
test writers' formulas, written out here from their facts (cfzd/Ultra-Fast-Lane-Detection 353df10,
evaluation/eval_wrapper.py: generate_tusimple_lines l. 64-83, generate_lines l. 9-45; models/ufld/codec.py), give
the same TuSimple rows (-2 pattern included) and the same CULane points."""

from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from lanevil_train.lanes import lanes_to_rows
from lanevil_train.models.ufld import UFLDHead

CHANNELS, STRIDES = [128, 256, 512], [8, 16, 32]
INPUT = (288, 800)
CONF = Path(__file__).resolve().parents[2] / "lanevil_train" / "conf"
TUSIMPLE_ROWS = np.arange(160, 711, 10, dtype=np.float64)  # the official writer's h_samples, l. 99-102


def _head(num_cells: int, row_anchors: str) -> UFLDHead:
    return UFLDHead(CHANNELS, STRIDES, INPUT, num_cells=num_cells, row_anchors=row_anchors, max_lanes=4,
                    hidden_dim=4, use_aux=False)


def _lane_logits(num_cells: int, rows: int, lanes: list[tuple[np.ndarray, np.ndarray]], seed: int) -> np.ndarray:
    """(num_cells + 1, rows, 4) float32 logits: per lane a bump over the cells around mu (its mass between cells),
    the no-lane class below the peak where `present`, above it elsewhere; plus noise."""
    rng = np.random.default_rng(seed)
    logits = rng.normal(0.0, 0.3, (num_cells + 1, rows, 4))
    cells = np.arange(num_cells)[:, None]
    for k, (mu, present) in enumerate(lanes):
        bump = -((cells - mu[None, :]) ** 2) / (2 * 1.3 ** 2)
        logits[:num_cells, :, k] += bump - bump.max(axis=0) + 6.0
        logits[num_cells, :, k] += np.where(present, 3.0, 9.0)
    return logits.astype(np.float32)


def _softmax_over_cells(out: np.ndarray) -> np.ndarray:
    """The official scipy.special.softmax(out[:-1], axis=0) on float32 logits (float32 result)."""
    cells = out[:-1]
    e = np.exp(cells - cells.max(axis=0, keepdims=True))
    return e / e.sum(axis=0, keepdims=True)


def official_tusimple_lanes(out: np.ndarray) -> list[list[int]]:
    """generate_tusimple_lines: one list per lane of one value per row anchor; -2 where the arg-max over all
    classes is the no-lane class, else round((loc + 0.5) * 1280 / (G - 1)), loc the expected cell index from 0."""
    griding = out.shape[0] - 1
    arg = out.argmax(axis=0)
    loc = (_softmax_over_cells(out) * np.arange(griding).reshape(-1, 1, 1)).sum(axis=0)
    return [[-2 if arg[r, k] == griding else int(round((loc[r, k] + 0.5) * 1280.0 / (griding - 1)))
             for r in range(out.shape[1])] for k in range(out.shape[2])]


def official_culane_lanes(out: np.ndarray) -> list[list[tuple[int, int]]]:
    """generate_lines (localization 'rel', flip_updown, a 288x800 input): rows bottom first, cells from 1, 0 on a
    no-lane row; lanes with more than 2 points; points (int(loc * 799 / (G - 1) * 1640 / 800) - 1, 590 - 20 k - 1)."""
    griding = out.shape[0] - 1
    out = out[:, ::-1, :]
    loc = (_softmax_over_cells(out) * (np.arange(griding) + 1).reshape(-1, 1, 1)).sum(axis=0)
    loc[out.argmax(axis=0) == griding] = 0
    col_w = np.linspace(0, 800 - 1, griding)[1]
    lanes = []
    for i in range(out.shape[2]):
        if np.sum(loc[:, i] != 0) > 2:
            lanes.append([(int(loc[k, i] * col_w * 1640 / 800) - 1, int(590 - k * 20) - 1)
                          for k in range(out.shape[1]) if loc[k, i] > 0])
    return lanes


def _to_original(lanes: list[np.ndarray], size: tuple[int, int]) -> list[np.ndarray]:
    """LaneDetector.decode_lanes' mapping (no crop), then the records' rounding."""
    h, w = size
    return [np.round(lane * np.array([w / INPUT[1], h / INPUT[0]]), 2) for lane in lanes]


def _tusimple_cases() -> list[tuple[np.ndarray, np.ndarray]]:
    """A lane that ends at the left edge, one with no-lane rows inside it, one of a single row, one running into
    the last cell (its x past the right edge)."""
    t = np.linspace(0.0, 1.0, 56)
    left = 40.0 - 50.0 * t
    holed = 46.0 - 18.0 * t
    right = 60.0 + 50.0 * t
    single = np.full(56, 70.0)
    return [(left, (t >= 0.1) & (left > -0.3)), (holed, (t >= 0.07) & ~((t > 0.5) & (t < 0.56))),
            (single, np.arange(56) == 30), (right, t >= 0.05)]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_tusimple_rows_are_the_official_writers(seed):
    out = _lane_logits(100, 56, _tusimple_cases(), seed)
    official = official_tusimple_lanes(out)
    head = _head(100, "tusimple")
    lanes = head.decode({"cls_logits": torch.from_numpy(out)[None]}, min_points=1, extend_ends=False,
                        official_writer="tusimple")[0]
    ours = lanes_to_rows(_to_original(lanes, (720, 1280)), TUSIMPLE_ROWS, "points")
    # as sets, leaving out the lanes the official writes all -2
    assert sorted(map(list, ours.tolist())) == sorted(lane for lane in official if any(x >= 0 for x in lane))
    flat = [x for lane in official for x in lane]
    assert max(flat) > 1279, "the case must run past the right edge"
    assert any(-2 in lane[lane.index(next(x for x in lane if x >= 0)):] and lane[-1] >= 0 for lane in official), \
        "the case must hold a no-lane row inside a lane"


def test_tusimple_ours_differs_where_the_issue_says():
    """Our own decoding (the project's configs) fills the hole rows, extends the ends and clips at the right edge;
    the official writer's decoding does none of them."""
    out = _lane_logits(100, 56, _tusimple_cases(), 0)
    head = _head(100, "tusimple")
    raw = {"cls_logits": torch.from_numpy(out)[None]}
    official = {tuple(lane) for lane in official_tusimple_lanes(out) if any(x >= 0 for x in lane)}
    ours = lanes_to_rows(_to_original(head.decode(raw)[0], (720, 1280)), TUSIMPLE_ROWS, "linear")
    assert {tuple(lane) for lane in ours.tolist()} != official
    assert float(ours.max()) <= 1279.0


@pytest.mark.parametrize("seed", [0, 3])
def test_culane_points_are_the_official_writers(seed):
    t = np.linspace(0.0, 1.0, 18)
    g = 2.0  # in TuSimple's 100-cell units
    cases = [(g * (40.0 - 50.0 * t), (t >= 0.1) & (g * (40.0 - 50.0 * t) > -0.3)),
             (g * (46.0 - 18.0 * t), (t >= 0.07) & (np.arange(18) != 9)),
             (g * (54.0 + 22.0 * t), (np.arange(18) >= 11) & (np.arange(18) <= 12)),  # 2 points: not written
             (g * (60.0 + 50.0 * t), t >= 0.05)]
    out = _lane_logits(200, 18, cases, seed)
    official = official_culane_lanes(out)
    assert len(official) == 3
    head = _head(200, "culane")
    lanes = head.decode({"cls_logits": torch.from_numpy(out)[None]}, min_points=3, extend_ends=False,
                        official_writer="culane")[0]
    ours = [[(float(x), float(y)) for x, y in lane] for lane in _to_original(lanes, (590, 1640))]  # bottom first
    assert sorted(ours) == sorted([(float(x), float(y)) for x, y in lane] for lane in official)
    assert max(x for lane in official for x, _ in lane) > 1639, "the case must run past the right edge"


def test_the_official_experiments_decode_as_the_official_writers():
    tusimple = OmegaConf.load(CONF / "experiment" / "official_ufld_tusimple.yaml").model
    assert tusimple.row_sampling == "points"
    assert dict(tusimple.decode) == {"official_writer": "tusimple", "min_points": 1, "extend_ends": False}
    culane = OmegaConf.load(CONF / "experiment" / "official_ufld_culane.yaml").model
    assert dict(culane.decode) == {"official_writer": "culane", "min_points": 3, "extend_ends": False}
    ours = OmegaConf.load(CONF / "model" / "ufld.yaml")
    assert ours.decode.official_writer is None and ours.decode.extend_ends is True


def test_unknown_writer_is_refused():
    head = _head(100, "tusimple")
    with pytest.raises(ValueError, match="official_writer"):
        head.decode({"cls_logits": torch.zeros(1, 101, 56, 4)}, official_writer="culane_v2")
