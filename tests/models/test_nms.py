import numpy as np
import torch

from lanevil_train.models.nms import lane_nms


def _brute_force(xs, starts, lengths, scores, thr, top_k):
    n, s = xs.shape
    order = sorted(range(n), key=lambda i: -scores[i])
    kept = []
    for i in order:
        suppressed = False
        for j in kept:
            end_i = min(starts[i] + int(np.floor(lengths[i] + 0.5)) - 1, s - 1)
            end_j = min(starts[j] + int(np.floor(lengths[j] + 0.5)) - 1, s - 1)
            lo, hi = max(starts[i], starts[j]), min(end_i, end_j)
            if hi < lo:
                continue
            d = sum(abs(xs[i, k] - xs[j, k]) for k in range(lo, hi + 1)) / (hi - lo + 1)
            if d < thr:
                suppressed = True
                break
        if not suppressed:
            kept.append(i)
            if top_k is not None and len(kept) == top_k:
                break
    return kept


def test_lane_nms_matches_brute_force():
    rng = np.random.default_rng(0)
    for trial in range(20):
        n, s = int(rng.integers(1, 40)), 12
        base = rng.uniform(0, 200, size=(n, 1))
        xs = base + rng.normal(0, 10, size=(n, s)).cumsum(1)
        starts = rng.integers(0, s, size=n)
        lengths = rng.uniform(-1, s, size=n)
        scores = rng.permutation(n).astype(np.float64) / n  # distinct scores: a unique order
        thr = float(rng.uniform(5, 60))
        top_k = None if trial % 2 else int(rng.integers(1, 6))
        got = lane_nms(torch.tensor(xs, dtype=torch.float64), torch.tensor(starts), torch.tensor(lengths),
                       torch.tensor(scores), thr, top_k)
        want = _brute_force(xs, starts, lengths, scores, thr, top_k)
        assert got.tolist() == want


def test_lane_nms_suppresses_near_duplicates_only():
    xs = torch.tensor([[10.0] * 5, [12.0] * 5, [100.0] * 5, [11.0] * 5])
    starts = torch.tensor([0, 0, 0, 3])
    lengths = torch.tensor([5.0, 5.0, 5.0, 2.0])
    scores = torch.tensor([0.9, 0.8, 0.7, 0.95])
    # 3 (best) covers rows 3-4 and is within 1-2 px of 0 and 1 there -> both suppressed
    assert lane_nms(xs, starts, lengths, scores, threshold=5.0).tolist() == [3, 2]
    # shorten 0-2 to rows 0..2: lane 3 (rows 3..4) shares no row with them, so it suppresses nothing
    assert lane_nms(xs, torch.tensor([0, 0, 0, 3]), torch.tensor([3.0, 3.0, 3.0, 2.0]), scores,
                    5.0).tolist() == [3, 0, 2]
    assert lane_nms(xs[:0], starts[:0], lengths[:0], scores[:0], 5.0).numel() == 0
