"""The command line end to end: help, a fast dev run, train -> checkpoint -> evaluate, resume. A test's first run
goes through `python -m lanevil_train`; its later runs, and the callbacks' runs, compose and run in this process."""

from __future__ import annotations

import json

import pytest
import torch

from lanevil_train.evaluation.lane_records import read_records
from tests.tasks.cli_helpers import TINY, run_cli, run_in_process


def test_help_lists_config_groups(tmp_path):
    out = run_cli(["--help"], tmp_path / "run").stdout
    for group in ("task:", "data:", "model:", "backbone:", "defense:", "trainer:", "callbacks:", "logger:",
                  "experiment:"):
        assert group in out, group
    assert "laneatt" in out and "quickstart" in out and "ddp_spawn" in out


def test_fast_dev_run_trains_and_tests_one_batch(tmp_path):
    run_dir = tmp_path / "run"
    run_cli([*TINY, "trainer.fast_dev_run=true"], run_dir)
    scores = json.loads((run_dir / "test_scores.json").read_text())
    assert len(scores) == 1
    row = scores[0]
    assert (row["model"], row["dataset"], row["images_kind"], row["images"]) == \
        ("laneatt-resnet18", "synthetic", "original", 2)  # fast_dev_run tests one batch of 2 images
    for key in ("Accuracy", "FP", "FN", "F1", "CULane_F1"):
        assert 0.0 <= row[key] <= 100.0
    records = read_records(run_dir / "per_image.jsonl")  # the record task=evaluate writes, one per image
    assert [r["case_id"] for r in records] == ["sim-1000000", "sim-1000001"]
    assert all(r["spec"] == "lane" and r["severity"] == 0 and r["model"] == "laneatt-resnet18" for r in records)
    assert row["Accuracy"] == pytest.approx(100 * sum(r["accuracy"] for r in records) / 2)
    assert not list(run_dir.glob("per_image.rank*"))  # the part files were merged and removed

    # task=report reads a training run like any evaluation: the same scores come back
    report_dir = tmp_path / "report"
    run_in_process(["task=report", f"task.runs=[{run_dir}]", "progress=none"], report_dir)
    reported = json.loads((report_dir / "test_scores.json").read_text())
    assert reported == scores


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
    run_in_process(["task=evaluate", f"ckpt_path={last}", *TINY, "data.input_size=[96,192]"], eval_dir)
    evaluated = json.loads((eval_dir / "test_scores.json").read_text())[0]
    trained = json.loads((train_dir / "test_scores.json").read_text())[0]
    assert evaluated["images"] == 4
    for key in ("Accuracy", "FP", "FN", "F1"):
        assert abs(evaluated[key] - trained[key]) < 1e-6, key

    # decoding is overridable at evaluation: a threshold no score exceeds (scores are probabilities, kept when
    # above it) leaves every lane missed
    strict_dir = tmp_path / "strict"
    run_in_process(["task=evaluate", f"ckpt_path={last}", *TINY, "task.decode.conf_threshold=1.0"], strict_dir)
    assert json.loads((strict_dir / "test_scores.json").read_text())[0]["FN"] == 100.0

    # resume: continues from step 3 to step 5, not from scratch
    resume_dir = tmp_path / "resume"
    run_in_process([*TINY, "trainer.max_steps=5", "trainer.limit_val_batches=1", "trainer.max_epochs=10",
                    f"ckpt_path={last}", "task.test_after_fit=false"], resume_dir)
    resumed = torch.load(resume_dir / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert resumed["global_step"] == 5


def test_unknown_task_function_is_a_clear_error(tmp_path):
    with pytest.raises(AssertionError, match=r"task._target_='lanevil_train.tasks.nope': cannot import"):
        run_cli(["task._target_=lanevil_train.tasks.nope", *TINY], tmp_path / "run")


def test_a_new_task_is_a_function_and_a_config(tmp_path):
    """A user's own task: one function in their module, one config in their search path."""
    (tmp_path / "mytasks.py").write_text("def hello(cfg):\n    print('hello from', cfg.task.name, cfg.task.greeting)\n")
    (tmp_path / "conf" / "task").mkdir(parents=True)
    (tmp_path / "conf" / "task" / "hello.yaml").write_text("name: hello\n_target_: mytasks.hello\ngreeting: hi\n")
    out = run_cli(["task=hello", f"hydra.searchpath=[file://{tmp_path / 'conf'}]"], tmp_path / "run",
                  pythonpath=[tmp_path]).stdout
    assert "hello from hello hi" in out


def test_progress_auto_prints_plain_lines_without_a_terminal(tmp_path):
    args = [arg for arg in TINY if not arg.startswith("progress=")]
    out = run_cli([*args, "progress=auto", "trainer.max_steps=3", "trainer.limit_val_batches=1",
                   "trainer.max_epochs=-1"], tmp_path / "run").stdout
    assert "train: 1/3 steps (33%)" in out and "train: 3/3 steps (100%)" in out
    assert "train/loss" in out and "ETA" in out and "\r" not in out
    assert "test: 2/2 batches (100%)" in out  # 4 test scenes at batch 2


def test_callbacks_come_from_config(tmp_path):
    without = tmp_path / "without"
    run_in_process([*TINY, "~callbacks.model_checkpoint", "trainer.max_steps=1", "trainer.limit_val_batches=0",
                    "task.test_after_fit=false"], without)
    assert not (without / "checkpoints").exists()
    # early stopping on a validation score that no check can improve by 101 points: stops at the first chance
    stopped = tmp_path / "stopped"
    run_in_process([*TINY, "callbacks=[model_checkpoint,early_stopping]", "callbacks.early_stopping.patience=0",
                    "callbacks.early_stopping.min_delta=101", "trainer.max_epochs=5", "trainer.limit_val_batches=1",
                    "task.test_after_fit=false"], stopped)
    ckpt = torch.load(stopped / "checkpoints" / "last.ckpt", map_location="cpu", weights_only=False)
    assert ckpt["epoch"] == 1  # the second validation could not improve: stopped there, not after 5 epochs


def test_wandb_logger_works_offline(tmp_path):
    run_dir = tmp_path / "run"
    run_cli([*TINY, "logger=wandb", "trainer.max_steps=1", "trainer.limit_val_batches=1",
             "task.test_after_fit=false"], run_dir)
    offline_runs = list((run_dir / "wandb").glob("offline-run-*"))
    assert len(offline_runs) == 1
    assert any(offline_runs[0].rglob("*.wandb"))


def test_multirun_sweep_writes_one_run_per_value_and_one_report(tmp_path):
    sweep = tmp_path / "sweep"
    run_cli(["-m", "model=laneatt,scnn", *TINY, "trainer.fast_dev_run=true", f"hydra.sweep.dir={sweep}"],
            tmp_path / "unused")
    runs = sorted(p.name for p in sweep.iterdir() if p.is_dir() and (p / "test_scores.json").is_file())
    assert runs == ["0", "1", "report"]
    # the families side by side: one row per job's model, each with its own job's scores
    report = {row["model"]: row for row in json.loads((sweep / "report" / "test_scores.json").read_text())}
    assert sorted(report) == ["laneatt-resnet18", "scnn-resnet18"]
    for job in ("0", "1"):
        own = json.loads((sweep / job / "test_scores.json").read_text())[0]
        assert {k: report[own["model"]][k] for k in ("Accuracy", "F1", "images")} == \
               {k: own[k] for k in ("Accuracy", "F1", "images")}


@pytest.mark.parametrize("exported, expected", [(None, "1000"), ("7", "7")])
def test_the_command_line_shortens_openmp_spinning_before_torch_loads_unless_the_user_set_it(exported, expected):
    """libgomp reads GOMP_SPINCOUNT when torch loads it: the command line sets 1,000 spins first (a CPU run on a busy
    machine otherwise goes about 3x slower), and leaves a value the user exported alone."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    if exported is not None:
        env["GOMP_SPINCOUNT"] = exported
    # the value in the environment at the moment torch is first imported (libgomp reads it then)
    script = ("import os, sys\n"
              "seen = []\n"
              "class Watch:\n"
              "    def find_spec(self, name, path=None, target=None):\n"
              "        if name == 'torch' and not seen:\n"
              "            seen.append(os.environ.get('GOMP_SPINCOUNT'))\n"
              "sys.meta_path.insert(0, Watch())\n"
              "import lanevil_train.__main__\n"
              "import torch\n"
              "print(seen[0])\n")
    out = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == [expected]
