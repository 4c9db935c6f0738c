"""task=compare with a job launcher: every run one job of hydra/launcher=local (submitit's local executor, real
processes), the report assembled from the finished runs, a failed job named and rerun alone."""

from __future__ import annotations

import json

import pytest

from tests.tasks.cli_helpers import TINY, run_cli

COMPARE = ["task=compare", "task.defenses=[none,flaky]", *TINY, "trainer.max_steps=2", "trainer.limit_val_batches=0",
           "task.cases=1", "task.illusions=[rail_shadow]", "task.severities=[3]", "task.test_after_fit=false",
           "hydra/launcher=local", "task.bootstrap=200"]


def test_compare_runs_each_defense_as_a_job_and_reruns_only_the_failed_one(tmp_path):
    trigger = tmp_path / "fail"
    trigger.touch()
    defenses = tmp_path / "conf" / "defense"
    defenses.mkdir(parents=True)
    (defenses / "flaky.yaml").write_text(
        "name: flaky\ntransforms: []\nmixer: null\n"
        f"callback:\n  _target_: tests.tasks.failing_defense.FailWhile\n  trigger: {trigger}\n")
    out = tmp_path / "compare"
    args = [*COMPARE, f"hydra.searchpath=[file://{tmp_path / 'conf'}]", f"task.out_dir={out}"]
    with pytest.raises(AssertionError) as failure:  # run_cli raises with the output when the command fails
        run_cli(args, tmp_path / "first")
    message = str(failure.value)
    assert "1 run(s) failed: flaky@0" in message and "failing on purpose" in message
    none_done = out / "runs" / "none" / "robustness" / "done.json"
    assert none_done.is_file() and not (out / "runs" / "flaky" / "robustness" / "done.json").exists()
    assert (out / "jobs" / "none@0").is_dir() and (out / "jobs" / "flaky@0").is_dir()  # each run was a job
    stamp = none_done.stat().st_mtime_ns

    trigger.unlink()  # the cause is fixed: the same command runs only the failed run
    proc = run_cli(args, tmp_path / "second")
    assert "1 run(s) as jobs (1 already done)" in proc.stdout + proc.stderr
    assert none_done.stat().st_mtime_ns == stamp
    gains = json.loads((out / "defense_gain.json").read_text())
    assert [(r["defense"], r["category"]) for r in gains] == [("flaky", "shadow"), ("flaky", "average"),
                                                              ("flaky", "original")]
    assert "Accuracy/low" in gains[0] and (out / "compare.md").is_file()
