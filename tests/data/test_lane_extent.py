"""Lanes outside the image: cut at the border (not an albumentations crash), labels for another image
size refused when read, too many lanes for max_lanes refused before training; errors name the sample."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from lanevil_train.data.datamodule import LaneDataModule, ProcessedDataset, check_lane_counts
from lanevil_train.data.datasets import CULaneDataset, TuSimpleDataset
from lanevil_train.data.formats import write_culane
from lanevil_train.data.transforms import LaneSampleProcessor, clip_lane_to_image
from lanevil_train.lanes import scale_lanes
from lanevil_train.models.laneatt.anchors import encode_lanes

H, W = 180, 320           # image
INPUT = (64, 160)         # network input (H, W)
N_OFFSETS = 16


class _Head:
    """Stands in for the LaneATT head: `encode` is a bound method of an object with max_lanes."""

    def __init__(self, max_lanes: int = 6):
        self.max_lanes = max_lanes

    def encode(self, lanes, meta=None):
        return {"lanes": encode_lanes(lanes, INPUT, N_OFFSETS, self.max_lanes)}


def _culane_lanes() -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Two straight lanes as CULane writes them (rows every 10 px from y = H, the bottom edge), one
    starting at x = -12.5 and one at x = W + 200; and the same lanes without their out-of-image points."""
    ys = np.arange(H, 79, -10.0)
    left = np.stack([-12.5 + 1.25 * (H - ys), ys], 1)        # crosses x = 0 at the point (0, 170)
    right = np.stack([W + 200 - 21.0 * (H - ys[:3]), ys[:3]], 1)  # (520, 180), (310, 170), (100, 160)
    middle = np.stack([160.0 + 0.0 * ys[1:], ys[1:] - 1], 1)  # inside
    inside = lambda lane: lane[(lane[:, 0] >= 0) & (lane[:, 0] < W) & (lane[:, 1] < H)]  # noqa: E731
    return [left, middle, right], [inside(left), middle, inside(right)]


def _sample(lanes) -> dict:
    image = np.full((H, W, 3), 60, np.uint8)
    return {"image": image, "lanes": lanes, "meta": {"case_id": "c", "source": "list.txt:3"}}


def test_clip_lane_cuts_at_the_border_by_interpolation():
    lane = np.array([[-20.0, 180.0], [0.0, 160.0], [40.0, 120.0]])
    assert np.array_equal(clip_lane_to_image(lane, H, W), lane[1:])  # the crossing is a point already
    lane = np.array([[400.0, 180.0], [300.0, 160.0], [200.0, 140.0]])
    cut = clip_lane_to_image(lane, H, W)
    assert cut.shape == (3, 2) and np.allclose(cut[0], [W, 164.0], atol=1e-2) and cut[0, 0] < W
    assert np.array_equal(cut[1:], lane[1:])
    inside = np.array([[10.0, 170.0], [20.0, 100.0]])
    assert clip_lane_to_image(inside, H, W) is not None and np.array_equal(clip_lane_to_image(inside, H, W), inside)
    assert clip_lane_to_image(np.array([[-50.0, 170.0], [-40.0, 100.0]]), H, W).shape == (0, 2)


@pytest.mark.parametrize("augment", [False, True])
def test_out_of_image_points_go_through_the_processor(augment):
    lanes, without = _culane_lanes()
    head = _Head()
    processor = LaneSampleProcessor(INPUT, augment, head.encode)
    for seed in range(4 if augment else 1):
        np.random.seed(seed)
        item = processor(_sample(lanes))
        assert item["target"]["lanes"].shape == (6, 3 + N_OFFSETS)
        assert item["lanes"] is not None and len(item["lanes"]) == 3  # the labels as given, for scoring
    if augment:
        return
    # eval semantics: the lane is cut where it leaves the image; for these straight lanes that encodes the
    # same as the lane without its out-of-image points (the encoder extends a lane down along its line)
    reference = processor(_sample(without))
    assert np.allclose(item["target"]["lanes"], reference["target"]["lanes"], atol=1e-2)
    # and the geometry after the resize is the cut lane, scaled
    expected = scale_lanes([clip_lane_to_image(lane, H, W) for lane in lanes], INPUT[1] / W, INPUT[0] / H)
    expected.sort(key=lambda lane: lane[0, 0])
    assert len(item["input_lanes"]) == 3
    for got, want in zip(item["input_lanes"], expected):
        assert np.allclose(got, want, atol=1e-3)


def _write_image(path, height=H, width=W):
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((height, width, 3), 90, np.uint8))


def test_culane_lanes_outside_the_image_train_and_evaluate(tmp_path):
    lanes, _ = _culane_lanes()
    _write_image(tmp_path / "d/0.jpg")
    write_culane([{"rel_path": "d/0.jpg", "lanes": lanes}], tmp_path, tmp_path / "list.txt")
    data = CULaneDataset(tmp_path, "list.txt")
    dm = LaneDataModule(data, data, None, input_size=INPUT, batch_size=1, encode=_Head().encode)
    for loader in (dm.train_dataloader(), dm.val_dataloader()):
        batch = next(iter(loader))
        assert batch["targets"]["lanes"].shape == (1, 6, 3 + N_OFFSETS)
        assert batch["meta"][0]["source"] == f"{tmp_path / 'list.txt'}:1"


def _tusimple(tmp_path, lanes_xs, h_samples, height=H, width=W):
    _write_image(tmp_path / "clips/a.jpg", height, width)
    label = tmp_path / "label.json"
    label.write_text(json.dumps({"lanes": lanes_xs, "h_samples": h_samples, "raw_file": "clips/a.jpg"}) + "\n")
    return label


def test_labels_for_another_image_size_are_refused_when_read(tmp_path):
    ys = list(range(160, 720, 10))  # TuSimple's rows at 1280x720, for a 320x180 image
    label = _tusimple(tmp_path, [[600 + 0 * y for y in ys], [700 for _ in ys]], ys)
    data = TuSimpleDataset(tmp_path, "label.json")
    with pytest.raises(ValueError) as info:
        data[0]
    message = str(info.value)
    assert message.startswith(f"{label}:1: lanes[0] does not fit the 320x180 image: ")
    assert "none of its 56 points lies in the image (320 wide, 180 high): they span x 600.0..600.0, y 160.0..710.0" \
        in message and "every point within x -320..640, y -3.6..183.6" in message
    assert "Are the lanes for another image size" in message


def test_culane_overshoot_within_the_margin_is_accepted(tmp_path):
    ys = list(range(100, 180, 10))
    # x from 200 at the top row to 620 (W + 300, within the W margin) at the bottom one
    _tusimple(tmp_path, [[100 - 10 * i for i in range(len(ys))], [200 + 60 * i for i in range(len(ys))]], ys)
    assert len(TuSimpleDataset(tmp_path, "label.json")[0]["lanes"]) == 2


def _ten_lanes(tmp_path):
    ys = list(range(100, 180, 10))
    return _tusimple(tmp_path, [[10 + 30 * j for _ in ys] for j in range(10)], ys)


def test_too_many_lanes_refused_before_training(tmp_path):
    label = _ten_lanes(tmp_path)
    data = TuSimpleDataset(tmp_path, "label.json")
    with pytest.raises(ValueError) as info:
        LaneDataModule(data, None, None, input_size=INPUT, encode=_Head(6).encode)
    assert str(info.value).startswith(f"{label}:1: 10 lanes, but data.max_lanes=6 (the model head's max_lanes)")
    assert "Raise data.max_lanes to at least 10" in str(info.value)
    LaneDataModule(data, None, None, input_size=INPUT, encode=_Head(10).encode)  # enough
    check_lane_counts(None, 1)  # no dataset, nothing to check


def test_errors_while_processing_name_the_sample(tmp_path):
    label = _ten_lanes(tmp_path)
    data = TuSimpleDataset(tmp_path, "label.json")
    # an encoder with no visible max_lanes: the pre-flight check cannot run, the sample's error names it
    encode = lambda lanes, meta: {"lanes": encode_lanes(lanes, INPUT, N_OFFSETS, 6)}  # noqa: E731
    processed = ProcessedDataset(data, LaneSampleProcessor(INPUT, False, encode))
    with pytest.raises(ValueError) as info:
        processed[0]
    assert str(info.value).startswith(f"{label}:1: encode: 10 lanes inside the 160x64 image but max_lanes=6")
