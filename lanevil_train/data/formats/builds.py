"""What every resumable set builder shares (the illusion image set, the VLM clip suite): the build record that says
what a set should hold and whether it is whole, and the worker pool that renders its parts."""

from __future__ import annotations

import json
from multiprocessing import get_context
from pathlib import Path
from typing import Callable, Iterable, Iterator

from lanevil_train.files.atomic import atomic_write_text, remove_temporaries

BUILD_FILE = "build.json"


def write_build_record(root: Path, expected: dict, complete: bool) -> None:
    """root/build.json: what the set should hold and whether it is whole; no timestamps (reruns end
    byte-identical)."""
    atomic_write_text(Path(root) / BUILD_FILE,
                      json.dumps({**expected, "complete": complete}, indent=1, sort_keys=True) + "\n")


def read_build_record(root: str | Path, count_key: str, what: str, rerun: str) -> dict:
    """The parsed build.json of a set (`what`, e.g. "illusion set"), which counts its items under `count_key`; an
    error naming the file, what it should hold, and the command (`rerun`) that rewrites it."""
    path = Path(root) / BUILD_FILE
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as error:
        raise ValueError(f"{path}: cannot read the {what}'s build record ({error}); rerun {rerun} with the same "
                         f"out_dir ({path.parent}) to rewrite it") from error
    if not isinstance(record, dict) or not isinstance(record.get(count_key), int) or \
            not isinstance(record.get("complete"), bool):
        raise ValueError(f"{path}: expected a JSON object with an integer {count_key!r} and a boolean 'complete', "
                         f"got {str(record)[:120]}")
    return record


def map_jobs(fn: Callable, jobs: Iterable, workers: int) -> Iterator:
    """fn over jobs in order: in this process (workers 0) or in `workers` spawned processes."""
    if workers <= 0:
        yield from map(fn, jobs)
        return
    with get_context("spawn").Pool(workers) as pool:
        yield from pool.imap(fn, jobs)


def begin_build(root: Path, expected: dict, count_key: str, what: str, rerun: str) -> None:
    """Start or resume a build into root: refuse a folder holding a set of another plan, clear the temporaries a kill
    left, and mark the set incomplete (unless it is already whole) until its last part is written."""
    previous = read_build_record(root, count_key, what, rerun) if (Path(root) / BUILD_FILE).exists() else None
    if previous is not None and {k: previous.get(k) for k in expected} != json.loads(json.dumps(expected)):
        raise ValueError(
            f"{Path(root) / BUILD_FILE}: out_dir {root} holds a {what} built with other cases or another plan "
            f"({previous.get(count_key)} {count_key} of {previous.get('cases')} cases, plan {previous.get('plan')}; "
            f"now {expected[count_key]} {count_key} of {expected.get('cases')} cases, plan {expected['plan']}); "
            f"rerun with the same settings to finish it, or choose a new out_dir")
    Path(root).mkdir(parents=True, exist_ok=True)
    remove_temporaries(root)
    if previous is None or not previous.get("complete"):
        write_build_record(root, expected, complete=False)
