"""Time the scoring commands as whole processes, side by side with the official tools when given.

Usage::

    python benchmarks/bench_metric_commands.py [--tusimple-images 2782] [--culane-images 3000]
        [--repeats 7] [--workdir DIR]
        [--official-tusimple /path/to/evaluate/lane.py --official-python /path/to/python]
        [--official-culane /path/to/evaluate]

Generates TuSimple-format JSON-lines files (2,782 images: the TuSimple test-set size; 4-5 GT lanes on
the 56 official h_samples, noisy predictions with misses and spurious lanes) and a CULane-format tree
(``.lines.txt`` per image at 1640x590 + an image list), then runs each command ``--repeats`` times in a
fresh process (the commands interleaved, so background noise hits all alike) and prints best and median
wall seconds, the speed ratios and whether the scores agree.

The official tools are not part of this project: pass their locations. ``--official-tusimple`` is the
TuSimple benchmark's ``evaluate/lane.py``; it is Python 2 code, so it is run by ``--official-python``
(an interpreter with numpy, scikit-learn and ujson) through a small loader that executes the file up to
its ``__main__`` block and prints ``LaneEval.bench_one_submit(pred, gt)``. ``--official-culane`` is the
CULane ``evaluate`` binary, run as ``evaluate -a GT -d PRED -i IMG -l LIST -w 30 -t 0.5 -c 1640 -r 590
-o OUT``. A tool that is not given is skipped.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

TUSIMPLE_W, TUSIMPLE_H = 1280, 720
H_SAMPLES = list(range(160, 720, 10))  # the 56 official rows
CULANE_W, CULANE_H = 1640, 590

# Runs the Python 2 official script under Python 3 without editing it: execute the file up to its
# `if __name__ == '__main__':` block (whose print statements are Python 2 syntax), then score.
OFFICIAL_TUSIMPLE_LOADER = (
    "import sys; src = open(sys.argv[1]).read(); cut = src.find(\"if __name__ == '__main__':\"); "
    "ns = {'__name__': 'lane'}; exec(compile(src if cut < 0 else src[:cut], sys.argv[1], 'exec'), ns); "
    "print(ns['LaneEval'].bench_one_submit(sys.argv[2], sys.argv[3]))"
)


# ------------------------------------------------------------------------------------------ data
def _lane_xs(ys: np.ndarray, vp: tuple[float, float], x_bottom: float, y_bottom: float, bend: float) -> np.ndarray:
    """x of a straight-ish lane through the vanishing point ``vp`` and (x_bottom, y_bottom), plus a bend."""
    s = (ys - vp[1]) / (y_bottom - vp[1])  # 0 at the horizon, 1 at the bottom
    return vp[0] + (x_bottom - vp[0]) * s + bend * (1 - s) ** 2


def make_tusimple(n: int, rng: np.random.Generator) -> tuple[list[dict], list[dict]]:
    """(GT objects, prediction objects) of ``n`` TuSimple-like images (integer GT, float predictions)."""
    ys = np.asarray(H_SAMPLES, dtype=np.float64)
    gts, preds = [], []
    for i in range(n):
        raw = f"clips/0530/{1492626000000 + i * 7}_0/20.jpg"
        vp = (640 + rng.normal(0, 50), 250 + rng.normal(0, 15))
        n_gt = int(rng.choice([4, 5], p=[0.7, 0.3]))
        spacing = rng.uniform(380, 480)
        first = -(n_gt - 1) / 2 + rng.normal(0, 0.15)
        bend = rng.normal(0, 60)
        gt_rows = []
        for k in range(n_gt):
            xs = np.round(_lane_xs(ys, vp, 640 + (first + k) * spacing, 710.0, bend))
            top = vp[1] + rng.uniform(10, 60)
            xs = np.where((ys > top) & (xs >= 0) & (xs < TUSIMPLE_W), xs, -2.0)
            gt_rows.append(xs)
        pred_rows = []
        for xs in gt_rows:
            if rng.random() < 0.08 or np.count_nonzero(xs >= 0) < 2:
                continue  # a missed lane
            off = rng.normal(0, 6) + (rng.uniform(25, 60) * rng.choice([-1, 1]) if rng.random() < 0.1 else 0)
            p = np.where(xs >= 0, xs + off + rng.normal(0, 4, xs.shape), -2.0)
            p[: int(rng.integers(0, 4))] = -2.0  # predictions often start a few rows lower
            p[(p < 0) | (p >= TUSIMPLE_W)] = -2.0
            pred_rows.append(p)
        if rng.random() < 0.25:  # a spurious lane
            x0 = rng.uniform(0, TUSIMPLE_W)
            p = _lane_xs(ys, vp, x0, 710.0, rng.normal(0, 80))
            p = np.where((ys > vp[1] + 40) & (p >= 0) & (p < TUSIMPLE_W), p, -2.0)
            pred_rows.append(p)
        gts.append({"lanes": [[int(v) for v in r] for r in gt_rows], "h_samples": H_SAMPLES, "raw_file": raw})
        preds.append({"lanes": [[v if v >= 0 else -2 for v in r.tolist()] for r in pred_rows],
                      "raw_file": raw, "run_time": 10})
    return gts, preds


def _culane_points(rng: np.random.Generator, vp: tuple[float, float], x_bottom: float, bend: float,
                   top: float, jitter: float) -> np.ndarray:
    """CULane-style lane points: every 10 rows from the bottom up to ``top``, inside the image."""
    ys = np.arange(CULANE_H, top, -10.0)
    xs = _lane_xs(ys, vp, x_bottom, float(CULANE_H), bend) + rng.normal(0, jitter, ys.shape)
    keep = (xs >= 0) & (xs < CULANE_W)
    return np.stack([xs[keep], ys[keep]], 1)


def make_culane(n: int, rng: np.random.Generator) -> list[tuple[str, list[np.ndarray], list[np.ndarray]]]:
    """(image path, GT lanes, predicted lanes) of ``n`` CULane-like images (1640x590, 2-4 GT lanes)."""
    images = []
    for i in range(n):
        name = f"/driver_100_30frame/05251{i // 60:03d}_0{i % 7}.MP4/{(i % 60) * 30:05d}.jpg"
        vp = (820 + rng.normal(0, 60), 260 + rng.normal(0, 15))
        n_gt = int(rng.choice([2, 3, 4], p=[0.15, 0.35, 0.5]))
        spacing = rng.uniform(650, 900)
        first = -(n_gt - 1) / 2 + rng.normal(0, 0.2)
        bend = rng.normal(0, 50)
        gt = []
        for k in range(n_gt):
            lane = _culane_points(rng, vp, 820 + (first + k) * spacing, bend, vp[1] + rng.uniform(15, 60), 0.0)
            if len(lane) >= 2:
                gt.append(lane)
        pred = []
        for lane in gt:
            if rng.random() < 0.1:
                continue
            off = rng.normal(0, 8) + (rng.uniform(30, 80) * rng.choice([-1, 1]) if rng.random() < 0.12 else 0)
            p = lane + [off, 0] + np.c_[rng.normal(0, 3, len(lane)), np.zeros(len(lane))]
            p = p[: len(p) - int(rng.integers(0, 4))]
            if len(p) >= 2:
                pred.append(p)
        if rng.random() < 0.3:
            p = _culane_points(rng, vp, rng.uniform(-400, 2000), rng.normal(0, 80), vp[1] + 40, 2.0)
            if len(p) >= 2:
                pred.append(p)
        images.append((name, gt, pred))
    return images


def write_tusimple(workdir: Path, n: int, seed: int) -> tuple[Path, Path]:
    """Write pred.json and gt.json (JSON lines, predictions in the GT order) and return their paths."""
    gts, preds = make_tusimple(n, np.random.default_rng(seed))
    gt_path, pred_path = workdir / "tusimple_gt.json", workdir / "tusimple_pred.json"
    gt_path.write_text("".join(json.dumps(o) + "\n" for o in gts))
    pred_path.write_text("".join(json.dumps(o) + "\n" for o in preds))
    return pred_path, gt_path


def write_culane(workdir: Path, n: int, seed: int) -> tuple[Path, Path, Path]:
    """Write the GT and prediction ``.lines.txt`` trees and the list; return (pred dir, gt dir, list)."""
    gt_dir, pred_dir, lst = workdir / "culane_gt", workdir / "culane_pred", workdir / "culane_test.txt"
    names = []
    for name, gt, pred in make_culane(n, np.random.default_rng(seed)):
        rel = name.lstrip("/").rsplit(".", 1)[0] + ".lines.txt"
        for root, lanes, fmt in ((gt_dir, gt, "{:.3f} {:.0f} "), (pred_dir, pred, "{:.5f} {:.0f} ")):
            path = root / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text("".join("".join(fmt.format(x, y) for x, y in lane) + "\n" for lane in lanes))
        names.append(name)
    lst.write_text("".join(s + "\n" for s in names))
    return pred_dir, gt_dir, lst


# --------------------------------------------------------------------------------------- running
def run_timed(cmd: list[str], cwd: Path) -> tuple[float, str]:
    """Wall seconds of one fresh process and its stdout; raises with stderr if it fails."""
    t0 = time.perf_counter()
    res = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if res.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({res.returncode}):\n{res.stderr[-2000:]}")
    return dt, res.stdout


def parse_official_tusimple(stdout: str) -> dict:
    """{"Accuracy", "FP", "FN"} from the official script's JSON list of {name, value, order}."""
    return {d["name"]: d["value"] for d in json.loads(stdout.strip().splitlines()[-1])}


def parse_official_culane(out_file: Path) -> dict:
    """{"TP", "FP", "FN"} from the ``tp: .. fp: .. fn: ..`` line of the official output file."""
    m = re.search(r"tp:\s*(\d+)\s+fp:\s*(\d+)\s+fn:\s*(\d+)", out_file.read_text())
    if not m:
        raise RuntimeError(f"no 'tp: fp: fn:' line in {out_file}")
    return {"TP": int(m[1]), "FP": int(m[2]), "FN": int(m[3])}


def compare_tusimple(ours: dict, official: dict) -> str:
    """'identical' when every official value equals ours bit for bit, else the largest difference."""
    diffs = {k: abs(ours[k] - official[k]) for k in ("Accuracy", "FP", "FN")}
    if all(ours[k] == official[k] for k in diffs):
        return "identical (Accuracy, FP, FN bit-equal)"
    return "DIFFER: " + ", ".join(f"{k} ours {ours[k]!r} official {official[k]!r} (|d| {d:.3g})"
                                  for k, d in diffs.items() if d)


def compare_culane(ours: dict, official: dict) -> str:
    """'identical' when TP, FP and FN agree, else both sets of counts."""
    if all(ours[k] == official[k] for k in ("TP", "FP", "FN")):
        return f"identical (TP {ours['TP']}, FP {ours['FP']}, FN {ours['FN']})"
    return f"DIFFER: ours {[ours[k] for k in ('TP', 'FP', 'FN')]} official {[official[k] for k in ('TP', 'FP', 'FN')]}"


def time_commands(commands: dict[str, list[str]], repeats: int, cwd: Path) -> tuple[dict, dict]:
    """Run every command ``repeats`` times, interleaved; return (times per name, last stdout per name)."""
    times: dict[str, list[float]] = {name: [] for name in commands}
    outs: dict[str, str] = {}
    for _ in range(repeats):
        for name, cmd in commands.items():
            dt, out = run_timed(cmd, cwd)
            times[name].append(dt)
            outs[name] = out
    return times, outs


def print_table(title: str, times: dict[str, list[float]], baseline: str | None) -> None:
    """Markdown table: best and median seconds, and speed-up over ``baseline`` (official / ours)."""
    print(f"\n{title}\n")
    print("| command | best s | median s | speed-up vs official (best / median) |")
    print("|---|---|---|---|")
    for name, ts in times.items():
        best, med = min(ts), statistics.median(ts)
        ratio = ""
        if baseline and name != baseline:
            ratio = f"{min(times[baseline]) / best:.2f}x / {statistics.median(times[baseline]) / med:.2f}x"
        print(f"| {name} | {best:.3f} | {med:.3f} | {ratio} |")


def side_by_side(title: str, commands: dict[str, list[str]], official: str | None,
                 read_official: Callable[[str], dict], compare: Callable[[dict, dict], str], repeats: int,
                 cwd: Path) -> dict:
    """Time our command (the first) beside the `official` one when given, print the table and whether the scores
    agree (`read_official` gets the official command's stdout); return our scores."""
    times, outs = time_commands(commands, repeats, cwd)
    print_table(title, times, official)
    ours = json.loads(outs[next(iter(commands))])
    print(f"\nours: {ours}")
    if official:
        theirs = read_official(outs[official])
        print(f"official: {theirs}\nscores: {compare(ours, theirs)}")
    return ours


def main() -> None:
    """Generate the data, time the commands and print the tables."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tusimple-images", type=int, default=2782)
    ap.add_argument("--culane-images", type=int, default=3000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workdir", help="where to write the data (default: a temporary directory)")
    ap.add_argument("--official-tusimple", help="TuSimple benchmark evaluate/lane.py")
    ap.add_argument("--official-python", default=sys.executable, help="interpreter for it (numpy, sklearn, ujson)")
    ap.add_argument("--official-culane", help="the CULane evaluator binary (evaluate)")
    ap.add_argument("--skip", choices=["tusimple", "culane"], action="append", default=[])
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.workdir or tmp).resolve()
        work.mkdir(parents=True, exist_ok=True)
        ours = [sys.executable, "-m", "lanevil_train.metrics"]
        env_note = f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs, repeats {args.repeats}"
        print(f"# scoring commands as processes ({env_note})")

        if "tusimple" not in args.skip:
            pred, gt = write_tusimple(work, args.tusimple_images, args.seed)
            commands = {"ours: python -m lanevil_train.metrics tusimple": ours + ["tusimple", "--pred", str(pred),
                                                                                  "--gt", str(gt)]}
            if args.official_tusimple:
                commands["official: evaluate/lane.py"] = [args.official_python, "-c", OFFICIAL_TUSIMPLE_LOADER,
                                                         args.official_tusimple, str(pred), str(gt)]
            side_by_side(f"TuSimple, {args.tusimple_images} images", commands,
                         "official: evaluate/lane.py" if args.official_tusimple else None,
                         parse_official_tusimple, compare_tusimple, args.repeats, work)

        if "culane" not in args.skip:
            pred_dir, gt_dir, lst = write_culane(work, args.culane_images, args.seed)
            out_file = work / "culane_official_out.txt"
            commands = {"ours: python -m lanevil_train.metrics culane": ours + [
                "culane", "--pred-dir", str(pred_dir), "--gt-dir", str(gt_dir), "--list", str(lst)]}
            if args.official_culane:
                commands["official: evaluate (C++, OpenMP)"] = [
                    args.official_culane, "-a", f"{gt_dir}/", "-d", f"{pred_dir}/", "-i", f"{work}/", "-l", str(lst),
                    "-w", "30", "-t", "0.5", "-c", str(CULANE_W), "-r", str(CULANE_H), "-f", "1", "-o", str(out_file)]
            our_scores = side_by_side(f"CULane, {args.culane_images} images at {CULANE_W}x{CULANE_H}", commands,
                                      "official: evaluate (C++, OpenMP)" if args.official_culane else None,
                                      lambda _stdout: parse_official_culane(out_file), compare_culane,
                                      args.repeats, work)
            if not math.isfinite(our_scores["F1"]):
                raise RuntimeError("our CULane F1 is not finite")


if __name__ == "__main__":
    main()
