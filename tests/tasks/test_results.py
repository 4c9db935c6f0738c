"""write_results: the official per-image ranges are accepted, a bad record is named by its file and line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lanevil_train.evaluation.lane_records import lane_record
from lanevil_train.evaluation.results import write_results
from lanevil_train.lanes import default_h_samples


def _lane(x: float) -> np.ndarray:
    ys = np.arange(300.0, 720.0, 10.0)
    return np.stack([np.full_like(ys, x), ys], 1)


def _record(case: int, pred: list, gt: list) -> dict:
    meta = {"case_id": f"c{case}", "h_samples": default_h_samples(720), "width": 1280, "height": 720}
    return {"model": "m", "dataset": "d", **lane_record(pred, gt, meta, keep_lanes=False)}


def _write(path, records) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))


def test_six_missed_lanes_give_the_official_fn_of_five_quarters_and_are_reported(tmp_path):
    six = [_lane(100.0 + 200 * k) for k in range(6)]
    missed, found = _record(0, [], six), _record(1, six, six)
    # official TuSimple: with more than 4 GT lanes one miss is forgiven, the rest divided by 4
    assert (missed["accuracy"], missed["fp"], missed["fn"]) == (0.0, 0.0, 1.25)
    assert (found["accuracy"], found["fp"], found["fn"]) == (1.25, 0.0, 0.0)
    _write(tmp_path / "per_image.jsonl", [missed, found])
    assert write_results([tmp_path / "per_image.jsonl"], tmp_path / "out") == pytest.approx(62.5)


def test_a_bad_record_is_named_by_its_file_and_line(tmp_path):
    good = [_record(k, [_lane(300.0)], [_lane(300.0)]) for k in range(3)]
    bad = [dict(r) for r in good]
    bad[1]["fn"] = -0.5
    _write(tmp_path / "a.jsonl", good)
    _write(tmp_path / "b.jsonl", [{**r, "model": "m2"} for r in bad])
    with pytest.raises(ValueError, match=rf"^{tmp_path / 'b.jsonl'}:2: fn must be a number in \[0.0, inf\], got -0.5$"):
        write_results([tmp_path / "a.jsonl", tmp_path / "b.jsonl"], tmp_path / "out")


def test_test_scores_show_f1_count_where_a_silent_model_reads_zero(tmp_path):
    """A model that finds nothing: the papers' F1 (CLRNet's, tp = 1 - FP) reads 66.67, F1_count 0; the records
    carry the lane counts it is summed from."""
    four = [_lane(100.0 + 300 * k) for k in range(4)]
    silent = [_record(k, [], four) for k in range(2)]
    assert [(r["tp_count"], r["fp_count"], r["fn_count"]) for r in silent] == [(0, 0, 4)] * 2
    _write(tmp_path / "per_image.jsonl", silent)
    write_results([tmp_path / "per_image.jsonl"], tmp_path / "out")
    row = json.loads((tmp_path / "out" / "test_scores.json").read_text())[0]
    assert row["F1"] == pytest.approx(200 / 3) and row["F1_count"] == 0.0
    # one image all found, one with 3 of 4 and a false positive: TP 7, FP 1, FN 1 -> 14 / 16
    found = [_record(0, four, four), _record(1, four[:3] + [_lane(1250.0)], four)]
    assert (found[1]["tp_count"], found[1]["fp_count"], found[1]["fn_count"]) == (3, 1, 1)
    _write(tmp_path / "per_image.jsonl", found)
    write_results([tmp_path / "per_image.jsonl"], tmp_path / "out")
    row = json.loads((tmp_path / "out" / "test_scores.json").read_text())[0]
    assert row["F1_count"] == pytest.approx(100 * 14 / 16)
    assert "F1_count" in (tmp_path / "out" / "test_scores.md").read_text()
