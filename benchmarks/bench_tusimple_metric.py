"""Time the TuSimple metric on 2,782 random TuSimple-like images (the TuSimple test-set size).

Usage: python benchmarks/bench_tusimple_metric.py [--images 2782] [--seed 0] [--repeats 3]
Prints the best wall time of tusimple_image_scores over all images (rows precomputed), of
TuSimpleMetric.update+compute (pixel lanes -> rows included) and of evaluate_tusimple_files
(JSON-lines files, parsing included).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from lanevil_train.lanes import TUSIMPLE_H_SAMPLES, rows_to_lane
from lanevil_train.metrics import TuSimpleMetric, evaluate_tusimple_files, tusimple_image_scores


def make_images(n: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """(pred rows, gt rows) per image: 4-5 GT lanes over 56 rows, 4-5 noisy/spurious preds."""
    ys = TUSIMPLE_H_SAMPLES
    out = []
    for _ in range(n):
        g = int(rng.integers(4, 6))
        gt = np.round(rng.uniform(100, 1200, (g, 1)) + rng.uniform(-1.5, 1.5, (g, 1)) * (ys - 400))
        gt[:, : int(rng.integers(0, 15))] = -2
        gt[gt < 0] = -2
        p = int(rng.integers(4, 6))
        base = gt[rng.integers(0, g, p)]
        pred = np.where(base >= 0, np.maximum(base + rng.normal(0, 15, (p, 56)), 0), -2.0)
        out.append((pred, gt))
    return out


def main() -> None:
    """Run the timing and print seconds."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=2782)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    images = make_images(args.images, rng)
    ys = TUSIMPLE_H_SAMPLES

    best = float("inf")
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        acc = sum(tusimple_image_scores(p, g, ys)[0] for p, g in images)
        best = min(best, time.perf_counter() - t0)
    print(f"tusimple_image_scores: {args.images} images in {best:.3f} s (mean accuracy {acc / args.images:.4f})")

    preds = [[rows_to_lane(r, ys) for r in p if np.any(r >= 0)] for p, _ in images]
    gts = [[rows_to_lane(r, ys) for r in g if np.any(r >= 0)] for _, g in images]
    best = float("inf")
    for _ in range(args.repeats):
        metric = TuSimpleMetric()
        t0 = time.perf_counter()
        metric.update(preds, gts, ys)
        out = metric.compute()
        best = min(best, time.perf_counter() - t0)
    print(f"TuSimpleMetric.update+compute (from pixel lanes): {args.images} images in {best:.3f} s "
          f"(Accuracy {float(out['Accuracy']):.4f})")

    with tempfile.TemporaryDirectory() as tmp:
        hs = [int(y) for y in ys]
        gt_path, pred_path = Path(tmp) / "gt.json", Path(tmp) / "pred.json"
        gt_path.write_text("".join(json.dumps({"lanes": g.tolist(), "h_samples": hs, "raw_file": f"clips/{i}/20.jpg"})
                                   + "\n" for i, (_, g) in enumerate(images)))
        pred_path.write_text("".join(json.dumps({"lanes": p.tolist(), "raw_file": f"clips/{i}/20.jpg", "run_time": 1})
                                     + "\n" for i, (p, _) in enumerate(images)))
        best = float("inf")
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            res = evaluate_tusimple_files(pred_path, gt_path)
            best = min(best, time.perf_counter() - t0)
    print(f"evaluate_tusimple_files (JSON parsing included): {args.images} images in {best:.3f} s "
          f"(Accuracy {res['Accuracy']:.4f})")


if __name__ == "__main__":
    main()
