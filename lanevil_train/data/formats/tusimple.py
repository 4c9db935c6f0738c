"""TuSimple labels: JSON lines {"lanes": [[x per h_sample]], "h_samples": [y], "raw_file": "clips/..."}.

x = -2 (any x < 0) marks "no lane point on this row". Reading converts each lane to an (N, 2)
pixel array (y descending, invalid rows removed); writing samples lanes back at the record's
h_samples. Prediction files use the same layout plus "run_time" and no "h_samples" needed by
the official script (we write them anyway, which it ignores).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from lanevil_train.data.formats.images import image_file_problem
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.files.jsonl import read_json_objects
from lanevil_train.lanes import INVALID_X, TUSIMPLE_H_SAMPLES, as_lane, lane_x_at, rows_to_lane

__all__ = ["read_tusimple", "write_tusimple"]

_REQUIRED = ("lanes", "h_samples", "raw_file")


def _numbers(value, where: str, what: str) -> np.ndarray:
    """A 1-D float array from a JSON list of numbers, or a clear error."""
    if not isinstance(value, list) or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
    ):
        raise ValueError(f"{where}: {what} must be a list of numbers, got {str(value)[:80]}")
    arr = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{where}: {what} contains non-finite values")
    return arr


def _check_line(obj: dict, where: str) -> dict:
    """TuSimple-specific checks of one parsed label line."""
    if not isinstance(obj["raw_file"], str) or not obj["raw_file"]:
        raise ValueError(f"{where}: raw_file must be a non-empty string, got {obj['raw_file']!r}")
    if not isinstance(obj["lanes"], list):
        raise ValueError(f"{where}: lanes must be a list of lanes, got {type(obj['lanes']).__name__}")
    return obj


def _check_h_samples(ys: np.ndarray, where: str) -> None:
    """h_samples are image rows: none negative, none repeated (any order is fine)."""
    negative = ys[ys < 0]
    if negative.size:
        raise ValueError(
            f"{where}: h_samples contains negative value {_num(negative[0])}; expected image rows y >= 0"
        )
    values, counts = np.unique(ys, return_counts=True)
    repeated = values[counts > 1]
    if repeated.size:
        raise ValueError(
            f"{where}: h_samples repeats value {_num(repeated[0])} ({int(counts[counts > 1][0])} times); "
            "expected each row once"
        )


def _num(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else str(float(v))


def read_tusimple(
    label_files: Sequence[Path | str] | Path | str,
    root: Path | str,
    check_images: bool = True,
    keep_empty: bool = False,
) -> list[dict]:
    """Read TuSimple label files into records {"raw_file", "image_path", "lanes", "h_samples", "source"}.

    Lanes keep the file's order; a lane with no valid point is dropped unless ``keep_empty``
    (the official metric still counts such a GT lane, so keep them to score exactly).
    Errors name file:line: an image (raw_file) on two lines, in one file or across ``label_files``,
    and negative or repeated h_samples are refused (unsorted h_samples are fine). A UTF-8 BOM is accepted.
    """
    if isinstance(label_files, (str, Path)):
        label_files = [label_files]
    root = Path(root)
    records: list[dict] = []
    first_seen: dict[str, str] = {}
    for label_file in map(Path, label_files):
        for where, obj in read_json_objects(label_file, _REQUIRED, "TuSimple label"):
            _check_line(obj, where)
            key = os.path.normpath(obj["raw_file"].lstrip("/"))
            if key in first_seen:
                raise ValueError(
                    f"{where}: raw_file {obj['raw_file']!r} appears twice (first at {first_seen[key]}); "
                    "each image must have one label line"
                )
            first_seen[key] = where
            ys = _numbers(obj["h_samples"], where, "h_samples")
            _check_h_samples(ys, where)
            lanes = []
            for j, xs in enumerate(obj["lanes"]):
                row = _numbers(xs, where, f"lane {j}")
                if row.shape != ys.shape:
                    raise ValueError(
                        f"{where}: lane {j} has {row.size} x values but h_samples has {ys.size}"
                    )
                lane = rows_to_lane(row, ys)
                if len(lane) or keep_empty:
                    lanes.append(lane)
            image_path = root / obj["raw_file"]
            problem = image_file_problem(image_path) if check_images else None
            if problem is not None:
                error = FileNotFoundError if problem == "not found" else ValueError
                raise error(f"{where}: image {image_path} (raw_file {obj['raw_file']!r}) {problem}")
            records.append(
                {"raw_file": obj["raw_file"], "image_path": image_path, "lanes": lanes, "h_samples": ys,
                 "source": where}
            )
    return records


def _number_list(values: np.ndarray, as_int: bool) -> list:
    """JSON-ready numbers: ints when asked (or when all values are integral), floats otherwise."""
    if as_int or np.all(values == np.round(values)):
        return [int(v) for v in np.round(values)]
    return [float(v) for v in values]


def _record_line(record: dict, index: int, int_x: bool) -> str:
    """One JSON line for a record; raises naming the record index on bad content."""
    if "raw_file" not in record:
        raise ValueError(f"record {index}: missing 'raw_file' (needed to write a TuSimple line)")
    ys = np.asarray(record.get("h_samples", TUSIMPLE_H_SAMPLES), dtype=np.float64).reshape(-1)
    rows = []
    for j, lane in enumerate(record.get("lanes", [])):
        xs = lane_x_at(as_lane(lane, name=f"record {index} lane {j}"), ys)
        if int_x:
            xs = np.round(xs)
        xs[xs < 0] = INVALID_X  # anything off the image's left edge is "no point" in TuSimple
        rows.append(_number_list(xs, int_x))
    obj = {"lanes": rows, "h_samples": _number_list(ys, False), "raw_file": str(record["raw_file"])}
    if "run_time" in record:
        obj["run_time"] = float(record["run_time"])
    return json.dumps(obj)


def write_tusimple(
    records: Iterable[dict], path: Path | str, int_x: bool = True, append: bool = False
) -> Path:
    """Write records as TuSimple JSON lines (lanes resampled at each record's h_samples).

    x is rounded to int as in TuSimple GT unless ``int_x=False`` (predictions may be floats);
    missing h_samples default to TuSimple's 160..710. A record's "run_time" is written if present.
    The file is replaced atomically, or with ``append`` extended line by line (flushed per line).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if append:
        with open(path, "a", encoding="utf-8") as f:
            for i, record in enumerate(records):
                f.write(_record_line(record, i, int_x) + "\n")
                f.flush()
        return path
    atomic_write_text(path, "".join(_record_line(record, i, int_x) + "\n" for i, record in enumerate(records)))
    return path
