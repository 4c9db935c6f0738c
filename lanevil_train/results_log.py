"""A resumable results log: one JSON object per line, appended as results are produced, each with a unique key.

Any long scoring job (images through a detector, clips and questions through a VLM) writes through it: a
rerun reads which keys are finished and skips them, and a line an interruption left half-written is cut
before anything is appended, so the file never holds a torn record in its middle. Plain Python, no
dependencies beyond the standard library.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable


class ResultsLog:
    """JSON-lines results at `path`, one record per finished unit of work, identified by `record[key_field]`."""

    def __init__(self, path: str | Path, key_field: str = "key"):
        self.path = Path(path)
        self.key_field = key_field

    def resume(self) -> set[str]:
        """Prepare to append (parent folder made, a torn last line cut); the keys already finished."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not self.path.exists():
            return set()
        data = self.path.read_bytes()
        if data and not data.endswith(b"\n"):
            # truncate in place: a kill during this step leaves the file whole or cut at its last full line
            os.truncate(self.path, data.rfind(b"\n") + 1)
        return {record[self.key_field] for record in self.records()}

    def append(self, records: Iterable[dict]) -> None:
        """Append records (each must have the key field), flushed to disk before returning."""
        lines = []
        for record in records:
            if record.get(self.key_field) is None:
                raise ValueError(f"{self.path}: a result record needs a {self.key_field!r}, got keys {sorted(record)}")
            lines.append(json.dumps(record) + "\n")
        with open(self.path, "a", encoding="utf-8") as handle:
            handle.writelines(lines)
            handle.flush()
            os.fsync(handle.fileno())

    def records(self, drop: Iterable[str] = (), keep_for: set[str] | None = None) -> list[dict]:
        """Every complete record; the fields in `drop` are removed except from records whose key is in `keep_for`
        (so tables over many records stay small). A last line without its newline (an interrupted write) is
        skipped; any other line that is not a JSON object is an error naming the file and line."""
        drop, keep_for = tuple(drop), keep_for or set()
        out = []
        with open(self.path, encoding="utf-8") as handle:
            for number, line in enumerate(handle, 1):
                try:
                    record = json.loads(line)
                except json.JSONDecodeError as error:
                    if not line.endswith("\n"):
                        break  # the torn tail of an interrupted write
                    raise ValueError(f"{self.path}:{number}: not a JSON object ({error.msg})") from error
                if not isinstance(record, dict):
                    raise ValueError(f"{self.path}:{number}: expected a JSON object, got {type(record).__name__}")
                if drop and record.get(self.key_field) not in keep_for:
                    for field in drop:
                        record.pop(field, None)
                out.append(record)
        return out
