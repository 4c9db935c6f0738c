"""The text-only reader, the QA leakage audit (task=audit_qa) and the visual-reliance table, on constructed QA whose
leaks are known: what the words alone answer must be found, and what they cannot answer must score chance."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lanevil_train.report.reliance import reliance_rows
from lanevil_train.vlm.answer_scoring.leakage import audit, read_qa_file, template_of
from lanevil_train.vlm.backends.text_only import TextOnlyReader, TextOnlyVLM, split_prompt
from lanevil_train.vlm.clips.qa_records import answer_is_correct, prompt_text

LEAKY_YES_NO = "Are the dark straight lines on the right shoulder part of the lane markings?"  # always No
LEAKY_CHOICE = "What should the ego vehicle do next?"  # the safe action always the same
BALANCED_YES_NO = "Is the road surface wet?"
BALANCED_CHOICE = "How many lanes does this road have?"
ACTIONS = ["Keep driving in its lane.", "Brake hard to a full stop.", "Swerve into the lane on its left.",
           "Swerve into the lane on its right."]
LANES = ["Two lanes.", "Three lanes.", "Four lanes.", "Five lanes."]


def _choice(qa_id, base, question, options, right, rng):
    order = [int(i) for i in rng.permutation(len(options))]
    choices = [f"{chr(65 + k)}. {options[i]}" for k, i in enumerate(order)]
    return {"qa_id": qa_id, "base_clip_id": base, "category": "action", "type": "choice", "question": question,
            "answer": choices[order.index(right)], "choices": choices}


def _yes_no(qa_id, base, category, question, yes):
    return {"qa_id": qa_id, "base_clip_id": base, "category": category, "type": "yes_no", "question": question,
            "answer": "Yes. It is." if yes else "No. It is not."}


def built_like_before(scenes: int = 60, seed: int = 0) -> list[dict]:
    """QA made the way the suite was before issue 44: the answer drawn first and the wording chosen so that the truth
    answers it that way ("Is it daytime?" where the day answers Yes, "Is it night-time?" where it answers No: as most
    scenes are by day, each wording has its own answer), an illusion question with one answer whatever the clip
    shows, one safe action; beside two templates whose answer is a fair coin."""
    rng = np.random.default_rng(seed)
    records = []
    for s in range(scenes):
        base, day, yes = f"case{s:03d}-over", bool(rng.random() < 0.85), bool(rng.random() < 0.5)  # most are day
        wording = "Is it daytime in this scene?" if yes == day else "Is it night-time in this scene?"
        records += [
            _yes_no(f"{base}-q0", base, "scene_description", wording, yes),
            _yes_no(f"{base}-q1", base, "object_recognition", LEAKY_YES_NO, yes=False),
            _choice(f"{base}-q2", base, LEAKY_CHOICE, ACTIONS, 0, rng),
            _yes_no(f"{base}-q3", base, "scene_description", BALANCED_YES_NO, yes=bool(rng.random() < 0.5)),
            {**_choice(f"{base}-q4", base, BALANCED_CHOICE, LANES, int(rng.integers(4)), rng),
             "category": "lane_recognition"},
        ]
    for r in records:
        r["scene"] = r["base_clip_id"].split("-")[0]
    return records


def test_the_reader_answers_what_the_words_give_away_and_nothing_else():
    records = built_like_before(80)
    train, test = records[:200], records[200:]
    reader = TextOnlyReader().fit(train)
    by_question = {}
    for qa in test:
        by_question.setdefault(qa["question"], []).append(bool(answer_is_correct(qa, reader.predict(qa))))
    assert np.mean(by_question[LEAKY_YES_NO]) == 1.0 and np.mean(by_question[LEAKY_CHOICE]) == 1.0
    assert np.mean(by_question["Is it daytime in this scene?"] + by_question["Is it night-time in this scene?"]) > 0.75
    assert 0.2 <= np.mean(by_question[BALANCED_YES_NO]) <= 0.8  # a coin: about half
    assert np.mean(by_question[BALANCED_CHOICE]) <= 0.6  # about a quarter
    # from the prompt alone, as a model is asked: the same answers (the type told by the words and the options)
    for qa in test:
        assert answer_is_correct(qa, reader.answer_prompt(prompt_text(qa))) == \
            answer_is_correct(qa, reader.predict(qa)), qa
    question, options = split_prompt(prompt_text(test[2]))
    assert question == LEAKY_CHOICE and options == test[2]["choices"]
    vlm = TextOnlyVLM(reader, "m-text")
    assert vlm.reads_frames is False and vlm.identity()["fitted_on"] == reader.digest
    assert vlm.answer([[], []], [prompt_text(test[1]), prompt_text(test[2])])[0] == "No"


def test_the_reader_uses_where_the_right_option_stands():
    """A file whose right answer is always option A (letters not dealt evenly) is answered from the letter."""
    rng = np.random.default_rng(3)
    records = []
    for k in range(120):
        qa = _choice(f"c{k}-q0", f"c{k}", f"Which colour is car {k}?", ["Red.", "Blue.", "Green.", "White."],
                     int(rng.integers(4)), rng)
        right = qa["answer"]
        qa["choices"] = [right.replace(right[0], "A", 1)] + [c for c in qa["choices"] if c != right]
        qa["choices"] = [f"{chr(65 + i)}.{c.split('.', 1)[1]}" for i, c in enumerate(qa["choices"])]
        qa["answer"] = qa["choices"][0]
        records.append(qa)
    reader = TextOnlyReader().fit(records[:80])
    assert np.mean([answer_is_correct(qa, reader.predict(qa)) for qa in records[80:]]) == 1.0


def test_the_audit_flags_the_leaking_templates_by_name_and_passes_the_balanced_ones():
    result = audit(built_like_before(60), folds=2, seed=0, min_count=8, alpha=0.01)
    leaking = {t["template"] for t in result["leaking"]}
    assert {LEAKY_YES_NO, LEAKY_CHOICE, "Is it daytime in this scene?", "Is it night-time in this scene?"} <= leaking
    assert BALANCED_YES_NO not in leaking and BALANCED_CHOICE not in leaking
    templates = {t["template"]: t for t in result["templates"]}
    assert templates[LEAKY_YES_NO]["yes_share"] == 0.0 and templates[LEAKY_YES_NO]["text_only_accuracy"] == 100.0
    assert templates[LEAKY_CHOICE]["top_option"] == ACTIONS[0] and templates[LEAKY_CHOICE]["top_option_share"] == 100
    assert abs(templates[BALANCED_YES_NO]["text_only_accuracy"] - 50) <= 25
    by_type = {r["type"]: r for r in result["by_type"]}
    assert by_type["yes_no"]["chance"] == 50.0 and by_type["choice"]["chance"] == 25.0
    assert result["settings"] == {"folds": 2, "seed": 0, "min_count": 8, "alpha": 0.01, "questions": 300,
                                  "closed": 300, "scenes": 60, "templates_judged": 6}


def test_a_balanced_file_scores_chance_and_nothing_leaks():
    rng = np.random.default_rng(5)
    records = []
    for s in range(80):
        base = f"s{s}"
        records += [{**_yes_no(f"{base}-a", base, "scene_description", BALANCED_YES_NO, bool(rng.random() < 0.5)),
                     "scene": base},
                    {**_choice(f"{base}-b", base, BALANCED_CHOICE, LANES, int(rng.integers(4)), rng), "scene": base}]
    result = audit(records, min_count=8)
    assert result["leaking"] == []
    by_type = {r["type"]: r for r in result["by_type"]}
    assert abs(by_type["yes_no"]["text_only_accuracy"] - 50) <= 15
    assert abs(by_type["choice"]["text_only_accuracy"] - 25) <= 15


def test_a_drivelm_file_is_audited_with_its_object_references_masked(tmp_path):
    from lanevil_train.vlm.clips.drivelm import write_drivelm

    records = built_like_before(12)
    clips = [{"clip_id": f"{qa['base_clip_id']}-clean", "base_clip_id": qa["base_clip_id"], "case_id": qa["scene"],
              "segment": "over", "illusion": None, "category": None, "severity": 0, "seed": 0,
              "frames": [f"f/{k}.png" for k in range(6)]} for qa in records[::5]]
    path = tmp_path / "drivelm.json"
    write_drivelm(path, clips, [{k: v for k, v in qa.items() if k != "scene"} for qa in records])
    read = read_qa_file(path)
    assert len(read) == len(records) and {r["scene"] for r in read} == {r["scene"] for r in records}
    assert template_of({"question": "What is the status of <c1,CAM_FRONT,714.2,483.3> at 12 m?"}) == \
        "What is the status of # at # m?"


def test_task_audit_qa_reads_a_suite_folder_and_writes_its_report(tmp_path):
    from tests.tasks.cli_helpers import run_in_process

    records = built_like_before(40)
    suite = tmp_path / "suite"
    suite.mkdir()
    bases = sorted({qa["base_clip_id"] for qa in records})
    (suite / "qa.jsonl").write_text("".join(json.dumps({k: v for k, v in qa.items() if k != "scene"}) + "\n"
                                            for qa in records))
    (suite / "clips.jsonl").write_text("".join(json.dumps({
        "clip_id": f"{b}-clean", "base_clip_id": b, "case_id": b.split("-")[0], "segment": "over", "illusion": None,
        "category": None, "severity": 0, "seed": 0, "frames": [f"f/{k}.png" for k in range(6)]}) + "\n"
        for b in bases))
    out = tmp_path / "audit"
    value = run_in_process(["task=audit_qa", f"task.suite={suite}", f"task.out_dir={out}", "progress=none"],
                           tmp_path / "run")
    saved = json.loads((out / "qa_audit.json").read_text())
    assert value == pytest.approx(next(r for r in saved["by_type"] if r["type"] == "yes_no")["text_only_accuracy"])
    assert LEAKY_YES_NO in {t["template"] for t in saved["leaking"]} and (out / "qa_audit.png").stat().st_size > 0
    assert "## Templates that give their answer away" in (out / "qa_audit.md").read_text()
    with pytest.raises(ValueError, match=r"task\.folds: expected an integer >= 2, got 1"):
        run_in_process(["task=audit_qa", f"task.suite={suite}", "task.folds=1"], tmp_path / "run2")


def _answers(model, kind, correct, scenes=40, per_scene=4):
    return [{"key": f"s{s}/q{k}", "model": model, "case_id": f"s{s}-over", "scene": f"s{s}", "qa_type": kind,
             "qa_category": "scene_description", "correct": int(correct(s, k))}
            for s in range(scenes) for k in range(per_scene)]


def test_visual_reliance_is_the_model_minus_the_better_baseline_with_a_paired_interval():
    rng = np.random.default_rng(0)
    coin = {(s, k): bool(rng.random() < 0.5) for s in range(40) for k in range(4)}
    model = _answers("m", "yes_no", lambda s, k: True)
    grey = _answers("m-blind", "yes_no", lambda s, k: coin[s, k])
    text = _answers("m-text", "yes_no", lambda s, k: k < 3)  # 75 %: the better baseline
    [row, total] = reliance_rows(model, {"m-blind": grey, "m-text": text})
    assert row["qa_category"] == "scene_description" and total["qa_category"] == "all"
    assert row["yes_no/best_baseline"] == "m-text" and row["yes_no/reliance"] == pytest.approx(25.0)
    assert row["yes_no/low"] > 0 and row["yes_no/distinguishable"] and row["choice/n"] == 0
    same = reliance_rows(text, {"m-blind": grey, "m-text": text})[0]
    assert same["yes_no/reliance"] == 0.0 and not same["yes_no/distinguishable"]
    with pytest.raises(ValueError, match="at least one blind baseline"):
        reliance_rows(model, {})


def test_the_accuracy_gap_pairs_each_perturbed_answer_with_its_clean_twin_and_has_an_interval():
    from lanevil_train.report.reliance import gap_rows

    records = []
    for s in range(30):
        for k in range(4):
            base = {"scene": f"s{s}", "case_id": f"s{s}-over", "qa_id": f"s{s}-q{k}", "qa_type": "yes_no",
                    "qa_category": "lane_recognition" if k < 2 else "action"}
            records.append({**base, "severity": 0, "correct": 1})  # right on every clean clip
            for severity in (1, 2):  # the illusion breaks question 0 at both severities, question 2 at severity 2
                wrong = k == 0 or (k == 2 and severity == 2)
                records.append({**base, "severity": severity, "correct": int(not wrong)})
    rows = {row["qa_category"]: row for row in gap_rows(records, order=["action", "lane_recognition"])}
    assert list(rows) == ["action", "lane_recognition", "all"]
    assert rows["lane_recognition"]["n"] == 120 and rows["lane_recognition"]["gap"] == pytest.approx(-50.0)
    assert rows["action"]["gap"] == pytest.approx(-25.0) and rows["all"]["gap"] == pytest.approx(-37.5)
    assert rows["all"]["original"] == 100.0 and rows["all"]["high"] < 0 and rows["all"]["distinguishable"]
    assert gap_rows([r for r in records if r["severity"] == 0]) == []  # no perturbed answer: no gap
