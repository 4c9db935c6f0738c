"""CurveLanes layout (Xu et al., ECCV 2020, "CurveLane-NAS"): a list file and one ``.lines.json`` per image.

Facts, from the dataset kit's README (github SoulmateB/CurveLanes at c47eca7, README.md; its "Evaluation Tools"
section, l. 127-129, says "To be provided": the kit ships no evaluation code, see metrics/curvelanes.py):

* Three split folders (l. 24-60): ``train`` (``images/``, ``labels/``, ``train.txt``), ``valid`` (``images/``,
  ``labels/``, ``valid.txt``) and ``test`` (``images/`` and ``test.txt``; its labels are not public). The kit's
  own ``test.txt`` (same commit) lists its 30,000 images as ``images/<md5>.jpg``: list entries are relative to the
  split folder. 100K train, 20K valid, 30K test images (l. 9).
* The label of ``<split>/images/<name>.jpg`` is ``<split>/labels/<name>.lines.json`` (l. 62-83):
  ``{"Lines": [lane, ...]}``, each lane a list of key points ``{"x": "2079.41", "y": "1439.0"}`` (the example
  writes the numbers as strings) "of a lane marking that has at least two key points", annotated as natural
  cubic splines (l. 12).
* Image sizes vary: "most" are 2560 x 1440 (l. 9 says 2650 x 1440, a typo); the loaders of
  aliyun/conditional-lane-detection (``mmdet/datasets/curvelanes_dataset.py`` at 6deb6c2, l. 23-38) and CLRerNet's
  CurveLanes branch (hirotomusiker/CLRerNet ``libs/datasets/curvelanes_dataset.py`` at 33add07, l. 32-48) know
  2560 x 1440, 1570 x 660 and 1280 x 720 (and skip any other size), cropping the top 640, 180 and 368 rows.
* Both score the ``valid`` split (CLRerNet ``configs/clrernet/curvelanes/dataset_curvelanes_clrernet.py`` at
  29c9e9a: its val and test are ``valid/valid.txt``), with the metric of metrics/curvelanes.py.

This reader: ``read_curvelanes(root, split)`` reads ``<root>/<split>/<split>.txt`` and every label it names, and
checks every label and image before any work, each error naming the file and the field (``Lines[2][5].x``): a
missing or unreadable label, malformed JSON, no ``Lines`` list, a point that is not an ``{"x", "y"}`` object, a
coordinate that is not a finite number (or a string of one), a lane of fewer than 2 points, a missing image or a
file that is not an image, an image listed twice, and, with the official list file, a label in ``labels/`` whose
image the list does not name (a list of your own, ``list_file``, may name a subset). Records keep the lanes as the
rest of the package does (float64 (N, 2), y descending: ``lanes.as_lane``); ``read_curvelanes_label`` gives them
in the file's order, which the metric command draws (metrics/curvelanes.py).
"""

from __future__ import annotations

import json
import math
from pathlib import Path, PurePosixPath

import numpy as np

from lanevil_train.data.formats.images import image_file_problem
from lanevil_train.files.jsonl import read_json_label
from lanevil_train.lanes import as_lane

__all__ = ["CURVELANES_SPLITS", "LABEL_SUFFIX", "read_curvelanes", "read_curvelanes_label", "parse_curvelanes_label",
           "label_path_for", "official_list_file", "read_list_file", "image_size_of"]

CURVELANES_SPLITS = ("train", "valid", "test")  # folder names; test has images and its list only
LABEL_SUFFIX = ".lines.json"
_MIN_POINTS = 2


def official_list_file(root: Path | str, split: str) -> Path:
    """``<root>/<split>/<split>.txt`` (train/train.txt, valid/valid.txt, test/test.txt)."""
    return Path(root, split, f"{split}.txt")


def label_path_for(split_dir: Path | str, entry: str) -> Path:
    """``images/<name>.jpg`` (a list entry) -> ``<split_dir>/labels/<name>.lines.json``."""
    name = PurePosixPath(entry).name
    stem = name[: name.rfind(".")] if "." in name else name
    return Path(split_dir, "labels", stem + LABEL_SUFFIX)


def _coordinate(value, where: str) -> float:
    """A finite coordinate from a number or a string of one (the official labels write strings)."""
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise ValueError(f"{where}: expected a number or a string of one, got {json.dumps(value)[:60]}")
    try:
        out = float(value)
    except (ValueError, OverflowError):
        raise ValueError(f"{where}: expected a number or a string of one, got {json.dumps(value)[:60]}") from None
    if not math.isfinite(out):
        raise ValueError(f"{where}: expected a finite number, got {json.dumps(value)[:60]}")
    return out


def parse_curvelanes_label(obj, path: Path | str = "<label>") -> list[np.ndarray]:
    """The lanes of a parsed label as (N, 2) float64 (x, y) arrays in the file's point order; every field checked."""
    if not isinstance(obj, dict) or "Lines" not in obj:
        got = f"keys {list(obj)[:8]}" if isinstance(obj, dict) else type(obj).__name__
        raise ValueError(f"{path}: expected a JSON object with key 'Lines' (a CurveLanes label), got {got}")
    if not isinstance(obj["Lines"], list):
        raise ValueError(f"{path}: Lines: expected a list of lanes, got {type(obj['Lines']).__name__}")
    lanes = []
    for j, lane in enumerate(obj["Lines"]):
        where = f"{path}: Lines[{j}]"
        if not isinstance(lane, list):
            raise ValueError(f"{where}: expected a list of points {{\"x\": ..., \"y\": ...}}, got "
                             f"{json.dumps(lane)[:60]}")
        if len(lane) < _MIN_POINTS:
            raise ValueError(f"{where}: {len(lane)} point(s); a CurveLanes lane has at least {_MIN_POINTS}")
        points = []
        for k, point in enumerate(lane):
            if not isinstance(point, dict) or "x" not in point or "y" not in point:
                raise ValueError(f"{where}[{k}]: expected an object {{\"x\": ..., \"y\": ...}}, got "
                                 f"{json.dumps(point)[:60]}")
            points.append((_coordinate(point["x"], f"{where}[{k}].x"), _coordinate(point["y"], f"{where}[{k}].y")))
        lanes.append(np.asarray(points, dtype=np.float64))
    return lanes


def read_curvelanes_label(path: Path | str) -> list[np.ndarray]:
    """One ``.lines.json`` -> its lanes, (N, 2) float64 (x, y) in the file's order. Errors name the file and field."""
    path = Path(path)
    obj = read_json_label(path, "CurveLanes label")
    return parse_curvelanes_label(obj, path)


def image_size_of(path: Path | str, option: str | None = None) -> tuple[int, int]:
    """(height, width) of an image from its header (PIL, lazy), as ``load_image`` (cv2, EXIF-rotated) will see it;
    ``option`` names what replaces it when the images are elsewhere."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    try:
        with Image.open(path) as im:
            w, h = im.size
            if im.format == "JPEG" and im.getexif().get(0x0112) in (5, 6, 7, 8):
                w, h = h, w
    except FileNotFoundError:
        instead = f"; give {option} when the images are elsewhere" if option else ""
        raise FileNotFoundError(f"image {path} not found (its size scales its lanes){instead}") from None
    except (UnidentifiedImageError, OSError) as e:
        raise ValueError(f"image {path}: cannot read its size ({e})") from None
    return h, w


def read_list_file(list_file: Path) -> list[tuple[int, str]]:
    """(line number, entry) of a list file's non-blank lines; an entry leaving its split folder or listed twice
    is an error naming the lines."""
    try:
        text = list_file.read_text(encoding="utf-8-sig")
    except FileNotFoundError as e:
        raise FileNotFoundError(f"CurveLanes list file {list_file} not found (the official layout: <root>/<split>/"
                                f"<split>.txt listing images/<name>.jpg)") from e
    entries, seen = [], {}
    for lineno, line in enumerate(text.splitlines(), start=1):
        entry = line.strip()
        if not entry:
            continue
        parts = PurePosixPath(entry.lstrip("/")).parts
        if not parts or ".." in parts:
            raise ValueError(f"{list_file}:{lineno}: {entry!r} is not a path inside the split folder "
                             f"(expected images/<name>.jpg)")
        entry = "/".join(parts)
        if entry in seen:
            raise ValueError(f"{list_file}:{lineno}: {entry} is listed twice (first at line {seen[entry]})")
        seen[entry] = lineno
        entries.append((lineno, entry))
    return entries


def read_curvelanes(root: Path | str, split: str = "valid", check_images: bool = True,
                    list_file: Path | str | None = None) -> list[dict]:
    """Records {"image_path", "rel_path", "label_path", "lanes", "labeled", "source"} of a CurveLanes split.

    ``split`` is a folder name (train, valid, test). ``list_file`` (default ``<split>/<split>.txt``; a relative
    path is under ``root``) names the images, relative to the split folder. The test split has no public labels
    ("lanes" [] and "labeled" False). Every label is parsed and every image checked here, so a bad file stops the
    run before any long work, naming it. "rel_path" is ``<split>/images/<name>.jpg``, the image's path under
    ``root`` (what evaluations key the image by).
    """
    root = Path(root)
    if split not in CURVELANES_SPLITS:
        raise ValueError(f"CurveLanes split {split!r}: expected one of {', '.join(CURVELANES_SPLITS)} (folder names "
                         f"under {root}; 'val' is 'valid')")
    split_dir = root / split
    official = list_file is None
    list_path = official_list_file(root, split) if official else Path(root, list_file)
    entries = read_list_file(list_path)
    labeled = split != "test"
    records = []
    for lineno, entry in entries:
        source = f"{list_path}:{lineno}"
        image_path = split_dir / entry
        label_path = label_path_for(split_dir, entry) if labeled else None
        lanes = []
        if labeled:
            try:
                raw = read_curvelanes_label(label_path)
            except FileNotFoundError as e:
                raise FileNotFoundError(f"{source}: {e}") from None
            lanes = [as_lane(lane, name=f"{label_path}: Lines[{j}]") for j, lane in enumerate(raw)]
        problem = image_file_problem(image_path) if check_images else None
        if problem is not None:
            error = FileNotFoundError if problem == "not found" else ValueError
            raise error(f"{source}: image {image_path} {problem}")
        records.append({"image_path": image_path, "rel_path": f"{split}/{entry}", "label_path": label_path,
                        "lanes": lanes, "labeled": labeled, "source": source})
    if labeled and official:
        _check_unlisted_labels(split_dir, list_path, {label_path_for(split_dir, e).name for _, e in entries})
    return records


def _check_unlisted_labels(split_dir: Path, list_path: Path, listed: set[str]) -> None:
    """With the official list: a label in ``labels/`` whose image the list does not name is an error (a tree whose
    list and labels disagree)."""
    folder = split_dir / "labels"
    if not folder.is_dir():  # an empty list reads no label
        return
    extra = sorted(p.name for p in folder.iterdir() if p.name.endswith(LABEL_SUFFIX) and p.name not in listed)
    if extra:
        raise ValueError(f"{folder / extra[0]}: its image is not in the list {list_path} ({len(extra)} such label(s)); "
                         f"list the image there, remove the label, or read a list of your own (list_file=...)")
