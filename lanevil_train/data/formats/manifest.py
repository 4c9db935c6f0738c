"""The illusion test-set manifest: JSON lines, one per image of the set.

{"image": relative path, "source_image": the clean image it derives from (itself for an original),
 "case_id": str, "illusion": name or null, "category": name or null, "severity": 0 (original) or 1..5,
 "seed": int}
"""

from __future__ import annotations

import json
from pathlib import Path

from lanevil_train.data.formats.jsonl import read_json_objects

MANIFEST_KEYS = ("image", "source_image", "case_id", "illusion", "category", "severity", "seed")


def manifest_line(record: dict) -> str:
    """One manifest line (keys in MANIFEST_KEYS order), or a ValueError naming a missing key."""
    missing = [k for k in MANIFEST_KEYS if k not in record]
    if missing:
        raise ValueError(f"manifest record is missing {missing}: {record}")
    return json.dumps({k: record[k] for k in MANIFEST_KEYS})


def read_manifest(path: str | Path) -> list[dict]:
    """All records of a manifest file; malformed lines raise naming the file and line."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"manifest not found: {path}")
    return [record for _, record in read_json_objects(path, MANIFEST_KEYS, "manifest")]


class ManifestWriter:
    """Appends manifest lines, flushed one by one, so an interruption loses at most the line being written."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._handle = open(self.path, "a", encoding="utf-8")

    def write(self, record: dict) -> None:
        self._handle.write(manifest_line(record) + "\n")
        self._handle.flush()

    def close(self) -> None:
        self._handle.close()

    def __enter__(self) -> "ManifestWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
