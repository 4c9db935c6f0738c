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

from lanevil_train.metrics.culane import culane_image_counts, culane_summary

__all__ = ["OddCountWarning", "read_lines_file", "lines_file_path", "count_images", "evaluate_culane_dirs"]

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
) -> dict:
    """Official file-level evaluation: for each image path in ``list_file``, ``<dir>/<path sans ext>.lines.txt``.

    Images are split into contiguous chunks scored by ``workers`` processes (default: one per CPU for long
    lists, see ``worker_count``; 1 scores in this process). The counts are integers summed over images, so
    the result is the same for any number of workers.

    Inputs are checked before any scoring (``_check_inputs``): a missing prediction file is an image with no
    lanes, as officially, but a list none of whose entries has a GT file, or none a prediction file, is refused.
    Lines with an odd count of numbers are scored as officially (the last number dropped) and reported in one
    OddCountWarning naming the first files and lines.
    """
    names = _check_inputs(pred_dir, gt_dir, list_file, width, height, lane_width, iou_threshold)
    n_proc = worker_count(workers, len(names))
    score = partial(count_images, pred_dir, gt_dir, width=width, height=height, lane_width=lane_width,
                    iou_threshold=iou_threshold)
    if n_proc == 1:
        counts = [score(names)]
    else:
        size = -(-len(names) // (n_proc * CHUNKS_PER_WORKER))
        chunks = [names[i : i + size] for i in range(0, len(names), size)]
        # spawn, not fork: a fresh interpreter per worker is safe whatever threads the caller runs (torch,
        # OpenMP); it costs one numpy + OpenCV import per worker, paid in parallel.
        with ProcessPoolExecutor(n_proc, mp_context=multiprocessing.get_context("spawn")) as pool:
            counts = list(pool.map(score, chunks))
    odd = [note for c in counts for note in c[3]]
    if odd:
        verb = "hold" if len(odd) > 1 else "holds"
        warnings.warn(f"{len(odd)} line{'s' * (len(odd) > 1)} of the .lines.txt files {verb} an odd count of numbers, "
                      f"each scored as the official tool scores it (its last number dropped): "
                      f"{'; '.join(odd[:3])}{'; ...' if len(odd) > 3 else ''}", OddCountWarning, stacklevel=2)
    return culane_summary(*(sum(c[k] for c in counts) for k in range(3)))
