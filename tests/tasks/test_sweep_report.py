"""A multirun's closing report: the jobs side by side, or none when their rows would merge."""

from __future__ import annotations

import json

import numpy as np
from omegaconf import OmegaConf

from lanevil_train.evaluation.lane_records import lane_record
from lanevil_train.tasks.sweep_report import ReportSweep


def _job(path, model: str, shift: float) -> None:
    """A job's per_image.jsonl: 3 images, one straight lane each, predicted `shift` px to the side."""
    path.mkdir(parents=True)
    rows = np.arange(160, 720, 10.0)
    lines = []
    for i in range(3):
        gt = [np.stack([np.full_like(rows, 600.0), rows], 1)]
        pred = [gt[0] + np.array([shift, 0.0])]
        meta = {"case_id": f"c{i}", "h_samples": rows, "width": 1280, "height": 720}
        lines.append(json.dumps({"model": model, "dataset": "synthetic", **lane_record(pred, gt, meta)}))
    (path / "per_image.jsonl").write_text("\n".join(lines) + "\n")


def _end(sweep) -> None:
    ReportSweep().on_multirun_end(OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}}}))


def test_jobs_of_different_models_get_one_table(tmp_path):
    _job(tmp_path / "0", "laneatt-resnet18", 0.0)
    _job(tmp_path / "1", "ufld-resnet18", 50.0)  # 50 px off: every point missed
    _end(tmp_path)
    rows = {r["model"]: r for r in json.loads((tmp_path / "report" / "test_scores.json").read_text())}
    assert rows["laneatt-resnet18"]["Accuracy"] == 100.0 and rows["ufld-resnet18"]["Accuracy"] == 0.0
    assert rows["laneatt-resnet18"]["images"] == rows["ufld-resnet18"]["images"] == 3


def test_jobs_sharing_a_label_get_no_merged_report(tmp_path):
    _job(tmp_path / "0", "laneatt-resnet18", 0.0)
    _job(tmp_path / "1", "laneatt-resnet18", 50.0)
    _end(tmp_path)
    assert not (tmp_path / "report").exists()


def test_rows_follow_the_sweep_order_past_ten_jobs(tmp_path):
    names = [f"family{i}-resnet18" for i in range(12)]
    for i, name in enumerate(names):
        _job(tmp_path / str(i), name, 0.0)
    _end(tmp_path)
    rows = json.loads((tmp_path / "report" / "test_scores.json").read_text())
    assert [r["model"] for r in rows] == names  # job 10 after job 9, not after job 1
