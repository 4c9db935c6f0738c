import pytest
import torch

from lanevil_train.models.sampling import sample_at


def test_sample_at_reads_cells_and_interpolates_between_them():
    # a stride-4 map of a 9x13 image (3x4 cells under align_corners: pixel 0 -> cell 0, pixel 12 -> cell 3)
    fmap = torch.arange(12, dtype=torch.float32).reshape(1, 1, 3, 4)
    xs = torch.tensor([[0.0, 12.0, 4.0, 2.0, 0.0]])
    ys = torch.tensor([[0.0, 8.0, 4.0, 0.0, 2.0]])
    values = sample_at(fmap, xs, ys, (9, 13))
    assert values.shape == (1, 1, 5)
    # (row, col) = (0, 0) -> 0; (2, 3) -> 11; (1, 1) -> 5; (0, 0.5) -> 0.5; (0.5, 0) -> 2
    assert values[0, 0].tolist() == pytest.approx([0.0, 11.0, 5.0, 0.5, 2.0])


def test_sample_at_keeps_point_shape_channels_and_zero_outside():
    fmap = torch.ones(2, 3, 5, 5)
    xs = torch.full((2, 4, 6), 2.0)
    xs[1, 0, 0] = -50.0
    values = sample_at(fmap, xs, torch.full((2, 4, 6), 2.0), (5, 5))
    assert values.shape == (2, 3, 4, 6)
    assert values[0].min() == 1.0 and values[1, :, 0, 0].abs().max() == 0.0


def test_sample_at_bad_shapes():
    with pytest.raises(ValueError, match="share a shape"):
        sample_at(torch.zeros(1, 1, 2, 2), torch.zeros(1, 3), torch.zeros(1, 4), (8, 8))
