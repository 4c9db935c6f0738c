"""LLAMAS layout: one JSON label per image, lane markers turned into an x per image row as the official code does.

Layout (LaneATT ``lib/datasets/llamas.py`` l. 9-12, 44-48; CLRNet ``clrnet/datasets/llamas.py`` l. 10-13, 45-50 and
README l. 117-124): ``labels/{train,valid}/<recording>/<name>.json`` and the image of each at
``color_images/{train,valid}/<recording>/<name>_color_rect.png`` (``.json`` -> ``_color_rect.png``);
``color_images/test`` has no public labels, so both repositories score the ``valid`` split (their ``val``). The
images are 1276 x 717 (LaneATT ``lib/datasets/llamas.py`` l. 26; CLRNet ``configs/clrnet/clr_resnet18_llamas.py``
l. 47-48).

A label is a JSON object whose ``lanes`` each have a ``lane_id`` (``l1``, ``l0``, ``r0``, ``r1`` ...) and
``markers``, each marker with ``pixel_start``/``pixel_end`` {x, y} and ``world_start``/``world_end`` {x, y, z}.
The official per-row lanes (``get_horizontal_values_for_four_lanes``, LaneATT ``utils/llamas_utils.py``
l. 262-299, identical in CLRNet ``clrnet/utils/llamas_utils.py``; read at LaneATT 2f8583b, CLRNet 7269e9d), whose
procedure is reimplemented here (line numbers of LaneATT's ``utils/llamas_utils.py``):

1. ``read_json`` (l. 342-363): pixel coordinates become ``int(v)`` (truncation), world ones ``float(v)``. Before
   that, lanes whose markers' ``int(pixel_start.y)`` span (max - min) is under 20 rows are dropped (l. 302-311,
   ``min_height=20`` from l. 342), then lanes with fewer than 2 markers (l. 314-320).
2. Lane names are renumbered per side (l. 323-339): the ids sorted as strings, the ``l...`` ones renamed ``l0``,
   ``l1``, ... in that order and the ``r...`` ones ``r0``, ``r1``, ... (so ``l0, l2, l3`` -> ``l0, l1, l2``).
3. Each lane gets an extra marker at the front reaching the image's bottom (``_extend_lane``, l. 59-131): among
   the markers whose pixel start and end differ in both x and y, the one with the smallest ``world_start.z``
   (the first such on ties); unless that z is negative, its pixel line from start through end is extended from
   the start to row 716: x0 = sx + (716 - sy) (ex - sx) / (ey - sy). If x0 < 0 the new point is (0, sy - sx
   (ey - sy) / (ex - sx)), if x0 > 1276 it is (1276, sy + (1276 - sx) (ey - sy) / (ex - sx)), else (x0, 716),
   each rounded with Python's ``round`` (half to even); the new marker runs from that point to the chosen
   marker's start.
4. ``_sample_points`` (l. 160-231) over the markers (the new one first): every marker adds its start x at its
   start row; one whose start lies more than 2 rows below its end (h = sy - ey > 2) adds, for i = 0..h,
   round(sx + i (ex - sx) / h) at row round(sy - i) (its start row thus twice). Each row's x is the mean of what it
   got, -1 where nothing (a mean of exactly -1 counts as missing too). Missing rows between the first and the
   last set row are filled walking down the rows: x[c] = x[c - 1] + (x[n] - x[c - 1]) / (n - c + 1), n the next
   set row. Rows above the first and below the last set row stay missing.
5. Four lanes are kept, in the order l1, l0, r0, r1 (l. 293-299; a missing one is all -1; ``l2``, ``r2`` ...
   are dropped), each an x per row 0..716.

The dataset loaders keep the rows with x >= 0 and drop empty lanes (LaneATT ``lib/datasets/llamas.py`` l. 84-86;
CLRNet l. 100-107 also drops lanes of <= 2 points). Here a lane needs >= 2 points (the metric ignores shorter ones:
``utils/llamas_metric.py`` l. 144), and each record keeps the ids of the lanes it holds (``lane_ids``).

Where the official code would crash or index outside its 717 rows, this reader decides: a lane with no marker is
dropped (``min`` of nothing, l. 306); a lane to keep with no marker differing in both x and y is an error naming
the file and lane (l. 78 ``min`` of nothing); rows outside 0..716 are ignored (l. 183, 192 index a 717-list: an
IndexError, or a negative index wrapping to the bottom). World x and y, and ``projection_matrix``, are not used
for the pixels and not required; ``world_start.z`` is.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from lanevil_train.data.formats.images import image_file_problem
from lanevil_train.files.jsonl import read_json_label
from lanevil_train.lanes import as_lane

__all__ = ["LLAMAS_HEIGHT", "LLAMAS_WIDTH", "LLAMAS_LANE_IDS", "LLAMAS_SPLITS", "read_llamas", "read_llamas_label",
           "llamas_rows", "image_path_for"]

LLAMAS_HEIGHT, LLAMAS_WIDTH = 717, 1276
LLAMAS_LANE_IDS = ("l1", "l0", "r0", "r1")  # the official order of the four lanes
LLAMAS_SPLITS = ("train", "valid", "test")  # folder names; test has images only
_MIN_LANE_HEIGHT = 20
_MIN_MARKERS = 2
_BOTTOM = LLAMAS_HEIGHT - 1
_MISSING = -1.0


def image_path_for(label_path: Path | str, root: Path | str) -> Path:
    """``labels/<split>/<recording>/<name>.json`` -> ``root/color_images/<split>/<recording>/<name>_color_rect.png``."""
    parts = Path(label_path).parts[-3:]
    return Path(root, "color_images", *parts[:-1], parts[-1][: -len(".json")] + "_color_rect.png")


def _number(value, where: str, convert):
    """convert(value) (int or float) of a number, or of a string it reads, as the official read_json does."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ValueError(f"{where}: expected a number, got {json.dumps(value)[:60]}")
    try:
        return convert(value)
    except (ValueError, OverflowError):
        raise ValueError(f"{where}: expected a number, got {json.dumps(value)[:60]}") from None


def _pixel(value, where: str) -> int:
    """int(v) of a pixel coordinate."""
    return _number(value, where, int)


def _world(value, where: str) -> float:
    """A world coordinate (m), finite."""
    out = _number(value, where, float)
    if not np.isfinite(out):
        raise ValueError(f"{where}: expected a finite number, got {value!r}")
    return out


def _point(marker: dict, key: str, where: str) -> tuple[int, int]:
    p = marker.get(key)
    if not isinstance(p, dict) or "x" not in p or "y" not in p:
        raise ValueError(f"{where}.{key}: expected an object {{\"x\": ..., \"y\": ...}}, got {json.dumps(p)[:60]}")
    return _pixel(p["x"], f"{where}.{key}.x"), _pixel(p["y"], f"{where}.{key}.y")


def _parse(obj, path: Path) -> list[tuple[str, list[tuple[int, int, int, int, float]]]]:
    """(lane_id, markers as (sx, sy, ex, ey, world_start.z)) per lane, every field checked."""
    if not isinstance(obj, dict) or "lanes" not in obj:
        raise ValueError(f"{path}: expected a JSON object with key 'lanes' (a LLAMAS label), "
                         f"got {type(obj).__name__ if not isinstance(obj, dict) else 'keys ' + str(list(obj))[:80]}")
    if not isinstance(obj["lanes"], list):
        raise ValueError(f"{path}: lanes: expected a list of lanes, got {type(obj['lanes']).__name__}")
    lanes = []
    for j, lane in enumerate(obj["lanes"]):
        where = f"{path}: lanes[{j}]"
        if not isinstance(lane, dict) or "lane_id" not in lane or "markers" not in lane:
            raise ValueError(f"{where}: expected an object with 'lane_id' and 'markers', got {json.dumps(lane)[:80]}")
        lane_id = lane["lane_id"]
        if not isinstance(lane_id, str) or lane_id[:1] not in ("l", "r"):
            raise ValueError(f"{where}.lane_id: expected a name starting with 'l' or 'r' (l1, l0, r0, r1 ...), "
                             f"got {json.dumps(lane_id)}")
        if not isinstance(lane["markers"], list):
            raise ValueError(f"{where}.markers: expected a list of markers, got {type(lane['markers']).__name__}")
        markers = []
        for k, marker in enumerate(lane["markers"]):
            mwhere = f"{where}.markers[{k}]"
            if not isinstance(marker, dict):
                raise ValueError(f"{mwhere}: expected a marker object, got {json.dumps(marker)[:60]}")
            sx, sy = _point(marker, "pixel_start", mwhere)
            ex, ey = _point(marker, "pixel_end", mwhere)
            ws = marker.get("world_start")
            if not isinstance(ws, dict) or "z" not in ws:
                raise ValueError(f"{mwhere}.world_start: expected an object with 'z', got {json.dumps(ws)[:60]}")
            markers.append((sx, sy, ex, ey, _world(ws["z"], f"{mwhere}.world_start.z")))
        lanes.append((lane_id, markers))
    return lanes


def _renamed(lanes: list) -> list:
    """Drop short and few-marker lanes, then renumber each side's ids in sorted order (read_json, l. 342-349)."""
    kept = []
    for lane_id, markers in lanes:
        if not markers:
            continue
        starts = [m[1] for m in markers]
        if max(starts) - min(starts) < _MIN_LANE_HEIGHT or len(markers) < _MIN_MARKERS:
            continue
        kept.append((lane_id, markers))
    mapping, counters = {}, {"l": 0, "r": 0}
    for lane_id in sorted(i for i, _ in kept):
        mapping[lane_id] = f"{lane_id[0]}{counters[lane_id[0]]}"
        counters[lane_id[0]] += 1
    return [(mapping[i], m, i, j) for j, (i, m) in enumerate(kept)]


def _extension(markers: list, where: str) -> tuple[int, int, int, int] | None:
    """The marker reaching the bottom row that _extend_lane puts first, or None when it adds none."""
    sloped = [m for m in markers if m[1] != m[3] and m[0] != m[2]]
    if not sloped:
        raise ValueError(f"{where}: no marker whose pixel start and end differ in both x and y; the official "
                         "lane extension (llamas_utils._extend_lane) needs one")
    sx, sy, ex, ey, z = min(sloped, key=lambda m: m[4])  # min keeps the first of equal z
    if z < 0:
        return None
    x0 = sx + (_BOTTOM - sy) * ((ex - sx) / (ey - sy))
    if x0 < 0:
        point = (0, sy - sx * ((ey - sy) / (ex - sx)))
    elif x0 > LLAMAS_WIDTH:
        point = (LLAMAS_WIDTH, sy + (LLAMAS_WIDTH - sx) * ((ey - sy) / (ex - sx)))
    else:
        point = (x0, _BOTTOM)
    return int(round(point[0])), int(round(point[1])), sx, sy


def _row_xs(markers: list[tuple[int, int, int, int]]) -> np.ndarray:
    """_sample_points: an x per row 0..716 (the mean of the markers' samples, gaps between them filled), -1 missing."""
    sums = np.zeros(LLAMAS_HEIGHT)
    counts = np.zeros(LLAMAS_HEIGHT, np.int64)

    def add(rows: np.ndarray, xs: np.ndarray) -> None:
        ok = (rows >= 0) & (rows < LLAMAS_HEIGHT)
        np.add.at(sums, rows[ok], xs[ok])
        np.add.at(counts, rows[ok], 1)

    for sx, sy, ex, ey in markers:
        add(np.array([sy]), np.array([float(sx)]))
        height = sy - ey
        if height > 2:
            i = np.arange(height + 1)
            slope = (ex - sx) / height
            add(np.rint(sy - i.astype(np.float64)).astype(np.int64), np.rint(sx + slope * i))
    xs = np.full(LLAMAS_HEIGHT, _MISSING)
    np.divide(sums, counts, out=xs, where=counts > 0)  # integer sums: exact, as Python's sum of the ints
    set_rows = np.flatnonzero(xs != _MISSING)
    if len(set_rows) == 0:
        return xs
    for current in range(int(set_rows[0]) + 1, int(set_rows[-1])):
        if xs[current] != _MISSING:
            continue
        nxt = int(set_rows[np.searchsorted(set_rows, current)])  # the next set row (rows filled here are before it)
        xs[current] = xs[current - 1] + (xs[nxt] - xs[current - 1]) / (nxt - current + 1)
    return xs


def llamas_rows(obj, path: Path | str = "<label>") -> dict[str, np.ndarray]:
    """The official x per row (717 values, -1 where missing) of each of l1, l0, r0, r1 present in a parsed label."""
    path = Path(path)
    out: dict[str, np.ndarray] = {}
    for name, markers, original_id, index in _renamed(_parse(obj, path)):
        if name not in LLAMAS_LANE_IDS:
            continue
        extra = _extension(markers, f"{path}: lanes[{index}] (lane_id {original_id!r})")
        pixels = [m[:4] for m in markers]
        out[name] = _row_xs(([extra] if extra else []) + pixels)  # a later lane of the same name wins, as officially
    return out


def read_llamas_label(path: Path | str) -> tuple[list[np.ndarray], list[str]]:
    """One label file -> (lanes as (N, 2) arrays, y descending, in the order l1, l0, r0, r1; their ids).

    A lane keeps the rows with x >= 0 and needs at least 2 of them. Errors name the file and the key at fault.
    """
    path = Path(path)
    obj = read_json_label(path, "LLAMAS label")
    rows = llamas_rows(obj, path)
    ys = np.arange(LLAMAS_HEIGHT, dtype=np.float64)
    lanes, ids = [], []
    for name in LLAMAS_LANE_IDS:
        xs = rows.get(name)
        if xs is None:
            continue
        valid = xs >= 0
        if valid.sum() >= 2:
            lanes.append(as_lane(np.stack([xs[valid], ys[valid]], 1), name=f"{path} lane {name}"))
            ids.append(name)
    return lanes, ids


def read_llamas(root: Path | str, split: str = "valid", check_images: bool = True) -> list[dict]:
    """Records {"image_path", "rel_path", "label_path", "lanes", "lane_ids", "labeled", "source"} of a LLAMAS split.

    ``split`` is a folder name: "train" or "valid" read ``labels/<split>`` (sorted by path), "test" lists
    ``color_images/test`` (no public labels: "lanes" [] and "labeled" False). Every label is parsed and every
    image checked here, so a bad file stops the run before any long work, naming it.
    """
    root = Path(root)
    if split not in LLAMAS_SPLITS:
        raise ValueError(f"LLAMAS split {split!r}: expected one of {', '.join(LLAMAS_SPLITS)} (folder names under "
                         f"{root / 'labels'} and {root / 'color_images'}; 'val' is 'valid')")
    if split == "test":
        folder = root / "color_images" / "test"
        if not folder.is_dir():
            raise FileNotFoundError(f"LLAMAS image folder {folder} not found (expected color_images/test/<recording>/"
                                    "<name>_color_rect.png under the dataset root)")
        records = []
        for image_path in sorted(folder.rglob("*.png")):
            rel = image_path.relative_to(root).as_posix()
            records.append({"image_path": image_path, "rel_path": rel, "lanes": [], "lane_ids": [],
                            "labeled": False, "source": str(image_path)})
        return records
    folder = root / "labels" / split
    if not folder.is_dir():
        raise FileNotFoundError(f"LLAMAS label folder {folder} not found (expected labels/{split}/<recording>/"
                                "<name>.json under the dataset root)")
    records = []
    for label_path in sorted(folder.rglob("*.json")):
        if len(label_path.relative_to(folder).parts) != 2:
            raise ValueError(f"{label_path}: expected labels/{split}/<recording>/<name>.json (one folder level "
                             f"under {folder})")
        lanes, ids = read_llamas_label(label_path)
        image_path = image_path_for(label_path, root)
        problem = image_file_problem(image_path) if check_images else None
        if problem is not None:
            error = FileNotFoundError if problem == "not found" else ValueError
            raise error(f"{label_path}: image {image_path} {problem}")
        records.append({"image_path": image_path, "rel_path": os.path.relpath(image_path, root).replace(os.sep, "/"),
                        "label_path": label_path, "lanes": lanes, "lane_ids": ids, "labeled": True,
                        "source": str(label_path)})
    return records
