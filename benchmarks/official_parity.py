"""Our TuSimple prediction file beside the one the official code writes, for the same checkpoint and images.

Usage (this project's venv; the official code in its own environment, never imported here):

    python benchmarks/official_parity.py run --repos /src/official --official-python /envs/official/bin/python \
        --work /tmp/parity [--family ufld --family clrnet ...] [--launch LAUNCHER.py]

``--repos`` holds the official repositories, each in a folder named as the repository, at the commits of
``benchmarks/official_side/<family>.py``'s ``OFFICIAL`` (Ultra-Fast-Lane-Detection, CLRNet, pytorch-auto-drive,
LaneATT). ``--official-python`` is an environment that runs them (their own requirements; on a machine without CUDA,
``--launch`` names a launcher script run as ``python LAUNCHER.py REPO SCRIPT ARGS`` that stands in for their CUDA
parts). Per family, ``run``:

1. draws four 1280x720 road images in TuSimple's layout (``clips/0530/<n>/20.jpg``, ``test_label.json``,
   ``test.txt``) in ``<work>/tusimple``, and the same roads at 1640x590 in CULane's (``driver_100_30frame/...``,
   ``.lines.txt`` labels, ``list/test.txt`` and ``list/test_split/``) in ``<work>/culane`` (``images`` does only
   this);
2. builds an official checkpoint with the official code and random weights whose values draw lanes
   (``official_side/<family>.py checkpoint``, in the official environment);
3. runs the official test entry point on the images with it (``official_side/<family>.py predict``), keeping the
   TuSimple prediction file it writes;
4. runs ours, ``python -m lanevil_train task=evaluate <the family's OURS overrides> ckpt_path=<checkpoint>
   task.predictions=true``, on the same images;
5. compares the two files (``compare`` does only this): lanes matched as a set (each of ours to the official lane
   sharing most rows with it), the largest |dx| where both have a point, the samples where one side writes -2 and
   the other a point; for CULane (``compare --culane``) the .lines.txt folders: the largest |dx| at the rows both
   have and the lanes whose point counts differ. ``<work>/parity.json`` keeps every family's figures.

Steps 1-5 run per dataset (``--dataset tusimple``, ``--dataset culane``; both by default) where the family's side
names our overrides for it (``OURS``, ``OURS_CULANE``); its ``checkpoint`` and ``predict`` then get
``--dataset culane`` (the release's CULane shapes, the official CULane test writing its .lines.txt, copied to the
``--out`` folder).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

WIDTH, HEIGHT = 1280, 720
H_SAMPLES = list(range(160, 720, 10))
HORIZON = 250


def _lane_xs(bottom_x: float, top_x: float, bend: float, ys: np.ndarray) -> np.ndarray:
    """x of a drawn lane at rows ys: a line from (bottom_x, 719) to (top_x, HORIZON) bent by `bend` px at mid."""
    t = (HEIGHT - 1 - ys) / (HEIGHT - 1 - HORIZON)
    return bottom_x + (top_x - bottom_x) * t + bend * t * t


def draw_road(seed: int) -> tuple[np.ndarray, list[list[float]]]:
    """One BGR road image and its lanes' x at H_SAMPLES (-2 above the horizon or outside the image)."""
    import cv2

    rng = np.random.default_rng(seed)
    image = np.empty((HEIGHT, WIDTH, 3), np.uint8)
    image[:HORIZON] = (200, 170, 140)
    image[HORIZON:] = (90, 90, 90)
    image[HORIZON:] = np.clip(image[HORIZON:] + rng.normal(0, 8, (HEIGHT - HORIZON, WIDTH, 1)), 0, 255)
    vanish = WIDTH / 2 + rng.uniform(-80, 80)
    bend = rng.uniform(-120, 120)
    bottoms = [-250 + rng.uniform(-40, 40), 330 + rng.uniform(-30, 30), 950 + rng.uniform(-30, 30),
               1530 + rng.uniform(-40, 40)]
    ys_draw = np.arange(HORIZON, HEIGHT, dtype=np.float64)
    labels = []
    for k, bottom in enumerate(bottoms):
        xs = _lane_xs(bottom, vanish + (k - 1.5) * 12, bend, ys_draw)
        dashed = k in (1, 2) and seed % 2 == 0
        for y0 in range(HEIGHT - 1, HORIZON, -8):
            if dashed and (y0 // 40) % 2:
                continue
            i = int(y0 - HORIZON)
            if i < 8:
                break
            x0, x1 = xs[i], xs[i - 8]
            width = max(2, int(14 * (y0 - HORIZON) / (HEIGHT - HORIZON)))
            cv2.line(image, (int(round(x0)), y0), (int(round(x1)), y0 - 8), (235, 235, 235), width)
        at = _lane_xs(bottom, vanish + (k - 1.5) * 12, bend, np.asarray(H_SAMPLES, dtype=np.float64))
        row = [round(float(x), 1) if (y > HORIZON + 10 and 0 <= x < WIDTH) else -2 for x, y in zip(at, H_SAMPLES)]
        labels.append(row)
    return image, labels


def write_images(out: Path, count: int = 4) -> Path:
    """The TuSimple-layout folder both sides read: clips/0530/<n>/20.jpg, test_label.json, test.txt."""
    import cv2

    out.mkdir(parents=True, exist_ok=True)
    lines, names = [], []
    for n in range(count):
        raw_file = f"clips/0530/{1492626000 + n}_0/20.jpg"
        image, lanes = draw_road(n)
        (out / raw_file).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out / raw_file), image, [cv2.IMWRITE_JPEG_QUALITY, 95])
        lines.append(json.dumps({"lanes": lanes, "h_samples": H_SAMPLES, "raw_file": raw_file}))
        names.append(raw_file)
    (out / "test_label.json").write_text("\n".join(lines) + "\n")
    (out / "test.txt").write_text("\n".join(names) + "\n")
    return out


CULANE_SIZE = (1640, 590)
CULANE_CATEGORY_LISTS = ("test0_normal", "test1_crowd", "test2_hlight", "test3_shadow", "test4_noline",
                         "test5_arrow", "test6_curve", "test7_cross", "test8_night")


def write_culane_images(out: Path, count: int = 4) -> Path:
    """The same roads in CULane's layout: 1640x590 images (the 1280x720 drawing resized),
    driver_100_30frame/<n>/00000.jpg with its .lines.txt (bottom point first), list/test.txt and the nine
    list/test_split/ files the official CULane test sets read (every image listed as normal, the rest empty)."""
    import cv2

    out.mkdir(parents=True, exist_ok=True)
    sx, sy = CULANE_SIZE[0] / WIDTH, CULANE_SIZE[1] / HEIGHT
    names = []
    for n in range(count):
        image, lanes = draw_road(n)
        relative = f"driver_100_30frame/{1492626000 + n}_0.MP4/00000.jpg"
        (out / relative).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(out / relative), cv2.resize(image, CULANE_SIZE, interpolation=cv2.INTER_AREA),
                    [cv2.IMWRITE_JPEG_QUALITY, 95])
        lines = []
        for lane in lanes:
            points = [(x * sx, y * sy) for x, y in zip(lane, H_SAMPLES) if x >= 0][::-1]
            if len(points) >= 2:
                lines.append(" ".join(f"{x:.3f} {y:.3f}" for x, y in points))
        (out / relative).with_suffix(".lines.txt").write_text("\n".join(lines) + "\n")
        names.append("/" + relative)
    (out / "list" / "test_split").mkdir(parents=True, exist_ok=True)
    (out / "list" / "test.txt").write_text("\n".join(names) + "\n")
    for k, name in enumerate(CULANE_CATEGORY_LISTS):
        (out / "list" / "test_split" / f"{name}.txt").write_text("\n".join(names) + "\n" if k == 0 else "")
    return out


def read_culane_folder(folder: Path) -> dict[str, list[np.ndarray]]:
    """image path (relative, without extension) -> lanes (N, 2) of a folder of .lines.txt files."""
    out = {}
    for path in sorted(folder.rglob("*.lines.txt")):
        lanes = []
        for line in path.read_text().splitlines():
            values = [float(v) for v in line.split()]
            if values:
                lanes.append(np.asarray(values).reshape(-1, 2))
        out[str(path.relative_to(folder))[: -len(".lines.txt")]] = lanes
    return out


def compare_culane(ours_folder: Path, official_folder: Path) -> dict:
    """Per-point agreement of two folders of CULane .lines.txt for the same images: lanes matched as a set (each
    official lane to our lane sharing most rows with it, then the smallest largest |dx|), the largest |dx| at the
    rows both have, and the lanes whose point counts differ."""
    ours, official = read_culane_folder(ours_folder), read_culane_folder(official_folder)
    if set(ours) != set(official):
        raise SystemExit(f"the folders name different images: only ours {sorted(set(ours) - set(official))[:3]}, "
                         f"only official {sorted(set(official) - set(ours))[:3]}")
    largest, matched, unmatched, counts_differ, compared, examples = 0.0, 0, 0, 0, 0, []
    for image in sorted(official):
        candidates = []
        for j, b in enumerate(official[image]):
            for i, a in enumerate(ours[image]):
                rows = np.intersect1d(np.round(a[:, 1], 3), np.round(b[:, 1], 3))
                if len(rows):
                    xa = a[np.isin(np.round(a[:, 1], 3), rows), 0]
                    xb = b[np.isin(np.round(b[:, 1], 3), rows), 0]
                    candidates.append((-len(rows), float(np.abs(xa - xb).max()), i, j, len(rows)))
        used_i, used_j = set(), set()
        for _, dx, i, j, n in sorted(candidates):
            if i in used_i or j in used_j:
                continue
            used_i.add(i)
            used_j.add(j)
            matched += 1
            compared += n
            largest = max(largest, dx)
            if len(ours[image][i]) != len(official[image][j]):
                counts_differ += 1
                examples.append(f"{image}: our lane {i} has {len(ours[image][i])} points, the official's "
                                f"{len(official[image][j])}")
        unmatched += len(official[image]) - len(used_j) + len(ours[image]) - len(used_i)
    return {"lanes_matched": matched, "lanes_unmatched": unmatched, "points_compared": compared,
            "largest_dx": round(largest, 4), "point_counts_differ": counts_differ, "examples": examples[:12]}


def read_predictions(path: Path) -> dict[str, list[list[float]]]:
    """raw_file -> lanes (x per h_sample) of a TuSimple prediction file."""
    out = {}
    for line in path.read_text().splitlines():
        if line.strip():
            record = json.loads(line)
            out[record["raw_file"]] = record["lanes"]
    return out


def _pair_lanes(ours: list[list[float]], official: list[list[float]]) -> list[tuple[int | None, int | None]]:
    """Lanes matched as sets: greedily, the pair sharing the most valid rows with the smallest mean |dx| first;
    all -2 lanes are left out (the official UFLD writer emits them)."""
    ours_i = [i for i, lane in enumerate(ours) if any(x >= 0 for x in lane)]
    off_i = [j for j, lane in enumerate(official) if any(x >= 0 for x in lane)]
    pairs = []
    for i in ours_i:
        for j in off_i:
            a, b = np.asarray(ours[i], float), np.asarray(official[j], float)
            both = (a >= 0) & (b >= 0)
            if both.any():
                pairs.append((-int(both.sum()), float(np.abs(a[both] - b[both]).mean()), i, j))
    matched, used_i, used_j = [], set(), set()
    for _, _, i, j in sorted(pairs):
        if i not in used_i and j not in used_j:
            matched.append((i, j))
            used_i.add(i)
            used_j.add(j)
    matched += [(i, None) for i in ours_i if i not in used_i]
    matched += [(None, j) for j in off_i if j not in used_j]
    return matched


def compare(ours_path: Path, official_path: Path) -> dict:
    """Per-sample agreement of two TuSimple prediction files of the same images."""
    ours, official = read_predictions(ours_path), read_predictions(official_path)
    if set(ours) != set(official):
        raise SystemExit(f"the files name different images: only ours {sorted(set(ours) - set(official))[:3]}, "
                         f"only official {sorted(set(official) - set(ours))[:3]}")
    largest, dxs, differing, matched, unmatched, examples = 0.0, [], 0, 0, 0, []
    for raw_file in sorted(ours):
        for i, j in _pair_lanes(ours[raw_file], official[raw_file]):
            if i is None or j is None:
                unmatched += 1
                examples.append(f"{raw_file}: {'official' if i is None else 'our'} lane {j if i is None else i} "
                                f"has no partner")
                continue
            matched += 1
            a, b = np.asarray(ours[raw_file][i], float), np.asarray(official[raw_file][j], float)
            both = (a >= 0) & (b >= 0)
            dx = np.abs(a[both] - b[both])
            dxs.extend(dx.tolist())
            largest = max(largest, float(dx.max(initial=0.0)))
            one_sided = np.flatnonzero((a >= 0) != (b >= 0))
            differing += len(one_sided)
            for k in one_sided[:2]:
                examples.append(f"{raw_file} y={H_SAMPLES[k] if k < len(H_SAMPLES) else k}: ours {a[k]:g}, "
                                f"official {b[k]:g}")
    return {"lanes_matched": matched, "lanes_unmatched": unmatched, "samples_compared": len(dxs),
            "largest_dx": round(largest, 3), "mean_dx": round(float(np.mean(dxs)) if dxs else 0.0, 3),
            "samples_over_0.5px": int(sum(d > 0.5 for d in dxs)), "minus2_differ": differing,
            "examples": examples[:12]}


SIDE = Path(__file__).resolve().parent / "official_side"
# each family's official repository, by the folder name run expects under --repos
REPOSITORIES = {"ufld": "Ultra-Fast-Lane-Detection", "clrnet": "CLRNet", "scnn": "pytorch-auto-drive",
                "bezierlanenet": "pytorch-auto-drive", "laneatt": "LaneATT"}


def side_module(family: str):
    """benchmarks/official_side/<family>.py as a module (stdlib only at its top: OURS, OFFICIAL)."""
    import importlib.util

    path = SIDE / f"{family}.py"
    spec = importlib.util.spec_from_file_location(f"official_side_{family}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _run(argv: list[str], log: Path) -> None:
    """Run a command, its output into `log`; a failure names the command and the log's last lines."""
    import subprocess

    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("w") as out:
        code = subprocess.call(argv, stdout=out, stderr=subprocess.STDOUT)
    if code:
        tail = "\n".join(log.read_text().splitlines()[-15:])
        raise SystemExit(f"{' '.join(argv[:4])} ... failed ({code}); {log}:\n{tail}")


def run_family(family: str, dataset: str, repos: Path, official_python: str, work: Path,
               launch: Path | None, seed: int = 0) -> dict | None:
    """Steps 2-5 of the module docstring for one family on one dataset (tusimple, culane); its figures, or None
    where the family's side has no overrides for that dataset (OURS_CULANE)."""
    import shutil

    side = side_module(family)
    overrides = side.OURS if dataset == "tusimple" else getattr(side, "OURS_CULANE", None)
    if overrides is None:
        return None
    repo = repos / REPOSITORIES[family]
    if not repo.is_dir():
        raise SystemExit(f"--repos {repos}: no {REPOSITORIES[family]}/ (the official code of {family}, "
                         f"{side.OFFICIAL})")
    data, here = work / dataset, work / family / f"{dataset}_seed{seed}"
    checkpoint = here / "checkpoint.pth"
    official = here / ("official.json" if dataset == "tusimple" else "official_lines")
    side_script = str(SIDE / f"{family}.py")
    dataset_args = ["--dataset", dataset] if dataset != "tusimple" else []
    _run([official_python, side_script, "checkpoint", "--repo", str(repo), "--out", str(checkpoint),
          "--seed", str(seed), *dataset_args], here / "checkpoint.log")
    _run([official_python, side_script, "predict", "--repo", str(repo), "--ckpt", str(checkpoint),
          "--data-root", str(data), "--work", str(here / "official"), "--out", str(official), *dataset_args,
          *(["--launch", str(launch)] if launch else [])], here / "official.log")
    ours_dir = here / "ours"
    shutil.rmtree(ours_dir, ignore_errors=True)
    overrides = [o.format(work=here / "official") for o in overrides]  # {work}: the official side's --work
    _run([sys.executable, "-m", "lanevil_train", "task=evaluate", *overrides, f"ckpt_path={checkpoint}",
          f"data={dataset}", f"data.root={data}", "task.predictions=true", f"task.out_dir={ours_dir}",
          # no category table: the folder's test_split lists are empty but the first (the official code only
          # needs them to exist), and task=evaluate refuses an empty list before scoring
          "task.culane_categories=null", f"hydra.run.dir={here / 'hydra'}", "progress=plain"], here / "ours.log")
    if dataset == "tusimple":
        figures = compare(ours_dir / "predictions" / "pred_tusimple.json", official)
    else:
        figures = compare_culane(ours_dir / "predictions" / "culane", official)
    return {"family": family, "dataset": dataset, "seed": seed, "official": side.OFFICIAL, "ours": overrides,
            **figures}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    images = sub.add_parser("images", help="draw the image folders (<out>/tusimple, <out>/culane)")
    images.add_argument("--out", type=Path, required=True)
    images.add_argument("--count", type=int, default=4)
    cmp = sub.add_parser("compare", help="compare two TuSimple prediction files")
    cmp.add_argument("--ours", type=Path, required=True)
    cmp.add_argument("--official", type=Path, required=True)
    cmp.add_argument("--culane", action="store_true", help="--ours and --official are folders of .lines.txt")
    run = sub.add_parser("run", help="build, run both sides and compare, per family")
    run.add_argument("--repos", type=Path, required=True, help="folder of the official repositories")
    run.add_argument("--official-python", required=True, help="the python of the official code's environment")
    run.add_argument("--work", type=Path, required=True)
    run.add_argument("--family", action="append", choices=sorted(REPOSITORIES),
                     help="a family to compare (repeatable; default all)")
    run.add_argument("--launch", type=Path, help="launcher script standing in for CUDA (see the docstring)")
    run.add_argument("--dataset", action="append", choices=["tusimple", "culane"],
                     help="the layouts to compare (repeatable; default both)")
    run.add_argument("--seed", type=int, action="append",
                     help="the random official checkpoint's seed (repeatable; default 0)")
    args = parser.parse_args(argv)
    if args.command == "images":
        print(write_images(args.out / "tusimple", args.count), write_culane_images(args.out / "culane", args.count))
    elif args.command == "compare":
        figures = (compare_culane if args.culane else compare)(args.ours, args.official)
        print(json.dumps(figures, indent=1))
    else:
        write_images(args.work / "tusimple")
        write_culane_images(args.work / "culane")
        results = []
        for family in args.family or sorted(REPOSITORIES):
            for dataset in args.dataset or ["tusimple", "culane"]:
                for seed in args.seed or [0]:
                    print(f"{family} {dataset} seed {seed}: ...", flush=True)
                    result = run_family(family, dataset, args.repos, args.official_python, args.work, args.launch,
                                        seed)
                    if result is not None:
                        results.append(result)
                        print(json.dumps(result, indent=1), flush=True)
        (args.work / "parity.json").write_text(json.dumps(results, indent=1) + "\n")
        print(results_table(results))
    return 0


def results_table(results: list[dict]) -> str:
    """The figures of every run as a markdown table (benchmarks/RESULTS.md's)."""
    lines = ["| family | dataset | seed | official code | lanes matched | unmatched | largest abs dx (px) | "
             "TuSimple: samples > 0.5 px / -2 samples differing; CULane: lanes with another point count |",
             "|---|---|---|---|---|---|---|---|"]
    for r in results:
        other = (f"{r['samples_over_0.5px']} / {r['minus2_differ']}" if r["dataset"] == "tusimple"
                 else str(r["point_counts_differ"]))
        lines.append(f"| {r['family']} | {r['dataset']} | {r['seed']} | {r['official']} | {r['lanes_matched']} | "
                     f"{r['lanes_unmatched']} | {r['largest_dx']} | {other} |")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
