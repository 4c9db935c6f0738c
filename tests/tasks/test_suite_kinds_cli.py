"""The corruption and combined-illusion suites from the command line: scored and reported like the illusions."""

from __future__ import annotations

import json

from lanevil_train.evaluation.lane_records import read_records
from tests.tasks.cli_helpers import TINY, run_in_process


def test_train_scores_the_combined_suite_and_evaluate_the_corruption_suite(tmp_path):
    train_dir = tmp_path / "train"
    run_in_process([*TINY, "trainer.max_steps=1", "trainer.limit_val_batches=0", "task.test_after_fit=false",
                    "task.suite=combined", "task.cases=1", "task.severities=[3]"], train_dir)
    records = read_records(train_dir / "robustness" / "per_image.jsonl")
    assert {r["dataset"] for r in records} == {"synthetic-combined"}
    pairs = [r for r in records if "+" in (r["illusion"] or "")]
    assert len(records) == 1 + 4 + 6 and len(pairs) == 6
    rows = json.loads((train_dir / "robustness" / "combined.json").read_text())
    assert [r["pair"] for r in rows] == ["RD+TO", "RD+SH", "RD+RF", "TO+SH", "TO+RF", "SH+RF"]
    for row in rows:  # each pair's Gap against the original and against each of its illusions alone
        assert row["Accuracy/Gap"] == row["Accuracy/Perturbed"] - row["Accuracy/Original"]
        first = next(r for r in records if r["illusion"] == next(p for p in pairs if p["category"] == row["category"])
                     ["illusion"].split("+")[0])
        assert row["Accuracy/first alone"] == 100.0 * first["accuracy"]
    assert "Combined illusions" in (train_dir / "robustness" / "report.md").read_text()

    out = tmp_path / "eval"
    run_in_process(["task=evaluate", f"ckpt_path={train_dir / 'checkpoints' / 'last.ckpt'}", *TINY,
                    "task.suite=corruptions", "task.cases=1", "task.illusions=[snow,jpeg,gaussian_noise]",
                    "task.severities=[1,5]", f"task.out_dir={out}"], tmp_path / "run")
    records = read_records(out / "per_image.jsonl")
    assert sorted((r["illusion"], r["severity"]) for r in records if r["severity"]) == [
        (name, sev) for name in ("gaussian_noise", "jpeg", "snow") for sev in (1, 5)]
    severity = json.loads((out / "per_severity.json").read_text())
    assert {(r["category"], r["severity"]) for r in severity} == {(c, s) for c in ("digital", "noise", "weather")
                                                                  for s in (1, 5)}
