"""The command line end to end: help, a fast dev run, train -> checkpoint -> evaluate, resume."""

from __future__ import annotations

import json

import torch

from tests.tasks.cli_helpers import TINY, run_cli


def test_help_lists_config_groups(tmp_path):
    out = run_cli(["--help"], tmp_path / "run").stdout
    for group in ("task:", "data:", "model:", "backbone:", "defense:", "trainer:", "logger:", "experiment:"):
        assert group in out, group
    assert "laneatt" in out and "quickstart" in out and "ddp_spawn" in out


def test_fast_dev_run_trains_and_tests_one_batch(tmp_path):
    run_dir = tmp_path / "run"
    run_cli([*TINY, "trainer.fast_dev_run=true"], run_dir)
    scores = json.loads((run_dir / "test_scores.json").read_text())
    assert len(scores) == 1
    row = scores[0]
    assert row["model"] == "laneatt" and row["data"] == "synthetic"
    for key in ("Accuracy", "FP", "FN", "F1"):
        assert 0.0 <= row[key] <= 100.0
    per_image = (run_dir / "per_image.csv").read_text().splitlines()
    assert per_image[0].startswith("case_id,accuracy,fp,fn")
    assert len(per_image) == 1 + 2  # fast_dev_run tests one batch of 2 images


def test_train_checkpoint_evaluate_and_resume(tmp_path):
    train_dir = tmp_path / "train"
    run_cli([*TINY, "trainer.max_steps=3", "trainer.limit_val_batches=1", "trainer.max_epochs=10"], train_dir)
    last = train_dir / "checkpoints" / "last.ckpt"
    assert last.is_file()
    ckpt = torch.load(last, map_location="cpu", weights_only=False)
    assert ckpt["global_step"] == 3
    assert ckpt["lanevil_model"]["input_size"] == [64, 160]
    metrics_csv = (train_dir / "csv" / "metrics.csv").read_text()
    assert "train/loss" in metrics_csv

    # evaluate rebuilds the network from the checkpoint, whatever the command line's model size says
    eval_dir = tmp_path / "eval"
    run_cli(["task=evaluate", f"ckpt_path={last}", *TINY, "data.input_size=[96,192]"], eval_dir)
    evaluated = json.loads((eval_dir / "test_scores.json").read_text())[0]
    trained = json.loads((train_dir / "test_scores.json").read_text())[0]
    assert evaluated["images"] == 4
    for key in ("Accuracy", "FP", "FN", "F1"):
        assert abs(evaluated[key] - trained[key]) < 1e-6, key

    # decoding is overridable at evaluation: a threshold no score reaches leaves every lane missed
    strict_dir = tmp_path / "strict"
    run_cli(["task=evaluate", f"ckpt_path={last}", *TINY, "task.decode.conf_threshold=1.01"], strict_dir)
    assert json.loads((strict_dir / "test_scores.json").read_text())[0]["FN"] == 100.0

    # resume: continues from step 3 to step 5, not from scratch
    resume_dir = tmp_path / "resume"
    run_cli([*TINY, "trainer.max_steps=5", "trainer.limit_val_batches=1", "trainer.max_epochs=10",
             f"ckpt_path={last}", "task.test_after_fit=false"], resume_dir)
    resumed = torch.load(resume_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert resumed["global_step"] == 5


def test_unknown_task_is_a_clear_error(tmp_path):
    try:
        run_cli(["task.name=nope", *TINY], tmp_path / "run")
    except AssertionError as err:
        assert "task.name='nope'" in str(err)
    else:
        raise AssertionError("an unknown task must fail")


def test_wandb_logger_works_offline(tmp_path):
    run_dir = tmp_path / "run"
    run_cli([*TINY, "logger=wandb", "trainer.max_steps=1", "trainer.limit_val_batches=1",
             "task.test_after_fit=false"], run_dir)
    offline_runs = list((run_dir / "wandb").glob("offline-run-*"))
    assert len(offline_runs) == 1
    assert any(offline_runs[0].rglob("*.wandb"))


def test_multirun_sweep_writes_one_run_per_value(tmp_path):
    sweep = tmp_path / "sweep"
    run_cli(["-m", "seed=0,1", *TINY, "trainer.fast_dev_run=true", f"hydra.sweep.dir={sweep}"], tmp_path / "unused")
    runs = sorted(p.name for p in sweep.iterdir() if p.is_dir() and (p / "test_scores.json").is_file())
    assert runs == ["0", "1"]
