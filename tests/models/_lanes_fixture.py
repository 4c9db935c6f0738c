"""Synthetic ground-truth lanes and a small TuSimple-style scorer shared by the model tests."""

from __future__ import annotations

import numpy as np

from lanevil_train.lanes import INVALID_X, default_h_samples, lane_x_at


def synthetic_lanes(rng: np.random.Generator, image_size: tuple[int, int], n_lanes: int,
                    curved: bool) -> list[np.ndarray]:
    """n_lanes lanes converging to a vanishing point, straight or gently curved, left to right."""
    h, w = image_size
    vp_x = w * (0.5 + rng.uniform(-0.08, 0.08))
    vp_y = h * rng.uniform(0.35, 0.45)
    top = vp_y + 0.06 * h
    spacing = w * rng.uniform(0.45, 0.6)
    bottoms = vp_x + (np.arange(n_lanes) - (n_lanes - 1) / 2) * spacing
    bend = rng.uniform(-0.06, 0.06) * w if curved else 0.0
    lanes = []
    for xb in bottoms:
        ys = np.linspace(h - 1, top, 40)
        t = (h - 1 - ys) / (h - 1 - vp_y)
        xs = xb + (vp_x - xb) * t + bend * t**2
        lanes.append(np.stack([xs, ys], axis=1))
    # keep only the parts inside the image, as annotations do
    out = []
    for lane in lanes:
        ok = (lane[:, 0] >= 0) & (lane[:, 0] <= w - 1)
        if ok.sum() >= 2:
            out.append(lane[ok])
    return out


def tusimple_accuracy(pred: list[np.ndarray], gt: list[np.ndarray], image_size: tuple[int, int]) -> tuple[int, int]:
    """(correct points, GT points): per GT lane the best prediction, points within 20 px at 1280 width."""
    h, w = image_size
    ys = default_h_samples(h)
    ys = ys[ys <= h - 1]
    thr = 20.0 * w / 1280.0
    correct = total = 0
    for g in gt:
        gx = lane_x_at(g, ys)
        valid = gx != INVALID_X
        total += int(valid.sum())
        best = 0
        for p in pred:
            px = lane_x_at(p, ys)
            hit = valid & (px != INVALID_X) & (np.abs(px - gx) < thr)
            best = max(best, int(hit.sum()))
        correct += best
    return correct, total


def train_steps(network, head, images, targets, optimizer, steps: int) -> list[dict[str, float]]:
    """`steps` optimizer steps on head.loss(network(images), targets); per step, every scalar the loss returned
    (the total "loss" and its named parts)."""
    history = []
    for _ in range(steps):
        out = head.loss(network(images), targets)
        optimizer.zero_grad()
        out["loss"].backward()
        optimizer.step()
        history.append({k: v.item() for k, v in out.items() if v.ndim == 0})
    return history


def assert_lanes_inside(decoded: list[list[np.ndarray]], image_size: tuple[int, int], min_total: int = 1) -> None:
    """The contract's promise about decoded lanes: each an (N >= 2, 2) float array with y strictly descending and
    every point inside the image, each image's lanes left to right by their first point; min_total lanes in all."""
    h, w = image_size
    assert sum(len(lanes) for lanes in decoded) >= min_total
    for lanes in decoded:
        assert [lane[0, 0] for lane in lanes] == sorted(lane[0, 0] for lane in lanes)  # left to right
        for lane in lanes:
            assert lane.dtype == np.float64 and lane.ndim == 2 and lane.shape[1] == 2 and len(lane) >= 2
            assert np.all(np.diff(lane[:, 1]) < 0)  # y strictly descending
            assert lane[:, 0].min() >= 0 and lane[:, 0].max() <= w - 1
            assert lane[:, 1].min() >= 0 and lane[:, 1].max() <= h - 1


def assert_round_trip(decoded: list[list[np.ndarray]], gts: list[list[np.ndarray]], image_size: tuple[int, int],
                      min_accuracy: float = 0.99) -> None:
    """Decoded lanes reproduce the ground truth they were encoded from: one lane per GT lane, each with y strictly
    descending and inside the image, left to right, and >= min_accuracy TuSimple point accuracy overall."""
    assert_lanes_inside(decoded, image_size, min_total=0)
    correct = total = 0
    for gt, pred in zip(gts, decoded, strict=True):
        assert len(pred) == len(gt)
        c, n = tusimple_accuracy(pred, gt, image_size)
        correct, total = correct + c, total + n
    assert total > 100
    assert correct / total >= min_accuracy
