"""BatchAdapter in every documented form: where the images and the lane ground truth sit in a foreign batch."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from lanevil_train.callbacks import BatchAdapter

IMAGES = torch.rand(2, 3, 8, 10)
LANES = [[np.array([[2.0, 7.0], [2.0, 0.0]])], [np.array([[7.0, 7.0], [7.0, 0.0]])]]  # a vertical lane each
MASK = torch.zeros(2, 8, 10, dtype=torch.uint8)
MASK[0, :, 2] = 1
MASK[1, :, 7] = 1


def expected_columns(masks: np.ndarray) -> list[list[int]]:
    return [sorted(set(np.nonzero(m)[1].tolist())) for m in masks]


@pytest.mark.parametrize("adapter, batch", [
    (BatchAdapter(), {"images": IMAGES, "input_lanes": LANES}),
    (BatchAdapter(images="img", lanes="lanes"), {"img": IMAGES, "lanes": LANES}),
    (BatchAdapter(images="img", lane_mask="seg"), {"img": IMAGES, "seg": MASK}),
    (BatchAdapter(images=0, lane_mask=1), (IMAGES, MASK)),
    (BatchAdapter(images=0, lane_mask=1, lanes=None), [IMAGES, MASK[:, None]]),  # (B, 1, H, W) masks too
    (BatchAdapter(images=0, lanes=2), (IMAGES, None, LANES)),
    (BatchAdapter(images=lambda b: b.x, lanes=lambda b: b.lanes), SimpleNamespace(x=IMAGES, lanes=LANES)),
    (BatchAdapter(images=lambda b: b.x, lane_mask=lambda b: b.seg), SimpleNamespace(x=IMAGES, seg=MASK)),
])
def test_every_documented_form_finds_images_and_lanes(adapter, batch):
    assert adapter.images(batch) is IMAGES  # the batch's own tensor: edits to it change the batch
    masks = adapter.lane_masks(batch, (8, 10), width=1)
    assert masks.shape == (2, 8, 10) and masks.dtype == bool
    assert expected_columns(masks) == [[2], [7]]
    assert masks[0, :, 2].all() and masks[1, :, 7].all()


def test_lanes_are_widened_and_a_mask_is_taken_as_is():
    wide = BatchAdapter(images="img", lanes="lanes").lane_masks({"img": IMAGES, "lanes": LANES}, (8, 10), width=3)
    assert expected_columns(wide) == [[1, 2, 3], [6, 7, 8]]
    as_is = BatchAdapter(images="img", lane_mask="seg").lane_masks({"img": IMAGES, "seg": MASK}, (8, 10), width=3)
    assert expected_columns(as_is) == [[2], [7]]


def test_both_lanes_and_mask_is_an_error_naming_both():
    with pytest.raises(ValueError, match="not both.*lanes='lanes', lane_mask='seg'"):
        BatchAdapter(images="img", lanes="lanes", lane_mask="seg")


def test_a_missing_location_names_what_was_expected_where():
    with pytest.raises(KeyError, match=r"lane masks are expected at 'seg' of the dict batch \(keys: \['img'\]\)"):
        BatchAdapter(images="img", lane_mask="seg").lane_masks({"img": IMAGES}, (8, 10), width=1)
    with pytest.raises(ValueError, match=r"must be \(B, H, W\) with \(H, W\) = \(8, 10\)"):
        BatchAdapter(images="img", lane_mask="seg").lane_masks({"img": IMAGES, "seg": MASK[:, :4]}, (8, 10), 1)


@pytest.mark.parametrize("lanes, what", [
    (MASK, r"the lanes at 1 are a \(2, 8, 10\) Tensor, which looks like a lane mask"),
    (MASK[:, None], r"the lanes at 1 are a \(2, 1, 8, 10\) Tensor, which looks like a lane mask"),
    (MASK[0].numpy(), r"the lanes at 1 are a \(8, 10\) ndarray, which looks like a lane mask"),
    ([MASK[0], MASK[1]], r"the lanes of image 0 at 1 are a \(8, 10\) Tensor, which looks like a lane mask"),
])
def test_a_mask_passed_as_lanes_is_refused_and_lane_mask_is_suggested(lanes, what):
    with pytest.raises(ValueError, match=f"BatchAdapter: {what}; lanes must be a list of \\(N, 2\\) x, y "
                                         f"point arrays \\(input pixels\\) per image. "
                                         f"Pass .*as lane_mask=1 instead of lanes=1"):
        BatchAdapter(images=0, lanes=1).lane_masks((IMAGES, lanes), (8, 10), width=1)


@pytest.mark.parametrize("lanes, what", [
    (None, "the lanes at 1 are a NoneType"),
    ([[np.array([2.0, 7.0])]], r"lane 0 of image 0 at 1 is a \(2,\) ndarray"),
    ([LANES[0], [np.zeros((3, 3))]], r"lane 0 of image 1 at 1 is a \(3, 3\) ndarray"),
    ([LANES[0], 5], "the lanes of image 1 at 1 are a int"),
])
def test_lanes_that_are_not_lists_of_point_arrays_are_named(lanes, what):
    with pytest.raises(ValueError, match=f"BatchAdapter: {what}; expected a list of \\(N, 2\\) x, y point arrays"):
        BatchAdapter(images=0, lanes=1).lane_masks((IMAGES, lanes), (8, 10), width=1)


def test_lanes_as_tensors_and_images_without_lanes_are_accepted():
    lanes = [torch.tensor([[[2.0, 7.0], [2.0, 0.0]]]), []]  # image 0: an (L, N, 2) tensor; image 1: no lanes
    masks = BatchAdapter(images=0, lanes=1).lane_masks((IMAGES, lanes), (8, 10), width=1)
    assert expected_columns(masks) == [[2], []]
