"""task=evaluate's CULane category table and F1@75 / mF1 scores, from per-image records (hand counts)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from lanevil_train.evaluation.culane_categories import category_lists, category_rows, write_category_table
from lanevil_train.evaluation.lane_records import lane_record
from lanevil_train.metrics.culane_files import CATEGORIES
from lanevil_train.report.records import Additive
from lanevil_train.report.specs import CULANE_F1_75, CULANE_MF1, CULANE_SWEEP, LANE_SPEC
from lanevil_train.report.summary import summarise
from lanevil_train.results_log import ResultsLog


def record(key: str, tp_sweep: list[int], n_pred: int, n_gt: int) -> dict:
    tp = tp_sweep[0]
    return {"spec": "lane", "model": "m", "dataset": "culane", "case_id": key, "key": key, "severity": 0,
            "accuracy": 1.0, "fp": 0.0, "fn": 0.0, "culane_tp": tp, "culane_fp": n_pred - tp, "culane_fn": n_gt - tp,
            CULANE_SWEEP: tp_sweep}


# image "a": 4 predicted, 3 GT lanes, TP falling from 3 to 1 over the thresholds; "b": exact (TP 1 throughout);
# "x": a crossroads image, no GT lane and 2 predictions
A = record("driver_1/a.MP4/00000.jpg", [3, 3, 2, 2, 2, 2, 2, 1, 1, 1], 4, 3)
B = record("driver_1/b.MP4/00000.jpg", [1] * 10, 1, 1)
X = record("driver_1/x.MP4/00000.jpg", [0] * 10, 2, 0)


def test_f1_at_75_and_mf1_scores_by_hand() -> None:
    assert CULANE_F1_75.aggregate([A]) == pytest.approx(100 * 4 / 7)
    assert CULANE_MF1.aggregate([A]) == pytest.approx(100 * 38 / 70)
    # pooled: 7 predicted, 4 GT lanes; TP(t) = a's + 1
    assert CULANE_MF1.aggregate([A, B, X]) == pytest.approx(100 * 2 * (19 + 10) / 110)
    additive: Additive = CULANE_MF1.aggregate.additive  # the bootstrap's form gives the same value
    totals = np.sum([additive.parts(r) for r in (A, B, X)], axis=0, dtype=np.float64)
    assert float(additive.combine(totals)) == pytest.approx(CULANE_MF1.aggregate([A, B, X]))
    row = summarise([A, B, X], LANE_SPEC)
    assert row["CULane_F1"] == pytest.approx(100 * 8 / 11) and row["CULane_F1@75"] == pytest.approx(100 * 6 / 11)
    old = {k: v for k, v in A.items() if k != CULANE_SWEEP}  # a record written before the sweep: left out
    assert "CULane_mF1" not in summarise([old], LANE_SPEC) and "CULane_F1" in summarise([old], LANE_SPEC)


def test_lane_record_counts_the_sweep() -> None:
    lane = np.array([[800.0, 580.0], [800.0, 100.0]])
    meta = {"width": 1640, "height": 590, "h_samples": list(range(100, 590, 10)), "case_id": "c"}
    rec = lane_record([lane + [3, 0]], [lane], meta, keep_lanes=False)  # IoU 0.822: a TP up to 0.80
    assert rec[CULANE_SWEEP] == [1] * 7 + [0] * 3 and rec["culane_tp"] == 1


class FakeSet:
    def __init__(self, keys: list[str]) -> None:
        self.keys = keys

    def __len__(self) -> int:
        return len(self.keys)

    def item_key(self, i: int) -> str:
        return self.keys[i]


def _lists(folder: Path, members: dict[str, list[str]]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, filename in CATEGORIES:
        (folder / filename).write_text("".join(f"/{k}\n" for k in members.get(name, [A["key"]])))
    return folder


def _cfg(root: Path, **task) -> OmegaConf:
    return OmegaConf.create({"data": {"name": "culane", "root": str(root), "test": {"list_file": "list/test.txt"}},
                             "task": {"suite": None, **task}})


def test_category_lists_auto_explicit_and_refused(tmp_path: Path) -> None:
    dataset = FakeSet([A["key"], B["key"], X["key"]])
    assert category_lists(_cfg(tmp_path), dataset) is None  # auto, no list/test_split/: no table
    split = _lists(tmp_path / "list" / "test_split", {"cross": [X["key"]], "normal": [A["key"], B["key"]]})
    lists = category_lists(_cfg(tmp_path), dataset)
    assert lists["cross"] == ["driver_1/x.MP4/00000.lines.txt"] and len(lists["normal"]) == 2
    assert category_lists(_cfg(tmp_path, culane_categories=None), dataset) is None
    val = OmegaConf.merge(_cfg(tmp_path), {"data": {"test": {"list_file": "list/val.txt"}}})
    assert category_lists(val, dataset) is None  # auto: the official test list only
    (split / "test3_shadow.txt").write_text("/driver_1/a.MP4/00000.jpg\n/driver_2/gone.MP4/00000.jpg\n")
    with pytest.raises(ValueError, match=r"test3_shadow.txt:2: image '/driver_2/gone.MP4/00000.jpg' is not in"):
        category_lists(_cfg(tmp_path, culane_categories=str(split)), dataset)
    with pytest.raises(FileNotFoundError, match=r"task.culane_categories .*nowhere is not a directory"):
        category_lists(_cfg(tmp_path, culane_categories=str(tmp_path / "nowhere")), dataset)


def test_category_table_written(tmp_path: Path) -> None:
    split = _lists(tmp_path / "split", {"cross": [X["key"]], "normal": [A["key"]], "night": [B["key"]]})
    lists = category_lists(_cfg(tmp_path, culane_categories=str(split)), FakeSet([A["key"], B["key"], X["key"]]))
    rows = category_rows([A, B, X], lists)
    assert [r["list"] for r in rows] == [name for name, _ in CATEGORIES] + ["total"]
    assert rows[0] == {"list": "normal", "images": 1, "F1@50": pytest.approx(100 * 6 / 7),
                       "F1@75": pytest.approx(100 * 4 / 7), "mF1": pytest.approx(100 * 38 / 70), "FP": 1}
    assert rows[7] == {"list": "cross", "images": 1, "F1@50": None, "F1@75": None, "mF1": None, "FP": 2}
    assert rows[-1]["images"] == 3 and rows[-1]["FP"] == 3 and rows[-1]["F1@50"] == pytest.approx(100 * 8 / 11)
    results = tmp_path / "per_image.jsonl"
    ResultsLog(results).append([A, B, X])
    md = write_category_table(results, tmp_path, lists)
    assert "| cross | 1 | - | - | - | 2 |" in md.read_text()
    assert json.loads((tmp_path / "culane_categories.json").read_text())[8]["F1@50"] == 100.0
