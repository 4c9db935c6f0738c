"""task=evaluate (and task=train's test after fit) on CULane: F1@50, F1@75 and mF1 per official category
(list/test_split/), cross as its FP count.

The nine lists are found and checked before any image is scored (``category_lists``: ``task.culane_categories``,
``auto`` by default: ``<data.root>/list/test_split/`` when data=culane scores the official ``list/test.txt`` and
that folder exists); after scoring, ``write_category_table`` writes ``culane_categories.{json,md}`` beside
``test_scores`` from the per-image records (their CULane counts at IoU 0.5 and TP at each mF1 threshold), the
numbers the official evaluator gives when run on each list's prediction files (metrics/culane_files.py).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from omegaconf import DictConfig

from lanevil_train.evaluation.lane_records import read_records
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.metrics.culane_files import (
    CATEGORIES,
    FP_ONLY,
    category_markdown,
    image_key,
    read_category_lists,
)
from lanevil_train.report.specs import CULANE_F1, CULANE_F1_75, CULANE_MF1, CULANE_SWEEP

log = logging.getLogger(__name__)

KEY = "task.culane_categories"
TABLE = "culane_categories"
OFFICIAL_TEST_LIST = "list/test.txt"


def category_lists(cfg: DictConfig, dataset, suite_replaces_test: bool = True) -> dict[str, list[str]] | None:
    """The nine category lists as image keys (read_category_lists), checked against the images of `dataset` (its
    item_key: CULane's list path); None when ``task.culane_categories`` is null, or ``auto`` finds no folder.

    `suite_replaces_test`: task.suite is what the task scores instead of data.test (task=evaluate), so ``auto``
    finds no lists then; task=train scores data.test after fitting whatever the suite (False)."""
    setting = cfg.task.get("culane_categories", "auto")
    if setting is None:
        return None
    if setting == "auto":
        test = cfg.data.get("test") or {}
        if (suite_replaces_test and cfg.task.get("suite") is not None) or cfg.data.name != "culane" or \
                str(test.get("list_file", "")).lstrip("./") != OFFICIAL_TEST_LIST:
            return None
        folder = Path(cfg.data.root) / "list" / "test_split"
        if not folder.is_dir():
            return None
        where = f"{KEY}=auto (data.root's list/test_split/)"
    else:
        folder, where = Path(setting), KEY
    keys = [dataset.item_key(i) for i in range(len(dataset))]
    return read_category_lists(str(folder), keys, arg=where)


def category_rows(records: list[dict], lists: dict[str, list[str]]) -> list[dict]:
    """One row per category, then "total": images, F1@50, F1@75, mF1 (%), FP (at IoU 0.5); cross: FP only."""
    by_key = {image_key(r["key"]): r for r in records if r.get("severity", 0) == 0}
    rows = []
    for name, keys in [*lists.items(), ("total", list(by_key))]:
        part = [by_key[k] for k in keys if k in by_key]
        fp = int(sum(r["culane_fp"] for r in part))
        if name == FP_ONLY:
            rows.append({"list": name, "images": len(part), "F1@50": None, "F1@75": None, "mF1": None, "FP": fp})
            continue
        rows.append({"list": name, "images": len(part), "F1@50": CULANE_F1.aggregate(part),
                     "F1@75": CULANE_F1_75.aggregate(part), "mF1": CULANE_MF1.aggregate(part), "FP": fp})
    return rows


def write_category_table(results: Path, out_dir: Path, lists: dict[str, list[str]]) -> Path:
    """Write culane_categories.json and .md in `out_dir` from the per-image results file; print the table."""
    records = read_records(results, keep_lanes=False)
    lacking = [r["key"] for r in records if r.get(CULANE_SWEEP) is None]
    if lacking:
        raise ValueError(f"{results}: {len(lacking)} record(s) lack {CULANE_SWEEP} (written before mF1 was counted?), "
                         f"first {lacking[0]!r}; score again with a new task.out_dir")
    rows = category_rows(records, lists)
    text = category_markdown(rows)
    atomic_write_text(out_dir / f"{TABLE}.json", json.dumps(rows, indent=2) + "\n")
    atomic_write_text(out_dir / f"{TABLE}.md", f"CULane per category (%; cross: FP count), lists "
                                               f"{', '.join(f for _, f in CATEGORIES)}\n\n{text}\n")
    print(f"CULane per category (%; cross: FP count) — {out_dir / TABLE}.md\n{text}")
    return out_dir / f"{TABLE}.md"
