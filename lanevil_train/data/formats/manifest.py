"""The illusion test-set manifest: JSON lines, one per image of the set.

{"image": relative path, "source_image": the clean image it derives from (itself for an original),
 "case_id": str, "illusion": name or null, "category": name or null, "severity": 0 (original) or 1..5,
 "seed": int}

The build (data/illusion_set.py) appends lines through lanevil_train.results_log.ResultsLog keyed by "image";
readers of a finished set use read_manifest.
"""

from __future__ import annotations

from pathlib import Path

from lanevil_train.files.jsonl import read_json_objects

MANIFEST_KEYS = ("image", "source_image", "case_id", "illusion", "category", "severity", "seed")


def manifest_record(record: dict) -> dict:
    """The manifest fields of a record, in MANIFEST_KEYS order (so lines are byte-stable), or a ValueError
    naming a missing key."""
    missing = [k for k in MANIFEST_KEYS if k not in record]
    if missing:
        raise ValueError(f"manifest record is missing {missing}: {record}")
    return {k: record[k] for k in MANIFEST_KEYS}


def read_manifest(path: str | Path) -> list[dict]:
    """All records of a manifest file; malformed lines raise naming the file and line. A cut-off last line
    means the build was killed while writing it: the message says so and how to finish the set."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"manifest not found: {path}")
    try:
        return [record for _, record in read_json_objects(path, MANIFEST_KEYS, "manifest")]
    except ValueError as error:
        torn = _unterminated_last_line(path)
        if torn is None or not str(error).startswith(f"{path}:{torn}:"):
            raise
        raise ValueError(f"{path}:{torn}: the last line is cut off: the build that wrote this set was interrupted; "
                         f"rerun task=build with the same out_dir ({path.parent}) to finish it") from error


def _unterminated_last_line(path: Path) -> int | None:
    """The number of the file's last line if it lacks its newline (a write cut short), else None."""
    data = path.read_bytes()
    if not data or data.endswith(b"\n"):
        return None
    return data.count(b"\n") + 1
