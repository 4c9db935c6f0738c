"""Augmentation moves lanes with the image; batches carry what training and scoring need."""

from __future__ import annotations

import albumentations as A
import cv2
import numpy as np
import torch

from lanevil_train.data.datamodule import collate_lanes
from lanevil_train.data.transforms import LaneSampleProcessor, apply_pipeline, build_pipeline
from lanevil_train.models.detector import LaneDetector


def _painted_sample(height: int = 180, width: int = 320) -> dict:
    """Dark image with three bright painted lanes; the lanes are their centre lines."""
    image = np.full((height, width, 3), 40, np.uint8)
    ys = np.arange(height - 1, height * 0.4, -2.0)
    lanes = []
    for x_bottom, slope in ((60.0, 0.8), (160.0, 0.0), (260.0, -0.8)):
        lane = np.stack([x_bottom + slope * (height - 1 - ys), ys], 1)
        pts = np.round(lane).astype(np.int32)
        cv2.polylines(image, [pts.reshape(-1, 1, 2)], False, (230, 230, 230), thickness=7)
        lanes.append(lane)
    return {"image": image, "lanes": lanes, "meta": {"case_id": "x", "height": height, "width": width}}


def _fraction_on_paint(image: np.ndarray, lanes: list[np.ndarray]) -> float:
    pts = np.concatenate(lanes)
    h, w = image.shape[:2]
    xs = np.clip(np.round(pts[:, 0]).astype(int), 0, w - 1)
    ys = np.clip(np.round(pts[:, 1]).astype(int), 0, h - 1)
    return float(np.mean(image[ys, xs].mean(axis=1) > 120))


def test_train_augmentation_moves_lanes_with_the_image():
    sample = _painted_sample()
    pipeline = build_pipeline((90, 160), augment=True)
    for seed in range(25):
        pipeline.set_random_seed(seed)
        image, lanes = apply_pipeline(pipeline, sample["image"], sample["lanes"])
        assert image.shape == (90, 160, 3)
        assert 1 <= len(lanes) <= 3
        assert _fraction_on_paint(image, lanes) > 0.97, seed
        bottoms = [lane[0, 0] for lane in lanes]
        assert bottoms == sorted(bottoms)  # left to right, also after a flip
        for lane in lanes:
            assert np.all(np.diff(lane[:, 1]) <= 0)  # y descending


def test_flip_reverses_order_and_mirrors_x():
    sample = _painted_sample()
    flip = A.Compose([A.HorizontalFlip(p=1.0)],
                     keypoint_params=A.KeypointParams(format="xy", label_fields=["lane_ids"]))
    image, lanes = apply_pipeline(flip, sample["image"], sample["lanes"])
    assert np.array_equal(image, sample["image"][:, ::-1])
    assert _fraction_on_paint(image, lanes) > 0.99
    # the rightmost lane before the flip is the leftmost after it
    np.testing.assert_allclose(lanes[0][:, 1], sample["lanes"][2][:, 1])
    assert lanes[0][0, 0] < lanes[1][0, 0] < lanes[2][0, 0]


def test_eval_processor_only_resizes_and_keeps_original_ground_truth():
    sample = _painted_sample()
    seen = []

    def encode(lanes, meta):
        seen.append(lanes)
        assert meta is sample["meta"]
        return {"rows": np.zeros((4, 3), np.float32), "count": np.array(len(lanes))}

    item = LaneSampleProcessor((90, 160), augment=False, encode=encode)(sample)
    assert item["image"].shape == (3, 90, 160) and item["image"].dtype == np.float32
    assert item["lanes"] is sample["lanes"]  # scored against the original-size ground truth
    for small, big in zip(seen[0], sample["lanes"]):
        np.testing.assert_allclose(small, big * 0.5, atol=0.51)  # resize by exactly one half
    batch = collate_lanes([item, item])
    assert tuple(batch["images"].shape) == (2, 3, 90, 160)
    assert tuple(batch["targets"]["rows"].shape) == (2, 4, 3)  # each key stacked on its own
    assert batch["targets"]["count"].tolist() == [3, 3]
    assert len(batch["lanes"]) == 2 and batch["meta"][1]["case_id"] == "x"


class _EchoHead(torch.nn.Module):
    """A head whose decode returns fixed lanes in input pixels: isolates the detector's mapping back."""

    def __init__(self, lanes):
        super().__init__()
        self.lanes = lanes

    def forward(self, features):
        return {}

    def decode(self, raw):
        return [self.lanes]


def test_predicted_lanes_map_back_through_crop_and_resize():
    sample = _painted_sample(height=180, width=320)
    processor = LaneSampleProcessor((54, 160), augment=False, crop_top=0.4)
    item = processor(sample)
    assert item["image"].shape == (3, 54, 160)
    cut = 72  # 0.4 * 180
    for lane in item["input_lanes"]:
        assert lane[:, 1].min() >= 0
    detector = LaneDetector(torch.nn.Identity(), _EchoHead(item["input_lanes"]), crop_top=0.4)
    back = detector.predict_lanes(torch.zeros(1, 3, 54, 160), [(180, 320)])[0]
    assert len(back) == 3
    for mapped, original in zip(back, sample["lanes"]):
        kept = original[original[:, 1] >= cut]
        np.testing.assert_allclose(mapped, kept, atol=1.0)
