"""CULane file-level evaluation: ``.lines.txt`` trees scored exactly as the official ``evaluate`` tool."""

from __future__ import annotations

import math
import multiprocessing
import os
import warnings
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from typing import Sequence

import numpy as np

from lanevil_train.metrics.culane import (
    MF1_THRESHOLDS,
    culane_image_counts,
    culane_image_counts_multi,
    culane_leaderboard_scores,
    culane_summary,
)

__all__ = ["OddCountWarning", "read_lines_file", "lines_file_path", "count_images", "evaluate_culane_dirs",
           "CATEGORIES", "read_category_lists", "category_scores", "category_table"]

# The official per-scenario lists (list/test_split/ of CULane; run-full.sh runs the evaluator once per file), in
# the leaderboards' order. Cross images have no lanes: their row is the FP count.
CATEGORIES = (("normal", "test0_normal.txt"), ("crowd", "test1_crowd.txt"), ("hlight", "test2_hlight.txt"),
              ("shadow", "test3_shadow.txt"), ("noline", "test4_noline.txt"), ("arrow", "test5_arrow.txt"),
              ("curve", "test6_curve.txt"), ("cross", "test7_cross.txt"), ("night", "test8_night.txt"))
FP_ONLY = "cross"

IMAGES_PER_WORKER = 250  # below this a worker's start-up (~0.2-0.4 s: numpy + OpenCV) outweighs its share
CHUNKS_PER_WORKER = 4  # a few chunks per worker even out uneven images without much pickling


class OddCountWarning(UserWarning):
    """A .lines.txt line holds an odd count of numbers: scored as the official tool does, its last number dropped."""


def read_lines_file(path: str, side: str = "", odd: list[str] | None = None) -> list[np.ndarray]:
    """Lanes of a CULane ``.lines.txt`` like the official reader: one lane per line of "x y x y ..." pairs.

    A missing file means no lanes (as in evaluate.cpp); an odd trailing number is ignored like ``ss>>x>>y``, and
    said: an OddCountWarning naming file and line (or the note appended to `odd`, for the caller to report);
    a non-numeric or non-finite token (``nan``, ``inf``, which Python's float() accepts) raises ValueError
    naming file, line, lane and ``side`` (what the file holds: "prediction", "ground truth"). Blank lines are
    lanes with 0 points (the C++ counts them too).
    """
    if not os.path.exists(path):
        return []
    lane = f"{side} lane" if side else "lane"
    lanes = []
    with open(path) as f:
        for lineno, line in enumerate(f, 1):
            tokens = line.split()
            try:
                vals = [float(t) for t in tokens]
            except ValueError as e:
                raise ValueError(f"{path}:{lineno}: {lane} {lineno - 1}: expected numbers 'x y x y ...', "
                                 f"got {line.strip()!r}") from e
            if not all(map(math.isfinite, vals)):
                bad = next(t for t, v in zip(tokens, vals) if not math.isfinite(v))
                raise ValueError(f"{path}:{lineno}: {lane} {lineno - 1} has a non-finite coordinate {bad!r}; "
                                 f"expected finite pixel numbers 'x y x y ...'")
            if len(vals) % 2:
                note = (f"{path}:{lineno}: {lane} {lineno - 1} holds {len(vals)} numbers, an odd count; its last "
                        f"({tokens[-1]}) is dropped, as the official tool's 'ss >> x >> y' drops it")
                if odd is None:
                    warnings.warn(note, OddCountWarning, stacklevel=2)
                else:
                    odd.append(note)
            vals = vals[: len(vals) // 2 * 2]
            lanes.append(np.asarray(vals, np.float64).reshape(-1, 2))
    return lanes


def lines_file_path(name: str) -> str:
    """Relative ``.lines.txt`` path of a list entry: ``/d/v.MP4/00000.jpg`` -> ``d/v.MP4/00000.lines.txt``."""
    stem = name.strip().lstrip("/")
    if "." in os.path.basename(stem):
        stem = stem[: stem.rfind(".")]
    return stem + ".lines.txt"


def count_images(pred_dir: str, gt_dir: str, names: Sequence[str], width: int = 1640, height: int = 590,
                 lane_width: int = 30, iou_threshold: float = 0.5) -> tuple[int, int, int, list[str]]:
    """Summed (TP, FP, FN) of the list entries ``names``, scored one after another in this process, and the notes
    on lines with an odd count of numbers (read_lines_file)."""
    tp = fp = fn = 0
    odd: list[str] = []
    for name in names:
        rel = lines_file_path(name)
        a, b, c = culane_image_counts(read_lines_file(os.path.join(pred_dir, rel), "prediction", odd),
                                      read_lines_file(os.path.join(gt_dir, rel), "ground truth", odd),
                                      width, height, lane_width, iou_threshold)
        tp, fp, fn = tp + a, fp + b, fn + c
    return tp, fp, fn, odd


def image_counts(pred_dir: str, gt_dir: str, names: Sequence[str], width: int = 1640, height: int = 590,
                 lane_width: int = 30,
                 iou_thresholds: Sequence[float] = MF1_THRESHOLDS) -> tuple[np.ndarray, list[str]]:
    """Per image of ``names``: its TP at each of ``iou_thresholds``, then its predicted and its GT lane counts (an
    (images, thresholds + 2) int64 array; FP = predicted - TP, FN = GT - TP), one matching per image; and the
    notes on lines with an odd count of numbers."""
    rows = np.zeros((len(names), len(iou_thresholds) + 2), np.int64)
    odd: list[str] = []
    for i, name in enumerate(names):
        rel = lines_file_path(name)
        pred = read_lines_file(os.path.join(pred_dir, rel), "prediction", odd)
        gt = read_lines_file(os.path.join(gt_dir, rel), "ground truth", odd)
        counts = culane_image_counts_multi(pred, gt, width, height, lane_width, iou_thresholds)
        rows[i, :-2] = [tp for tp, _, _ in counts]
        rows[i, -2:] = len(pred), len(gt)
    return rows, odd


def totals_by_threshold(rows: np.ndarray, iou_thresholds: Sequence[float]) -> dict[float, tuple[int, int, int]]:
    """Summed (TP, FP, FN) per threshold of ``image_counts`` rows (all of them, or a category's)."""
    total = rows.sum(axis=0)
    n_pred, n_gt = int(total[-2]), int(total[-1])
    return {t: (int(tp), n_pred - int(tp), n_gt - int(tp)) for t, tp in zip(iou_thresholds, total[:-2])}


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask where the OS has one)."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return max(1, os.cpu_count() or 1)


def worker_count(workers: int | None, num_images: int) -> int:
    """Processes to use: ``workers`` if given (>= 1), else one per CPU but at least ``IMAGES_PER_WORKER`` each."""
    if workers is not None:
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        return min(workers, max(1, num_images))
    return max(1, min(available_cpus(), num_images // IMAGES_PER_WORKER))


def _read_list(list_file: str) -> list[str]:
    """The image paths of ``list_file``, one per non-blank line, or a ValueError naming list:line."""
    names = []
    with open(list_file) as f:
        for lineno, line in enumerate(f, 1):
            entry = line.strip()
            if not entry:
                continue
            columns = entry.split()
            if len(columns) > 1:
                # the official evaluate reads the whole line as the name: it resolves to no file, silently
                raise ValueError(
                    f"{list_file}:{lineno}: expected one image path per line, got {len(columns)} columns "
                    f"{entry!r} (a train_gt-style list? give the test list, e.g. list/test.txt, whose lines are "
                    f"image paths like /driver_100_30frame/05251517_0433.MP4/00000.jpg)")
            if "\\" in entry:
                raise ValueError(f"{list_file}:{lineno}: image path {entry!r} has backslashes; expected a "
                                 f"'/'-separated path like /driver_100_30frame/05251517_0433.MP4/00000.jpg")
            names.append(entry)
    if not names:
        raise ValueError(f"list file {list_file} has no image paths; expected one image path per line, "
                         f"like /driver_100_30frame/05251517_0433.MP4/00000.jpg")
    return names


def image_key(name: str) -> str:
    """An image's name in every list, its `.lines.txt` path: `/d/v.MP4/00000.jpg` -> `d/v.MP4/00000.lines.txt`."""
    return os.path.normpath(lines_file_path(name))


def read_category_lists(list_dir: str, scored: Sequence[str], arg: str = "--categories") -> dict[str, list[str]]:
    """The nine official category lists of ``list_dir`` (CATEGORIES: ``test0_normal.txt`` ... ``test8_night.txt``),
    each as the image keys (image_key) it names, in CATEGORIES order; checked before any scoring. Raises naming
    the folder (``arg``: the option that gave it), a missing file, or file:line of an image that is not among the
    ``scored`` list entries or is listed twice in its file."""
    if not os.path.isdir(list_dir):
        raise FileNotFoundError(f"{arg} {list_dir} is not a directory; expected CULane's list/test_split/ folder "
                                f"holding {', '.join(f for _, f in CATEGORIES)}")
    missing = [f for _, f in CATEGORIES if not os.path.isfile(os.path.join(list_dir, f))]
    if missing:
        raise FileNotFoundError(f"{arg} {list_dir} lacks the category list(s) {', '.join(missing)}; expected the "
                                f"nine official files {', '.join(f for _, f in CATEGORIES)}")
    known = {image_key(n) for n in scored}
    out = {}
    for category, filename in CATEGORIES:
        path = os.path.join(list_dir, filename)
        seen: dict[str, int] = {}
        with open(path) as f:
            numbered = [(lineno, line.strip()) for lineno, line in enumerate(f, 1) if line.strip()]
        _read_list(path)  # the list checks of the scored list: one path per line, '/' separators, not empty
        for lineno, entry in numbered:
            key = image_key(entry)
            if key not in known:
                raise ValueError(f"{path}:{lineno}: image {entry!r} is not in the scored list; a category list may "
                                 f"only name images that are scored (the test list's {len(known)} images)")
            if key in seen:
                raise ValueError(f"{path}:{lineno}: image {entry!r} is listed twice (first at line {seen[key]})")
            seen[key] = lineno
        out[category] = list(seen)
    return out


def category_scores(rows: np.ndarray, names: Sequence[str], categories: dict[str, list[str]],
                    iou_thresholds: Sequence[float]) -> dict[str, dict]:
    """Per category (read_category_lists): its images, TP/FP/FN at IoU 0.5, F1@50, F1@75 and mF1 (fractions), as
    the official evaluator run on its list alone would count them; cross: its images and FP only."""
    index = {}
    for i, name in enumerate(names):
        index.setdefault(image_key(name), i)
    out = {}
    for category, keys in categories.items():
        totals = totals_by_threshold(rows[[index[k] for k in keys]], iou_thresholds)
        tp, fp, fn = totals[0.5]
        if category == FP_ONLY:
            out[category] = {"images": len(keys), "FP": fp}
        else:
            out[category] = {"images": len(keys), "TP": tp, "FP": fp, "FN": fn, **culane_leaderboard_scores(totals)}
    return out


def category_table(result: dict) -> str:
    """Markdown of an evaluate_culane_dirs result: F1@50, F1@75 and mF1 (%) of the scored list and, when it has
    them, of each category (cross: its FP count only) and their total (IoU 0.5 for the FP column)."""
    rows = []
    for name, row in (result.get("categories") or {"total": result}).items():
        fp = row["FP"] if "categories" in result else ""  # without categories, FP is at --iou: left out
        scores = {key: None if name == FP_ONLY else 100 * row[key] for key in ("F1@50", "F1@75", "mF1")}
        rows.append({"list": name, "images": row["images"], **scores, "FP": fp})
    return category_markdown(rows)


def category_markdown(rows: list[dict]) -> str:
    """Rows of {list, images, F1@50, F1@75, mF1 (%), FP} as a markdown table: a score that is None (cross's) as '-',
    a float to two decimals."""
    columns = list(rows[0])
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for row in rows:
        cells = ["-" if row[c] is None else f"{row[c]:.2f}" if isinstance(row[c], float) else str(row[c])
                 for c in columns]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _check_dir(path: str, arg: str, holds: str) -> None:
    if not os.path.exists(path):
        raise FileNotFoundError(f"{arg} {path} does not exist; expected the directory of {holds} .lines.txt files")
    if not os.path.isdir(path):
        raise ValueError(f"{arg} {path} is not a directory; expected the directory of {holds} .lines.txt files")


def _check_inputs(pred_dir: str, gt_dir: str, list_file: str, width: int, height: int, lane_width: int,
                  iou_threshold: float) -> list[str]:
    """The list's image paths once every argument is valid, or an error naming the bad one (see below)."""
    if not os.path.isfile(list_file):
        raise FileNotFoundError(f"list file {list_file} does not exist")
    if width < 1 or height < 1 or lane_width < 1:
        raise ValueError(f"width, height, lane_width must be positive, got {width}, {height}, {lane_width}")
    if not 0 < iou_threshold < 1:  # also refuses nan
        raise ValueError(f"iou_threshold (--iou) must be a number between 0 and 1 (exclusive; official: 0.5), "
                         f"got {iou_threshold}")
    _check_dir(pred_dir, "pred_dir", "prediction")
    _check_dir(gt_dir, "gt_dir", "ground-truth")
    names = _read_list(list_file)
    first_gt = os.path.join(gt_dir, lines_file_path(names[0]))
    if not any(os.path.isfile(os.path.join(gt_dir, lines_file_path(n))) for n in names):
        raise ValueError(
            f"the list {list_file} and gt_dir {gt_dir} do not match: none of its {len(names)} image paths has a "
            f"ground-truth file (first entry {names[0]!r}: looked for {first_gt})")
    if not any(os.path.isfile(os.path.join(pred_dir, lines_file_path(n))) for n in names):
        raise ValueError(
            f"pred_dir {pred_dir} has no prediction file for any of the {len(names)} image paths of {list_file} "
            f"(first entry {names[0]!r}: looked for {os.path.join(pred_dir, lines_file_path(names[0]))}); "
            f"a missing file counts as an image with no lanes, but not for every image: a wrong pred_dir?")
    return names


def evaluate_culane_dirs(
    pred_dir: str,
    gt_dir: str,
    list_file: str,
    width: int = 1640,
    height: int = 590,
    lane_width: int = 30,
    iou_threshold: float = 0.5,
    workers: int | None = None,
    categories: str | None = None,
) -> dict:
    """Official file-level evaluation: for each image path in ``list_file``, ``<dir>/<path sans ext>.lines.txt``.

    Returns TP, FP, FN, Precision, Recall, F1 at ``iou_threshold`` (culane_summary), the number of images, and
    F1@50, F1@75, mF1 (culane_leaderboard_scores), all from one pass: each image's IoU matrix and matching are
    computed once and its TP counted at every threshold. ``categories``: a folder holding the nine official
    category lists (CATEGORIES, CULane's list/test_split/): adds "categories", {name: category_scores row} for the
    nine and a "total" row (every scored image, counts at IoU 0.5), each as the official evaluator counts that list.

    Images are split into contiguous chunks scored by ``workers`` processes (default: one per CPU for long
    lists, see ``worker_count``; 1 scores in this process). The counts are integers summed over images, so
    the result is the same for any number of workers.

    Inputs are checked before any scoring (``_check_inputs``, ``read_category_lists``): a missing prediction file
    is an image with no lanes, as officially, but a list none of whose entries has a GT file, or none a prediction
    file, is refused, and so is a category list that is missing or names an image outside ``list_file``.
    Lines with an odd count of numbers are scored as officially (the last number dropped) and reported in one
    OddCountWarning naming the first files and lines.
    """
    names = _check_inputs(pred_dir, gt_dir, list_file, width, height, lane_width, iou_threshold)
    lists = read_category_lists(categories, names) if categories is not None else None
    thresholds = tuple(dict.fromkeys((*MF1_THRESHOLDS, iou_threshold)))
    n_proc = worker_count(workers, len(names))
    score = partial(image_counts, pred_dir, gt_dir, width=width, height=height, lane_width=lane_width,
                    iou_thresholds=thresholds)
    if n_proc == 1:
        parts = [score(names)]
    else:
        size = -(-len(names) // (n_proc * CHUNKS_PER_WORKER))
        chunks = [names[i : i + size] for i in range(0, len(names), size)]
        # spawn, not fork: a fresh interpreter per worker is safe whatever threads the caller runs (torch,
        # OpenMP); it costs one numpy + OpenCV import per worker, paid in parallel.
        with ProcessPoolExecutor(n_proc, mp_context=multiprocessing.get_context("spawn")) as pool:
            parts = list(pool.map(score, chunks))
    odd = [note for part in parts for note in part[1]]
    if odd:
        verb = "hold" if len(odd) > 1 else "holds"
        warnings.warn(f"{len(odd)} line{'s' * (len(odd) > 1)} of the .lines.txt files {verb} an odd count of numbers, "
                      f"each scored as the official tool scores it (its last number dropped): "
                      f"{'; '.join(odd[:3])}{'; ...' if len(odd) > 3 else ''}", OddCountWarning, stacklevel=2)
    rows = np.concatenate([part[0] for part in parts])
    totals = totals_by_threshold(rows, thresholds)
    result = {**culane_summary(*totals[iou_threshold]), "images": len(names), **culane_leaderboard_scores(totals)}
    if lists is not None:
        tp, fp, fn = totals[0.5]
        result["categories"] = {**category_scores(rows, names, lists, thresholds),
                                "total": {"images": len(names), "TP": tp, "FP": fp, "FN": fn,
                                          **culane_leaderboard_scores(totals)}}
    return result
