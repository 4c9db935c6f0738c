import itertools

import numpy as np
import pytest
import torch

from lanevil_train.models.matching import match, match_batch


def _brute_force(cost: np.ndarray) -> float:
    """The smallest summed cost over every injective map of targets to predictions."""
    p, t = cost.shape
    return min(sum(cost[rows[j], j] for j in range(t)) for rows in itertools.permutations(range(p), t))


@pytest.mark.parametrize("shape", [(1, 1), (3, 3), (5, 2), (6, 4), (7, 7)])
def test_match_is_the_brute_force_optimum(shape):
    rng = np.random.default_rng(sum(shape))
    for _ in range(20):
        cost = rng.random(shape) * rng.choice([1.0, 100.0])
        rows, cols = match(cost)
        assert list(cols) == list(range(shape[1]))          # every target matched once, in target order
        assert len(set(rows.tolist())) == shape[1]          # to distinct predictions
        assert cost[rows, cols].sum() == pytest.approx(_brute_force(cost))


def test_match_finds_the_global_not_the_greedy_assignment():
    # greedy (each target its cheapest free prediction) takes (0, 0) then (1, 1): 1 + 10; the optimum is 2 + 2
    cost = np.array([[1.0, 2.0], [2.0, 10.0]])
    rows, cols = match(torch.tensor(cost))
    assert rows.tolist() == [1, 0] and cols.tolist() == [0, 1]


def test_match_empty_and_bad_costs():
    rows, cols = match(np.zeros((4, 0)))
    assert rows.size == 0 and cols.size == 0
    with pytest.raises(ValueError, match="NaN"):
        match(np.array([[0.0, np.nan]]))
    with pytest.raises(ValueError, match="matrix"):
        match(np.zeros(3))


def test_match_batch_ignores_padding_columns():
    costs = torch.tensor([[[0.0, 5.0], [5.0, 0.0]], [[9.0, -100.0], [0.0, -100.0]]])
    result = match_batch(costs, torch.tensor([2, 1]))
    assert [r.tolist() for r, _ in result] == [[0, 1], [1]]
    with pytest.raises(ValueError, match="2 cost matrices"):
        match_batch(costs, [1])
