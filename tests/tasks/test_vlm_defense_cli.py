"""Textual VLM defenses from the command line: defense=pat++ tunes a prefix for a saved tiny VLM (hard examples
found by asking it), writes prefix.json, tests it, resumes, and task=evaluate applies it again; defense=self_reminder
needs no training and tests the reminded model."""

from __future__ import annotations

import json

import pytest
from omegaconf import OmegaConf

from lanevil_dev.tiny_vlm import build_tiny_vlm
from lanevil_train.results_log import ResultsLog
from tests.tasks.cli_helpers import composed, run_cli, run_in_process
from tests.tasks.test_vlm_train_cli import ANSWERS, TINY_CLIPS

TINY_PAT = ["defense=pat++", "defense.steps=2", "defense.prefix_length=3", "defense.top_k=8",
            "defense.num_candidates=6", "defense.examples=2", "defense.pool_clips=4", "defense.chunk=8"]


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    return build_tiny_vlm("qwen2_vl", tmp_path_factory.mktemp("models") / "tiny-qwen2-vl")


def test_pat_plus_plus_tunes_a_prefix_tests_it_resumes_and_evaluates_with_it(tiny_model, tmp_path):
    run = tmp_path / "pat"
    # a random tiny model gets every yes/no wrong: the offline judge's scores tell its answers apart
    clips = [a for a in TINY_CLIPS if a != "judge=none"] + ["judge=minilm"]
    common = ["model=vlm/hf", f"model.path={tiny_model}", "model.max_new_tokens=4", *clips]
    run_cli(["task=train", *common, *TINY_PAT, "defense.hardness=judge"], run)
    record = json.loads((run / "prefix.json").read_text())
    assert record["step"] == 2 and len(record["ids"]) == 3 and len(record["history"]) == 3
    assert record["history"][-1] <= record["history"][0]
    chosen = json.loads((run / "examples.json").read_text())
    examples = chosen["examples"]
    assert sorted(e["hard"] for e in examples) == [False, False, True, True]
    assert all((e["score"] < chosen["mean_score"]) == e["hard"] for e in examples)
    assert all(e["target"] == "I will focus on the factors affecting the road" for e in examples if e["hard"])
    tested = ResultsLog(run / "test" / "per_answer.jsonl").records()
    assert len(tested) == ANSWERS and {r["model"] for r in tested} == {"tiny-qwen2-vl+pat++"}
    report = (run / "test" / "report.md").read_text()
    assert report.startswith("# Robustness report\n\n## Defense: PAT++ prefix")
    assert f"3 tokens: `` {record['text']} ``" in report and str(record["ids"]) in report

    # more steps resume from the prefix reached, reusing the examples chosen
    run_in_process(["task=train", *common, *TINY_PAT, "defense.hardness=judge", "defense.steps=3",
                    "task.test_after_fit=false"], run)
    resumed = json.loads((run / "prefix.json").read_text())
    assert resumed["step"] == 3 and resumed["history"][:3] == pytest.approx(record["history"])
    assert json.loads((run / "examples.json").read_text())["examples"] == examples
    with pytest.raises(ValueError, match="examples chosen with hard_target='goal', this run has "
                                         "hard_target='goal_then_answer'"):
        run_in_process(["task=train", *common, *TINY_PAT, "defense.hardness=judge",
                        "defense.hard_target=goal_then_answer"], run)

    # task=evaluate with the prefix answers as the tuning run's test did (with its 2-step prefix)
    out = tmp_path / "eval"
    (tmp_path / "two_steps.json").write_text(json.dumps(record))
    run_in_process(["task=evaluate", *common, "defense=pat++", f"defense.prefix_path={tmp_path / 'two_steps.json'}",
                    "task.suite=synthetic", f"task.out_dir={out}"], tmp_path / "eval-run")
    answers = {r["key"]: r["answer"] for r in ResultsLog(out / "per_answer.jsonl").records()}
    assert answers == {r["key"]: r["answer"] for r in tested}
    assert str(record["ids"]) in (out / "report.md").read_text()


def test_defense_misuse_is_refused_naming_the_key_before_any_work(tiny_model, tmp_path):
    from lanevil_train.tasks.vlm.evaluate import evaluate_vlm
    from lanevil_train.tasks.vlm.train import check_lanes_for_defense, train_vlm

    common = ["model=vlm/hf", f"model.path={tiny_model}", *TINY_CLIPS, f"output_dir={tmp_path / 'run'}"]
    with pytest.raises(ValueError, match="defense.prefix_path: defense=pat\\+\\+ applies a tuned prefix"):
        evaluate_vlm(composed(["task=evaluate", *common, "defense=pat++", "task.suite=synthetic",
                              f"task.out_dir={tmp_path / 'eval'}"]))
    with pytest.raises(ValueError, match="model.path: defense=pat\\+\\+ tunes a prefix for a trained model"):
        train_vlm(composed(["task=train", "model=vlm/embedded", *TINY_CLIPS, "defense=pat++"]))
    with pytest.raises(ValueError, match="defense.hardness: judge needs a judge .* got judge=none"):
        train_vlm(composed(["task=train", *common, "defense=pat++", "defense.hardness=judge"]))
    with pytest.raises(ValueError, match="defense=cutout: its image transforms act on a lane detector's samples"):
        train_vlm(composed(["task=train", *common, "defense=cutout"]))
    with pytest.raises(ValueError, match="defense=copypaste: .*CopyPaste moves lanes with their labels"):
        train_vlm(composed(["task=train", *common, "defense=copypaste"]))
    with pytest.raises(ValueError, match="defense=aam\\+\\+: model.attention_layer: auto knows the vision output of "
                                         "qwen2_vl, .* not 'gemma3'"):
        bad = tmp_path / "gemma"
        bad.mkdir()
        (bad / "config.json").write_text('{"model_type": "gemma3"}')
        train_vlm(composed(["task=train", *common, f"model.path={bad}", "defense=aam++"]))
    assert not (tmp_path / "run").exists()  # refused before any output
    with pytest.raises(ValueError, match="defense=aam: AAM compares each frame's attention with its lanes, which "
                                         "object does not keep"):
        check_lanes_for_defense(composed(["task=train", *common, "defense=aam"]), object())


# every VLM defense config, one step (a fine-tuning step, or a tuning step of its prompt), and what it leaves
VLM_DEFENSES = {"none": "model", "pgd": "model", "mixup": "model", "aam": "model", "aam++": "model",
                "mida": "model+prefix", "pat++": "prefix", "pat": "prefix", "self_reminder": ""}


@pytest.mark.parametrize("defense", list(VLM_DEFENSES))
def test_every_vlm_defense_config_runs_a_step(defense, tiny_model, tmp_path):
    from lanevil_train.tasks.vlm.train import train_vlm

    run = tmp_path / "run"
    tiny_prompt = ["defense.steps=1", "defense.prefix_length=2", "defense.top_k=4", "defense.num_candidates=3",
                   "defense.examples=1", "defense.pool_clips=3", "defense.chunk=4"]
    overrides = ["task=train", "model=vlm/hf", f"model.path={tiny_model}", "model.lora.r=2", *TINY_CLIPS,
                 "trainer.max_steps=1", "task.test_after_fit=false", f"defense={defense}", f"output_dir={run}",
                 *(tiny_prompt if "prefix" in VLM_DEFENSES[defense] else []),
                 *(["defense.suffix_length=2"] if defense == "pat" else []), "callbacks=none"]
    assert train_vlm(composed(overrides)) is None
    leaves = VLM_DEFENSES[defense]
    assert (run / "model" / "adapter_config.json").is_file() == ("model" in leaves)
    if "prefix" in leaves:
        record = json.loads((run / "prefix.json").read_text())
        assert record["step"] == 1 and len(record["ids"]) == 2
        assert ("attack" in record) == (defense == "pat")
        if defense == "mida":  # PAT++ tuned for the model the AAM++ fine-tuning left
            assert record["facts"]["model"]["adapter"] == str(run / "model")
    else:
        assert not (run / "prefix.json").exists()


def test_self_reminder_trains_nothing_and_tests_the_reminded_model(tiny_model, tmp_path):
    run = tmp_path / "reminder"
    run_in_process(["task=train", "model=vlm/hf", f"model.path={tiny_model}", "model.max_new_tokens=4", *TINY_CLIPS,
                    "defense=self_reminder"], run)
    tested = ResultsLog(run / "test" / "per_answer.jsonl").records()
    assert len(tested) == ANSWERS and {r["model"] for r in tested} == {"tiny-qwen2-vl+self_reminder"}
    assert not (run / "checkpoints").exists() and not (run / "model").exists()
    assert "## Defense: Self-Reminder" in (run / "test" / "report.md").read_text()


def test_a_vlm_compare_tunes_textual_defenses_for_the_none_runs_model_reports_and_skips_finished_runs(tiny_model,
                                                                                                    tmp_path):
    """task=compare for a VLM: none and mixup fine-tune the same model; self_reminder is applied to the model the
    none run fine-tuned; the gain tables (judge score and Language per category) and the plot are written; a rerun
    trains nothing."""
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    from lanevil_train.tasks.compare import compare

    out = tmp_path / "compare"
    clips = [a for a in TINY_CLIPS if a != "judge=none"] + ["judge=minilm"]
    overrides = ["model=vlm/hf", f"model.path={tiny_model}", "model.max_new_tokens=4", "model.lora.r=2", *clips,
                 "trainer.max_steps=2", "callbacks=[model_checkpoint]"]
    cfg = composed(["task=compare", "task.defenses=[none,self_reminder,mixup]", f"task.out_dir={out}", *overrides])
    GlobalHydra.instance().clear()
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        compare(cfg, overrides=overrides)
        runs = out / "runs"
        reminder = OmegaConf.load(runs / "self_reminder" / "config.yaml")
        assert reminder.model.adapter == str(runs / "none" / "model") and reminder.model.merge_adapter is True
        assert not (runs / "self_reminder" / "model").exists()
        for defense in ("none", "mixup"):
            assert (runs / defense / "model" / "adapter_config.json").is_file()
        labels = {d: {r["model"] for r in ResultsLog(runs / d / "test" / "per_answer.jsonl").records()}
                  for d in ("none", "self_reminder", "mixup")}
        assert labels == {"none": {"tiny-qwen2-vl"}, "self_reminder": {"tiny-qwen2-vl+self_reminder"},
                          "mixup": {"tiny-qwen2-vl+mixup"}}
        gains = json.loads((out / "defense_gain.json").read_text())
        assert [(g["defense"], g["category"]) for g in gains] == [
            (d, c) for d in ("self_reminder", "mixup") for c in ("road_damage", "average", "original")]
        scores = {r["defense"]: r for r in json.loads((out / "defense_scores.json").read_text())}
        for gain in gains:
            for metric in ("MiniLM_score", "Language"):
                expected = scores[gain["defense"]][f"{gain['category']}/{metric}"] - \
                    scores["none"][f"{gain['category']}/{metric}"]
                assert gain[f"{metric}/gain"] == pytest.approx(expected)
        report = (out / "compare.md").read_text()
        assert "## MiniLM_score gain over none" in report and "## Language gain over none" in report
        assert (out / "defense_gain.png").stat().st_size > 5000
        before = {p: p.stat().st_mtime_ns for p in runs.rglob("*") if p.is_file()}
        compare(cfg, overrides=overrides)  # every run finished: nothing is trained, tuned or scored again
        assert {p: p.stat().st_mtime_ns for p in runs.rglob("*") if p.is_file()} == before
    GlobalHydra.instance().clear()


def test_each_textual_defense_is_tuned_for_the_model_of_the_defense_with_its_visual_part(tiny_model):
    from lanevil_train.tasks.compare import vlm_sources

    common = ["task=train", "model=vlm/hf", f"model.path={tiny_model}", *TINY_CLIPS]
    configs = {d: composed([*common, f"defense={d}"]) for d in ("none", "pat++", "mida", "aam++", "pgd", "pat")}
    assert vlm_sources(configs) == {"none": None, "pat++": "none", "mida": "aam++", "aam++": None, "pgd": None,
                                    "pat": "none"}
    del configs["aam++"]  # nothing listed does what mida does to the frames: it fine-tunes in its own run
    assert vlm_sources(configs)["mida"] is None


def test_pat_plus_plus_finds_hard_examples_by_each_answers_language_score(tiny_model, tmp_path, monkeypatch):
    from lanevil_train.metrics import vqa
    from lanevil_train.tasks.vlm.train import train_vlm

    seen = {}

    def scored(predictions, references, tokenized=False):  # the real scores, recorded
        seen.update(real(predictions, references, tokenized))
        seen["pairs"] = [(predictions[k], references[k]) for k in predictions]
        return {k: seen[k] for k in predictions}

    real = vqa.language_per_answer
    monkeypatch.setattr(vqa, "language_per_answer", scored)
    run = tmp_path / "run"
    train_vlm(composed(["task=train", "model=vlm/hf", f"model.path={tiny_model}", "model.max_new_tokens=4",
                       *TINY_CLIPS, "task.test_after_fit=false", "defense=pat++", "defense.hardness=language",
                       "defense.steps=1", "defense.prefix_length=2", "defense.top_k=4", "defense.num_candidates=3",
                       "defense.examples=2", "defense.pool_clips=3", "defense.chunk=4", f"output_dir={run}"]))
    chosen = json.loads((run / "examples.json").read_text())
    examples = chosen["examples"]
    assert chosen["choosing"]["hardness"] == "language" and \
        sorted(e["hard"] for e in examples) == [False] * 2 + [True] * 2
    values = [v for k, v in seen.items() if k != "pairs"]
    assert len(values) == chosen["pool"] == len(seen["pairs"]) and chosen["mean_score"] == pytest.approx(
        sum(values) / len(values))
    for e in examples:  # every pool question scored (open ones too), each example's score its answer's
        assert e["hard"] == (e["score"] < chosen["mean_score"]) and e["score"] in values
        assert any(answer == e["answer"] for answer, _ in seen["pairs"])
