"""CULane as the leaderboards report it (F1@50, F1@75, mF1, nine categories), ours vs the official evaluator per list.

Usage::

    python benchmarks/bench_culane_categories.py [--images 900] [--seed 0] [--workdir DIR]
        [--official-culane /path/to/evaluate]

Writes a CULane-format set: bench_metric_commands.make_culane's 1640x590 images (2-4 GT lanes, a point every 10
rows) with one simulated detector's predictions (offsets, noise, misses, spurious lanes), each image put in one of
the nine official categories in turn (a category adds its own x noise to the predictions, and a cross image keeps
no GT lane, as in CULane), ``list/test.txt`` and the nine ``list/test_split/test<k>_<name>.txt``. Then scores it
with ``evaluate_culane_dirs(..., categories=list/test_split)`` (one pass over the predictions) and, given
``--official-culane``, runs the official ``evaluate`` once per category list and IoU threshold (0.50, 0.55, ...,
0.95: 90 runs, as run-full.sh does per list at one threshold), sums the nine lists' counts for the total (as
calTotal.m does), and prints the table with both sides' F1@50, F1@75, mF1 (cross: FP) and whether every count
(TP, FP, FN of every list at every threshold) is equal.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from lanevil_train.metrics.culane import MF1_THRESHOLDS, culane_leaderboard_scores
from lanevil_train.metrics.culane_files import (
    CATEGORIES,
    FP_ONLY,
    evaluate_culane_dirs,
    image_counts,
    image_key,
    read_category_lists,
    totals_by_threshold,
)

_BENCH = Path(__file__).resolve().parent / "bench_metric_commands.py"
_spec = importlib.util.spec_from_file_location("bench_metric_commands", _BENCH)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)

# extra x noise (px, per point) on a category's predictions: harder scenes, worse lanes
CATEGORY_NOISE = {"normal": 0.0, "crowd": 4.0, "hlight": 6.0, "shadow": 5.0, "noline": 8.0, "arrow": 2.0,
                  "curve": 6.0, "cross": 0.0, "night": 7.0}


def write_set(root: Path, n: int, seed: int) -> tuple[Path, Path, Path]:
    """Write GT (under root), predictions (root/pred) and the lists; return (pred dir, test list, split dir)."""
    rng = np.random.default_rng(seed + 1)
    pred_dir, split = root / "pred", root / "list" / "test_split"
    split.mkdir(parents=True, exist_ok=True)
    members: dict[str, list[str]] = {name: [] for name, _ in CATEGORIES}
    names = []
    for i, (name, gt, pred) in enumerate(bench.make_culane(n, np.random.default_rng(seed))):
        category = CATEGORIES[i % len(CATEGORIES)][0]
        if category == FP_ONLY:
            gt = []  # crossroads: no lane in the ground truth, every predicted lane is an FP
        pred = [p + np.c_[rng.normal(0, CATEGORY_NOISE[category], len(p)), np.zeros(len(p))] for p in pred]
        rel = name.lstrip("/").rsplit(".", 1)[0] + ".lines.txt"
        for folder, lanes, fmt in ((root, gt, "{:.3f} {:.0f} "), (pred_dir, pred, "{:.5f} {:.0f} ")):
            path = folder / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("".join("".join(fmt.format(x, y) for x, y in lane) + "\n" for lane in lanes))
        members[category].append(name)
        names.append(name)
    test = root / "list" / "test.txt"
    test.write_text("".join(s + "\n" for s in names))
    for category, filename in CATEGORIES:
        (split / filename).write_text("".join(s + "\n" for s in members[category]))
    return pred_dir, test, split


def official_counts(binary: str, root: Path, pred_dir: Path, split: Path, work: Path) -> dict[str, dict]:
    """{category: {threshold: (TP, FP, FN)}} from one official run per list and threshold, plus the total."""
    out: dict[str, dict] = {}
    for category, filename in CATEGORIES:
        out[category] = {}
        for t in MF1_THRESHOLDS:
            result = work / f"official_{category}_{t:.2f}.txt"
            cmd = [binary, "-a", f"{root}/", "-d", f"{pred_dir}/", "-i", f"{root}/", "-l", str(split / filename),
                   "-w", "30", "-t", f"{t:.2f}", "-c", "1640", "-r", "590", "-f", "1", "-o", str(result)]
            subprocess.run(cmd, check=True, capture_output=True)
            c = bench.parse_official_culane(result)
            out[category][t] = (c["TP"], c["FP"], c["FN"])
    out["total"] = {t: tuple(sum(out[c][t][k] for c, _ in CATEGORIES) for k in range(3)) for t in MF1_THRESHOLDS}
    return out


def our_counts(root: Path, pred_dir: Path, test: Path, split: Path) -> tuple[dict, dict[str, dict], float]:
    """evaluate_culane_dirs's result, the same counts per list and threshold, and its seconds. The per-threshold
    counts come from the library's one-pass per-image rows (image_counts), summed per list."""
    t0 = time.perf_counter()
    result = evaluate_culane_dirs(str(pred_dir), str(root), str(test), categories=str(split))
    seconds = time.perf_counter() - t0
    names = [line for line in test.read_text().splitlines() if line]
    rows, _ = image_counts(str(pred_dir), str(root), names)
    lists = read_category_lists(str(split), names)
    index = {image_key(n): i for i, n in enumerate(names)}
    counts = {c: totals_by_threshold(rows[[index[k] for k in keys]], MF1_THRESHOLDS) for c, keys in lists.items()}
    counts["total"] = totals_by_threshold(rows, MF1_THRESHOLDS)
    return result, counts, seconds


def table(result: dict, official: dict[str, dict] | None, ours: dict[str, dict]) -> str:
    """Markdown: per list, ours and the official F1@50, F1@75, mF1 (%; cross: FP), and whether all counts agree."""
    lines = ["| list | images | F1@50 ours / official | F1@75 ours / official | mF1 ours / official | "
             "counts at all 10 thresholds |", "|---|---|---|---|---|---|"]
    for name, row in result["categories"].items():
        theirs = culane_leaderboard_scores(official[name]) if official else None
        same = "equal" if official and official[name] == ours[name] else ("DIFFER" if official else "-")
        if name == FP_ONLY:
            fp = f"FP {row['FP']}" + (f" / {official[name][0.5][1]}" if official else "")
            lines.append(f"| {name} | {row['images']} | {fp} | - | - | {same} |")
            continue
        cells = [f"{100 * row[k]:.2f}" + (f" / {100 * theirs[k]:.2f}" if theirs else "") for k in
                 ("F1@50", "F1@75", "mF1")]
        lines.append(f"| {name} | {row['images']} | {' | '.join(cells)} | {same} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", type=int, default=900)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", help="where to write the set (default: a temporary directory)")
    ap.add_argument("--official-culane", help="the official CULane evaluator binary (evaluate)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.workdir or tmp).resolve()
        pred_dir, test, split = write_set(root, args.images, args.seed)
        result, ours, seconds = our_counts(root, pred_dir, test, split)
        print(f"# {args.images} images, seed {args.seed}: ours {seconds:.2f} s (one pass, every list and threshold)")
        official = None
        if args.official_culane:
            t0 = time.perf_counter()
            official = official_counts(args.official_culane, root, pred_dir, split, root)
            print(f"# official evaluate: {time.perf_counter() - t0:.1f} s (90 runs: 9 lists x 10 thresholds)")
        print(table(result, official, ours))
        if official and any(official[k] != ours[k] for k in ours):
            sys.exit("the counts differ from the official evaluator's")


if __name__ == "__main__":
    main()
