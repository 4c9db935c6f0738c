"""CULane layout: a list file of image paths under ``root`` and one ``.lines.txt`` per image.

List lines are ``/driver_37_30frame/05181432_0203.MP4/00000.jpg`` (test/val lists) or, in
``train_gt.txt``, that path followed by a segmentation-mask path and 4 lane-existence flags.
``00000.lines.txt`` next to ``00000.jpg`` holds one lane per line as ``x1 y1 x2 y2 ...``; the
CULane GT writes points bottom-up (y descending, rows every 10 px), y as integers, x as floats
with ~6 significant digits, and x may be negative (outside the image). We keep points as
written (no clipping) and write bottom-up with fixed decimals, trailing zeros stripped.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from lanevil_train.data.formats.images import image_file_problem
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.lanes import as_lane

__all__ = ["read_culane", "read_culane_lanes", "write_culane_lanes", "write_culane", "lines_path_for"]


def lines_path_for(image_path: Path | str) -> Path:
    """The ``.lines.txt`` annotation path of a CULane image (``x/00000.jpg`` -> ``x/00000.lines.txt``)."""
    return Path(image_path).with_suffix(".lines.txt")


def read_culane_lanes(path: Path | str) -> list[np.ndarray]:
    """Parse one ``.lines.txt`` into lanes (N, 2), y descending; errors name the file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")  # a BOM is accepted
    except FileNotFoundError as e:
        raise FileNotFoundError(f"CULane annotation {path} not found") from e
    except OSError as e:
        raise FileNotFoundError(f"cannot read CULane annotation {path}: {e}") from e
    lanes = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) % 2:
            raise ValueError(f"{path}:{lineno}: odd number of coordinates ({len(tokens)}); expected x y pairs")
        try:
            values = [float(t) for t in tokens]
        except ValueError:
            bad = next(t for t in tokens if not _is_float(t))
            raise ValueError(f"{path}:{lineno}: non-numeric coordinate {bad!r}; expected 'x1 y1 x2 y2 ...'") from None
        lanes.append(as_lane(np.asarray(values).reshape(-1, 2), name=f"{path}:{lineno}"))
    return lanes


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _join(root: Path, rel: str) -> Path:
    """root / rel, where CULane list paths start with '/' but are relative to the dataset root."""
    return root / rel.lstrip("/")


def read_culane(
    list_file: Path | str, root: Path | str, check_images: bool = True, require_labels: bool = True
) -> list[dict]:
    """Read a CULane list file into records {"image_path", "rel_path", "lines_path", "lanes", ...}.

    train_gt-style lines also give "mask_path" and "exist" (4 ints). A missing ``.lines.txt`` is an
    error unless ``require_labels=False`` (unlabelled test sets): then "lanes" is [] and
    "labeled" False. An image listed twice is an error naming both lines; a UTF-8 BOM is accepted.
    """
    list_file, root = Path(list_file), Path(root)
    try:
        text = list_file.read_text(encoding="utf-8-sig")  # a BOM is accepted
    except OSError as e:
        raise FileNotFoundError(f"cannot read CULane list file {list_file}: {e}") from e
    records = []
    first_seen: dict[str, str] = {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue
        where = f"{list_file}:{lineno}"
        if len(tokens) not in (1, 6):
            raise ValueError(
                f"{where}: expected 'IMAGE' or 'IMAGE MASK e1 e2 e3 e4' (1 or 6 fields), got {len(tokens)}"
            )
        rel = tokens[0]
        key = os.path.normpath(rel.lstrip("/"))
        if key in first_seen:
            raise ValueError(
                f"{where}: image {rel} is listed twice (first at {first_seen[key]}); "
                "each image must appear once in a CULane list"
            )
        first_seen[key] = where
        record: dict = {"image_path": _join(root, rel), "rel_path": rel.lstrip("/"), "source": where}
        if len(tokens) == 6:
            try:
                exist = [int(t) for t in tokens[2:]]
            except ValueError:
                raise ValueError(f"{where}: lane existence flags must be 0/1, got {tokens[2:]}") from None
            if any(e not in (0, 1) for e in exist):
                raise ValueError(f"{where}: lane existence flags must be 0/1, got {tokens[2:]}")
            record["mask_path"] = _join(root, tokens[1])
            record["exist"] = exist
        problem = image_file_problem(record["image_path"]) if check_images else None
        if problem is not None:
            error = FileNotFoundError if problem == "not found" else ValueError
            raise error(f"{where}: image {record['image_path']} {problem}")
        lines_path = lines_path_for(record["image_path"])
        record["lines_path"] = lines_path
        if lines_path.is_dir():
            raise ValueError(f"{where}: annotation {lines_path} is a directory, not a .lines.txt file")
        if lines_path.is_file():
            record["lanes"] = read_culane_lanes(lines_path)
            record["labeled"] = True
        elif require_labels:
            raise FileNotFoundError(
                f"{where}: annotation {lines_path} not found (use require_labels=False for unlabelled sets)"
            )
        else:
            record["lanes"] = []
            record["labeled"] = False
        records.append(record)
    return records


def _fmt(value: float, decimals: int) -> str:
    """Fixed-point text with trailing zeros stripped (590.0 -> '590', 532.8930 -> '532.893')."""
    text = f"{value:.{decimals}f}"
    if "." in text:
        text = text.rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def write_culane_lanes(lanes: Sequence[np.ndarray], path: Path | str, decimals: int = 3) -> Path:
    """Write lanes to one ``.lines.txt`` (one lane per line, bottom point first); skips empty lanes."""
    path = Path(path)
    lines = []
    for j, lane in enumerate(lanes):
        arr = as_lane(lane, name=f"lane {j} for {path}")
        if len(arr):
            lines.append(" ".join(f"{_fmt(x, decimals)} {_fmt(y, decimals)}" for x, y in arr))
    atomic_write_text(path, "".join(line + "\n" for line in lines))
    return path


def _relative(path: Path, root: Path, what: str, index: int) -> str:
    try:
        return Path(os.path.relpath(Path(path).resolve(), root.resolve())).as_posix()
    except ValueError as e:  # different drives on Windows
        raise ValueError(f"record {index}: {what} {path} is not under root {root}") from e


def write_culane(records: Iterable[dict], root: Path | str, list_path: Path | str, decimals: int = 3) -> Path:
    """Write each record's lanes next to its image under ``root`` and a CULane list file.

    A record needs "rel_path" or an "image_path" under root. If every record has "mask_path" and
    "exist", the list is written train_gt-style (``/img /mask e1 e2 e3 e4``).
    """
    root = Path(root)
    entries = []
    for i, record in enumerate(records):
        if "rel_path" in record:
            rel = str(record["rel_path"]).lstrip("/")
        elif "image_path" in record:
            rel = _relative(Path(record["image_path"]), root, "image_path", i)
        else:
            raise ValueError(f"record {i}: needs 'rel_path' or 'image_path' to place its .lines.txt")
        if rel.startswith(".."):
            raise ValueError(f"record {i}: image {rel} is not under root {root}")
        write_culane_lanes(record.get("lanes", []), lines_path_for(root / rel), decimals)
        entry = "/" + rel
        if "mask_path" in record and "exist" in record:
            mask = _relative(Path(record["mask_path"]), root, "mask_path", i)
            entry = (entry, f"/{mask} " + " ".join(str(int(e)) for e in record["exist"]))
        entries.append(entry)
    full = all(isinstance(e, tuple) for e in entries) and entries
    text = "".join((f"{e[0]} {e[1]}" if full else (e[0] if isinstance(e, tuple) else e)) + "\n" for e in entries)
    list_path = Path(list_path)
    atomic_write_text(list_path, text)
    return list_path
