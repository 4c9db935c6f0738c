"""benchmarks/bench_metric_commands.py: its data are valid inputs, and it reads the official tools' outputs."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

from lanevil_train.metrics import evaluate_culane_dirs, evaluate_tusimple_files

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_metric_commands.py"
_spec = importlib.util.spec_from_file_location("bench_metric_commands", BENCH)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def test_tusimple_data_are_realistic_and_scorable(tmp_path: Path) -> None:
    pred, gt = bench.write_tusimple(tmp_path, 40, seed=1)
    gts = [json.loads(line) for line in gt.read_text().splitlines()]
    assert len(gts) == 40 and all(g["h_samples"] == list(range(160, 720, 10)) for g in gts)
    assert {len(g["lanes"]) for g in gts} <= {4, 5}
    lanes = np.array([x for g in gts for lane in g["lanes"] for x in lane])
    assert set(lanes[lanes < 0].tolist()) == {-2} and lanes.max() < 1280
    out = evaluate_tusimple_files(pred, gt)
    assert 0.8 < out["Accuracy"] < 0.99 and 0 < out["FP"] < 0.4 and 0 < out["FN"] < 0.4


def test_culane_data_are_scorable(tmp_path: Path) -> None:
    pred_dir, gt_dir, lst = bench.write_culane(tmp_path, 30, seed=1)
    names = lst.read_text().splitlines()
    assert len(names) == 30 and all(n.startswith("/driver_") and n.endswith(".jpg") for n in names)
    out = evaluate_culane_dirs(str(pred_dir), str(gt_dir), str(lst), workers=1)
    assert 50 < out["TP"] + out["FN"] <= 120 and 0.6 < out["F1"] < 0.95


def test_parses_official_outputs_and_compares(tmp_path: Path) -> None:
    stdout = ('[{"name":"Accuracy","value":0.9,"order":"desc"},{"name":"FP","value":0.1,"order":"asc"},'
              '{"name":"FN","value":0.2,"order":"asc"}]\n')
    official = bench.parse_official_tusimple(stdout)
    assert official == {"Accuracy": 0.9, "FP": 0.1, "FN": 0.2}
    assert bench.compare_tusimple({"Accuracy": 0.9, "FP": 0.1, "FN": 0.2, "F1": 0.8}, official).startswith("identical")
    assert "DIFFER" in bench.compare_tusimple({"Accuracy": 0.9000001, "FP": 0.1, "FN": 0.2}, official)
    out = tmp_path / "out.txt"
    out.write_text("file: out.txt\ntp: 7603 fp: 2356 fn: 2433\nprecision: 0.76\n")
    counts = bench.parse_official_culane(out)
    assert counts == {"TP": 7603, "FP": 2356, "FN": 2433}
    assert bench.compare_culane(dict(counts), counts).startswith("identical")
    out.write_text("precision: -1\n")
    with pytest.raises(RuntimeError, match="no 'tp: fp: fn:' line"):
        bench.parse_official_culane(out)
