"""`task=evaluate task.suite=...` and `task=report` over run directories, from the command line."""

from __future__ import annotations

import json

import pytest

from lanevil_train.evaluation.lane_records import read_records
from tests.tasks.cli_helpers import TINY, run_cli, run_in_process, write_fake_run


def test_report_combines_run_directories(tmp_path):
    write_fake_run(tmp_path / "runs" / "0", "laneatt", original=0.9, perturbed=0.6)
    write_fake_run(tmp_path / "runs" / "1", "ufld", original=0.8, perturbed=0.7)
    out = tmp_path / "report"
    run_in_process(["task=report", f"task.runs=[{tmp_path / 'runs'}]", "task.baseline=laneatt", "progress=none"], out)
    scores = json.loads((out / "test_scores.json").read_text())
    assert [(r["model"], r["images_kind"], round(r["Accuracy"], 6)) for r in scores] == [
        ("laneatt", "original", 90.0), ("laneatt", "perturbed", 60.0),
        ("ufld", "original", 80.0), ("ufld", "perturbed", 70.0)]
    assert (out / "report.md").is_file()
    assert sorted(p.name for p in out.glob("*.png"))  # plots were written
    for png in out.glob("*.png"):
        assert png.stat().st_size > 2000


def test_evaluate_on_the_synthetic_illusion_suite_resumes_in_place(tmp_path):
    train_dir = tmp_path / "train"
    run_in_process([*TINY, "trainer.max_steps=1", "trainer.limit_val_batches=0", "task.test_after_fit=false"],
                   train_dir)
    ckpt = train_dir / "checkpoints" / "last.ckpt"
    (train_dir / ".hydra").mkdir()  # what Hydra saves beside a command-line run: the card's training data
    (train_dir / ".hydra" / "config.yaml").write_text("task: {name: train}\ndata: {name: synthetic}\n")
    out = tmp_path / "eval"
    args = ["task=evaluate", f"ckpt_path={ckpt}", *TINY, "task.suite=synthetic", "task.cases=2",
            "task.illusions=[fence_shadow,pedestrian]", "task.severities=[2,4]", f"task.out_dir={out}"]
    run_in_process(args, tmp_path / "run1")
    records = read_records(out / "per_image.jsonl")
    assert len(records) == 2 * (1 + 2 * 2)
    assert (out / "report.md").is_file()
    card = json.loads((out / "robustness_card.json").read_text())  # validated when written (report/card.py)
    assert (card["model"]["family"], card["suite"]["cases"], card["suite"]["severities"]) == ("laneatt", 2, [2, 4])
    assert card["model"]["training_data"] == "synthetic" and len(card["model"]["checkpoint_sha256"]) == 64
    assert card["suite"]["plan"]["illusions"] == ["fence_shadow", "pedestrian"]
    run_in_process(args, tmp_path / "run2")  # everything is already there: nothing is added
    assert len(read_records(out / "per_image.jsonl")) == 10


def test_cross_domain_scores_a_real_folder_beside_the_suite(tmp_path):
    from lanevil_train.data.formats import write_tusimple
    from tests.tasks.cli_helpers import write_photo_dataset

    root = tmp_path / "tusimple"
    write_tusimple(write_photo_dataset(root, [f"clips/x/{i}/20.jpg" for i in range(2)]), root / "test.json")
    train_dir = tmp_path / "train"
    run_in_process([*TINY, "trainer.max_steps=1", "trainer.limit_val_batches=0", "task.test_after_fit=false"],
                   train_dir)
    out = tmp_path / "xd"
    run_in_process(["task=cross_domain", f"ckpt_path={train_dir / 'checkpoints' / 'last.ckpt'}", "data=tusimple",
                    f"data.root={root}", "data.test.label_files=[test.json]", "data.batch_size=2",
                    "data.num_workers=0", "task.cases=1", "task.illusions=[vehicle]", "task.severities=[3]",
                    "progress=none", f"task.out_dir={out}"], tmp_path / "run")
    rows = json.loads((out / "test_scores.json").read_text())
    assert [(r["dataset"], r["images_kind"], r["images"]) for r in rows] == [
        ("tusimple", "original", 2), ("synthetic-illusions", "original", 1), ("synthetic-illusions", "perturbed", 1)]


def test_report_goes_to_wandb_offline_as_tables_and_images(tmp_path):
    write_fake_run(tmp_path / "runs" / "0", "laneatt", original=0.9, perturbed=0.6)
    out = tmp_path / "report"
    run_cli(["task=report", f"task.runs=[{tmp_path / 'runs'}]", "logger=wandb", "progress=none"], out)
    run = next((out / "wandb").glob("offline-run-*"))
    data = b"".join(p.read_bytes() for p in run.rglob("*.wandb"))
    assert b"evaluate/test_scores" in data and b"evaluate/plots" in data


def test_evaluate_a_built_set_draws_the_worst_cases(tmp_path):
    from lanevil_train.data.illusion_set import Plan, build_illusion_set, synthetic_cases

    suite = tmp_path / "set"
    build_illusion_set(synthetic_cases(2, 1000000), Plan(illusions=("rail_shadow",), severities=(5,), size=(90, 160)),
                       suite, progress="none")
    train_dir = tmp_path / "train"
    run_in_process([*TINY, "trainer.max_steps=1", "trainer.limit_val_batches=0", "task.test_after_fit=false"],
                   train_dir)
    out = tmp_path / "eval"
    run_in_process(["task=evaluate", f"ckpt_path={train_dir / 'checkpoints' / 'last.ckpt'}", *TINY,
                    f"task.suite={suite}", f"task.out_dir={out}"], tmp_path / "run")
    records = read_records(out / "per_image.jsonl")
    assert len(records) == 4 and all(r["image"].startswith(str(suite)) for r in records)
    assert {r["category"] for r in records} == {None, "shadow"}
    assert (out / "worst_cases.png").stat().st_size > 2000


def _seed_run(path, model: str, seed: int, perturbed: float):
    """A Hydra run directory of `model` trained with `seed`: its config and its suite results."""
    write_fake_run(path, model, original=0.9, perturbed=perturbed)
    (path / ".hydra").mkdir()
    (path / ".hydra" / "config.yaml").write_text(f"seed: {seed}\n")


def test_report_over_seeds_summarises_each_model_and_its_gain_with_an_interval(tmp_path):
    from lanevil_train.tasks.report import results_files, write_run_reports

    # a sweep over model and seed: laneatt at 60 +- 1 over 3 seeds, ufld at 70 +- 1
    for job, (model, seed) in enumerate((m, s) for m in ("laneatt", "ufld") for s in (0, 1, 2)):
        base = 0.6 if model == "laneatt" else 0.7
        _seed_run(tmp_path / "sweep" / str(job), model, seed, base + 0.01 * (seed - 1))
    out = tmp_path / "report"
    out.mkdir()
    write_run_reports(results_files([str(tmp_path / "sweep")]), out, baseline="laneatt", replicates=400)
    scores = json.loads((out / "test_scores.json").read_text())
    assert {r["model"] for r in scores} == {f"{m} (seed {s})" for m in ("laneatt", "ufld") for s in (0, 1, 2)}
    seeds = {(r["name"], r["category"]): r for r in json.loads((out / "seeds.json").read_text())}
    assert seeds["ufld", "shadow"]["Accuracy"] == pytest.approx(70.0)
    assert seeds["ufld", "shadow"]["Accuracy/std"] == pytest.approx(1.0)
    assert seeds["ufld", "shadow"]["Accuracy/runs"] == pytest.approx([69.0, 70.0, 71.0])
    gains = {r["category"]: r for r in json.loads((out / "seed_gains.json").read_text())}
    assert gains["average"]["Accuracy/gain"] == pytest.approx(10.0) and gains["average"]["Accuracy/distinguishable"]
    assert gains["original"]["Accuracy/gain"] == 0.0 and not gains["original"]["Accuracy/distinguishable"]
    text = (out / "seeds.md").read_text()
    assert "70.00 ± 1.00" in text and "+10.00 [" in text and (out / "seed_gains.png").stat().st_size > 2000
