"""JSON files: JSON lines (TuSimple labels, illusion-set manifests), one object per line, and whole-file JSON labels
(LLAMAS, CurveLanes); errors with file:line."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Iterator


def read_json_objects(path: str | Path, required: tuple[str, ...], what: str) -> Iterator[tuple[str, dict]]:
    """("file:line", object) for each non-blank line of `path`, each a JSON object with the `required` keys.

    `what` names the kind of file in messages ("TuSimple label", "manifest"). A UTF-8 byte-order
    mark at the start of the file is accepted (editors on Windows write one).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except OSError as e:
        raise FileNotFoundError(f"cannot read {what} file {path}: {e}") from e
    for lineno, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        where = f"{path}:{lineno}"
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as e:
            raise ValueError(f"{where}: malformed JSON ({e.msg} at column {e.colno})") from e
        if not isinstance(obj, dict):
            raise ValueError(f"{where}: expected a JSON object with keys {list(required)}, got {type(obj).__name__}")
        missing = [k for k in required if k not in obj]
        if missing:
            raise ValueError(f"{where}: missing key(s) {missing}; a {what} line needs {list(required)}")
        yield where, obj


def read_json_label(path: str | Path, what: str) -> Any:
    """The JSON value of a whole-file label (a UTF-8 byte-order mark accepted). `what` names the kind of label in
    messages ("LLAMAS label"): a missing file is a FileNotFoundError, malformed JSON a ValueError at file:line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except FileNotFoundError as e:
        raise FileNotFoundError(f"{what} {path} not found") from e
    except OSError as e:
        raise FileNotFoundError(f"cannot read {what} {path}: {e}") from e
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}:{e.lineno}: malformed JSON ({e.msg} at column {e.colno})") from e
