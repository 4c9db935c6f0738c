"""Benchmark: CULane TP/FP/FN (official procedure) on N synthetic CULane-like images (~4 GT, ~4 pred lanes).

Run: ``python benchmarks/bench_culane_metric.py [--images 1000] [--seed 0]``. Prints images/s and the counts.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from lanevil_train.metrics import culane_image_counts, culane_summary


def make_images(n: int, seed: int) -> list[tuple[list[np.ndarray], list[np.ndarray]]]:
    """CULane-style lanes: points every 10 px from the bottom row up to a random top, near-straight curves."""
    rng = np.random.default_rng(seed)
    images = []
    for _ in range(n):
        gt = []
        for k in range(4):
            top = rng.uniform(250, 350)
            ys = np.arange(590.0, top, -10.0)
            xb = 200 + 400 * k + rng.normal(0, 60)
            s = (ys - top) / (590 - top)
            xs = 820 + (xb - 820) * s + rng.uniform(-30, 30) * s * (1 - s)
            gt.append(np.stack([xs, ys], 1))
        pred = [g + [rng.normal(0, 12), 0] + rng.normal(0, 1.5, g.shape) for g in gt if rng.random() < 0.9]
        if rng.random() < 0.3:
            pred.append(gt[0] + [rng.uniform(60, 200), 0])
        images.append((pred, gt))
    return images


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    images = make_images(args.images, args.seed)
    n_lanes = sum(len(p) + len(g) for p, g in images)
    t0 = time.perf_counter()
    tp = fp = fn = 0
    for pred, gt in images:
        a, b, c = culane_image_counts(pred, gt)
        tp, fp, fn = tp + a, fp + b, fn + c
    dt = time.perf_counter() - t0
    print(json.dumps({"images": args.images, "lanes": n_lanes, "seconds": round(dt, 3),
                      "images_per_s": round(args.images / dt, 1), **culane_summary(tp, fp, fn)}))


if __name__ == "__main__":
    main()
