"""Attention-area extraction and mixing on constructed maps with known answers (paper §4.1)."""

import numpy as np
import pytest
import torch

from lanevil_train.callbacks.regions import (
    HAA,
    LAA,
    Box,
    attention_masks,
    blend_region,
    blur_and_normalise,
    choose_place,
    extract_regions,
    grad_cam,
    hard_examples,
    lane_mask,
    mismatched_regions,
    target_area,
)


def blob_map(shape=(60, 100)):
    """Two bright rectangles (rows 10:20 x cols 10:30, rows 40:50 x cols 60:90) on zero, plus a 1-pixel speck."""
    m = np.zeros(shape, dtype=np.float32)
    m[10:20, 10:30] = 1.0
    m[40:50, 60:90] = 0.9
    m[5, 95] = 1.0
    return m


def test_exact_boxes_for_known_blobs():
    m = blob_map()
    gt = np.zeros(m.shape, dtype=bool)
    regions = extract_regions(m, gt, (HAA,), sigma=0.0, t_haa=0.6, t_laa=0.4, min_area=5 / m.size,
                              overlap_threshold=0.2)
    assert sorted(regions[HAA], key=lambda b: b.x0) == [Box(10, 10, 30, 20), Box(60, 40, 90, 50)]


def test_components_no_larger_than_s_are_dropped():
    m = blob_map()
    gt = np.zeros(m.shape, dtype=bool)
    # the 10x20 blob has 200 pixels, the 10x30 one 300: S = 200 pixels keeps only the larger (area > S)
    boxes = mismatched_regions(m > 0.6, gt, min_area=200 / m.size, overlap_threshold=0.2)
    assert boxes == [Box(60, 40, 90, 50)]


def test_overlap_with_the_lane_mask_filters_regions():
    m = blob_map()
    gt = np.zeros(m.shape, dtype=bool)
    gt[:, 12:18] = True  # a lane through the first blob: 6 of its 20 columns = 30 % overlap
    kept = mismatched_regions(m > 0.6, gt, min_area=5 / m.size, overlap_threshold=0.2)
    assert kept == [Box(60, 40, 90, 50)]
    kept = mismatched_regions(m > 0.6, gt, min_area=5 / m.size, overlap_threshold=0.31)
    assert sorted(kept, key=lambda b: b.x0) == [Box(10, 10, 30, 20), Box(60, 40, 90, 50)]


def test_low_attention_regions_and_thresholds():
    m = np.full((40, 40), 0.5, dtype=np.float32)
    m[0:10, 0:40] = 0.0     # low band at the top
    m[30:40, 0:40] = 1.0    # high band at the bottom
    masks = attention_masks(blur_and_normalise(m, 0.0), t_haa=0.6, t_laa=0.4)
    assert masks[HAA].sum() == 400 and masks[HAA][30:].all()
    assert masks[LAA].sum() == 400 and masks[LAA][:10].all()
    regions = extract_regions(m, np.zeros_like(m, dtype=bool), (HAA, LAA), 0.0, 0.6, 0.4, 0.01, 0.2)
    assert regions == {HAA: [Box(0, 30, 40, 40)], LAA: [Box(0, 0, 40, 10)]}


def test_blur_then_normalise_spans_zero_to_one():
    m = blob_map()
    out = blur_and_normalise(m, 3.0)
    assert out.min() == 0.0 and out.max() == pytest.approx(1.0)
    assert out[15, 20] > 0.6 > out[30, 50]
    assert not blur_and_normalise(np.ones((5, 5)), 1.0).any()  # a flat map has no attention areas


def test_lane_mask_draws_the_polyline_with_its_width():
    lanes = [np.array([[20.0, 59.0], [20.0, 0.0]])]
    mask = lane_mask(lanes, (60, 40), width=3)
    assert mask[:, 19:22].all() and mask.sum() == 60 * 3


def test_grad_cam_weights_channels_by_the_negative_mean_gradient():
    act = torch.zeros(1, 2, 4, 4)
    act[0, 0, 1, 1] = 2.0
    act[0, 1, 2, 3] = 5.0
    grad = torch.zeros(1, 2, 4, 4)
    grad[0, 0] = -1.0   # lowering the loss: channel 0 is evidence (weight +1)
    grad[0, 1] = 1.0    # raising it: channel 1 is clipped away by the ReLU
    cam = grad_cam(act, grad)
    expected = torch.zeros(1, 4, 4)
    expected[0, 1, 1] = 2.0
    assert torch.equal(cam, expected)


def test_blend_changes_only_the_box_with_the_beta_blend():
    torch.manual_seed(0)
    image = torch.rand(3, 20, 30)
    before = image.clone()
    patch = torch.rand(3, 6, 8)
    box = Box(5, 4, 13, 10)
    blend_region(image, patch, box, beta=0.5)
    inside = image[:, 4:10, 5:13].clone()
    assert torch.allclose(inside, 0.5 * before[:, 4:10, 5:13] + 0.5 * patch)
    outside = torch.ones(20, 30, dtype=torch.bool)
    outside[4:10, 5:13] = False
    assert torch.equal(image[:, outside], before[:, outside])
    blend_region(image, patch, box, beta=0.25)
    assert torch.allclose(image[:, 4:10, 5:13], 0.75 * inside + 0.25 * patch)


def test_target_areas_are_off_lane_for_haa_and_on_lane_for_laa():
    gt = lane_mask([np.array([[50.0, 59.0], [50.0, 0.0]])], (60, 100), width=3)
    low = target_area(gt, HAA, sigma=3.0, t_haa=0.6, t_laa=0.4)
    high = target_area(gt, LAA, sigma=3.0, t_haa=0.6, t_laa=0.4)
    assert high[:, 50].all() and not high[:, :40].any() and not high[:, 60:].any()
    assert low[:, :40].all() and not low[:, 50].any()
    rng = np.random.default_rng(0)
    for _ in range(20):
        box = choose_place(low, 10, 20, rng)
        assert low[box.y0:box.y1, box.x0:box.x1].all()
        box = choose_place(high, 10, 8, rng)
        assert box.x0 <= 50 < box.x1  # the region goes over the lane
    with pytest.raises(ValueError, match="kind"):
        target_area(gt, "mid", 3.0, 0.6, 0.4)


def test_place_of_a_region_larger_than_the_image_is_clipped():
    box = choose_place(np.ones((10, 10), dtype=bool), 15, 4, np.random.default_rng(1))
    assert (box.height, box.width) == (10, 4) and box.y0 == 0


def test_hard_examples_are_below_the_mean_accuracy_or_above_the_mean_loss():
    acc = np.array([0.9, 0.5, 0.7, 0.95])
    assert hard_examples(acc, acc.mean(), higher_is_harder=False).tolist() == [1, 2]
    loss = np.array([0.1, 2.0, 0.3, 1.5])
    assert hard_examples(loss, loss.mean(), higher_is_harder=True).tolist() == [1, 3]
    assert hard_examples(np.zeros(4), 0.0, higher_is_harder=False).tolist() == []
