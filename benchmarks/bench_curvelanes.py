"""Benchmark: the CurveLanes reader and metric on a constructed valid split (official layout, 2560x1440 images).

Run: ``python benchmarks/bench_curvelanes.py [--images 300] [--lanes 8] [--seed 0] [--out DIR]``. Writes DIR/valid
(valid.txt, images/*.jpg, labels/*.lines.json with string coordinates) and DIR/pred/valid/images/*.lines.txt
(each ground-truth lane moved sideways by N(0, 12) px with 1.5 px point noise, 10 % of them left out, an extra lane
on 30 % of the images), then times ``read_curvelanes`` (every label parsed, every image checked) and
``python -m lanevil_train.metrics curvelanes`` (every label and image header read, then counted), and prints both
with the scores; the CULane procedure's scores of the same lanes (30 px at 1640 wide, scaled: 47 px at 2560) beside.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from lanevil_train.data.formats.curvelanes import read_curvelanes
from lanevil_train.metrics import culane_image_counts, culane_summary
from lanevil_train.metrics.curvelanes import evaluate_curvelanes_dirs

H, W = 1440, 2560


def make_split(out: Path, images: int, lanes: int, seed: int) -> None:
    """The constructed split and its predictions."""
    rng = np.random.default_rng(seed)
    folder, pred = out / "valid", out / "pred" / "valid" / "images"
    for sub in (folder / "images", folder / "labels", pred):
        sub.mkdir(parents=True, exist_ok=True)
    ok, jpg = cv2.imencode(".jpg", np.full((H, W, 3), 90, np.uint8))
    assert ok
    names = [f"{i:032x}" for i in range(images)]
    for name in names:
        (folder / "images" / f"{name}.jpg").write_bytes(jpg.tobytes())
        top, vx = rng.uniform(600, 800), W / 2 + rng.normal(0, 200)
        bend = rng.uniform(-400, 400)
        gt = []
        for k in range(lanes):
            ys = np.linspace(H - 1, top, 12)
            s = (ys - top) / (H - 1 - top)
            xb = vx + (k - (lanes - 1) / 2) * rng.uniform(500, 700)
            gt.append(np.stack([vx + (xb - vx) * s + bend * (1 - s) ** 2, ys], 1))
        label = {"Lines": [[{"x": f"{x:.2f}", "y": f"{y:.2f}"} for x, y in lane] for lane in gt]}
        (folder / "labels" / f"{name}.lines.json").write_text(json.dumps(label))
        preds = [g + [rng.normal(0, 12), 0] + rng.normal(0, 1.5, g.shape) for g in gt if rng.random() < 0.9]
        if rng.random() < 0.3:
            preds.append(gt[0] + [rng.uniform(80, 300), 0])
        (pred / f"{name}.lines.txt").write_text("".join(" ".join(f"{v:.3f}" for v in p.ravel()) + "\n"
                                                        for p in preds))
    (folder / "valid.txt").write_text("".join(f"images/{name}.jpg\n" for name in names))


def culane_scores(out: Path) -> dict:
    """The CULane procedure on the same lanes (its 30 px lanes scaled to the 2560 px width), for comparison."""
    from lanevil_train.metrics.culane_files import read_lines_file

    tp = fp = fn = 0
    for record in read_curvelanes(out, "valid", check_images=False):
        preds = read_lines_file(str((out / "pred" / record["rel_path"]).with_suffix(".lines.txt")))
        a, b, c = culane_image_counts(preds, record["lanes"], W, H, round(30 * W / 1640))
        tp, fp, fn = tp + a, fp + b, fn + c
    return culane_summary(tp, fp, fn)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=300)
    ap.add_argument("--lanes", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=None, help="folder to write the split in (default: a temporary one)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(args.out or tmp)
        make_split(out, args.images, args.lanes, args.seed)
        t0 = time.perf_counter()
        records = read_curvelanes(out, "valid")
        t_read = time.perf_counter() - t0
        t0 = time.perf_counter()
        scores = evaluate_curvelanes_dirs(out / "pred", out, "valid")
        t_metric = time.perf_counter() - t0
        print(json.dumps({"images": len(records), "gt_lanes": sum(len(r["lanes"]) for r in records),
                          "read_s": round(t_read, 3), "metric_s": round(t_metric, 3),
                          "curvelanes": {k: round(v, 4) if isinstance(v, float) else v for k, v in scores.items()},
                          "culane_procedure": {k: round(v, 4) for k, v in culane_scores(out).items()}}))


if __name__ == "__main__":
    main()
