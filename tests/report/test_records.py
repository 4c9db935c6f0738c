"""Generic result records: a VQA-like spec (two scores, one lower-is-better, several questions per clip, a QA
category table) gets the paper's tables from the same code as the lane detectors, with hand-computed values."""

from __future__ import annotations

import json

import pytest

from lanevil_train.evaluation.results import write_results
from lanevil_train.report import specs
from lanevil_train.report.defenses import best_defense, defense_gain, defense_scores
from lanevil_train.report.records import Field, RecordSet, RecordSpec, Score, mean_of, validate_records
from lanevil_train.report.robustness import group_table, main_table, relative_table, severity_table, type_table

VQA = RecordSpec(
    name="vqa-test",
    fields=(Field("gpt", 0.0, 100.0), Field("hallucinated", 0.0, 1.0)),
    scores=(Score("GPT", mean_of("gpt", scale=1.0)),
            Score("Hallucination", mean_of("hallucinated"), higher_is_better=False)),
    item_key="question_id",
    groups=("qa_category",),
)


def qa(case, question, severity, gpt, hallucinated, illusion=None, model="vlm"):
    category = {"q1": "perception", "q2": "prediction"}[question]
    return {"spec": "vqa-test", "model": model, "dataset": "clips", "case_id": case, "question_id": question,
            "qa_category": category, "illusion": illusion, "severity": severity, "gpt": gpt,
            "hallucinated": hallucinated, "key": f"{case}/{question}/{illusion}/{severity}"}


FS, VE = "fence_shadow", "vehicle"
RECORDS = [
    qa("k1", "q1", 0, 80, 0), qa("k1", "q2", 0, 60, 0), qa("k2", "q1", 0, 90, 0), qa("k2", "q2", 0, 40, 1),
    qa("k1", "q1", 1, 70, 0, FS), qa("k1", "q2", 1, 50, 1, FS), qa("k2", "q1", 1, 90, 0, FS),
    qa("k2", "q2", 1, 30, 1, FS),
    qa("k1", "q1", 3, 40, 1, FS), qa("k1", "q2", 3, 20, 1, FS),
    qa("k1", "q1", 2, 60, 0, VE),
]


def test_main_table_pools_perturbed_answers_against_the_same_questions_clean():
    row = main_table(RecordSet(RECORDS, VQA))[0]
    # shadow: 6 perturbed answers, GPT 300/6 = 50; Original = the 4 questions' clean answers, 270/4 = 67.5
    assert row["shadow/GPT/Perturbed"] == pytest.approx(50.0)
    assert row["shadow/GPT/Original"] == pytest.approx(67.5)
    assert row["shadow/GPT/Gap"] == pytest.approx(-17.5)
    # lower is better: 4 of 6 hallucinated vs 1 of 4 clean, a positive gap is the harm
    assert row["shadow/Hallucination/Perturbed"] == pytest.approx(400 / 6)
    assert row["shadow/Hallucination/Original"] == pytest.approx(25.0)
    assert row["shadow/Hallucination/Gap"] == pytest.approx(400 / 6 - 25)
    # traffic: only k1/q1 was perturbed, so its Original is k1/q1's clean answer alone (80), not the clip's mean
    assert row["traffic_obstruction/GPT/Original"] == pytest.approx(80.0)
    assert row["traffic_obstruction/GPT/Gap"] == pytest.approx(-20.0)
    assert row["average/GPT/Perturbed"] == pytest.approx(55.0)
    assert row["average/GPT/Original"] == pytest.approx(73.75)
    assert row["average/Hallucination/Gap"] == pytest.approx(((400 / 6 - 25) + 0) / 2)
    assert list(row)[:7] == ["model", "traffic_obstruction/GPT/Perturbed", "traffic_obstruction/GPT/Original",
                             "traffic_obstruction/GPT/Gap", "traffic_obstruction/Hallucination/Perturbed",
                             "traffic_obstruction/Hallucination/Original", "traffic_obstruction/Hallucination/Gap"]


def test_type_severity_and_qa_category_tables():
    rs = RecordSet(RECORDS, VQA)
    types = {r["illusion"]: r for r in type_table(rs)}
    assert list(types) == [VE, FS]  # paper order: traffic before shadow
    assert types[FS]["GPT/Gap"] == pytest.approx(-17.5) and types[VE]["Hallucination/Perturbed"] == 0.0
    sev = {(r["category"], r["severity"]): r for r in severity_table(rs)}
    assert list(sev) == [("traffic_obstruction", 2), ("shadow", 1), ("shadow", 3)]
    assert sev[("shadow", 1)]["images"] == 4 and sev[("shadow", 1)]["GPT"] == pytest.approx(60.0)
    assert sev[("shadow", 1)]["Hallucination/Gap"] == pytest.approx(25.0)
    s3 = sev[("shadow", 3)]  # k1 only: Original is k1's two clean answers
    assert (s3["GPT"], s3["GPT/Original"], s3["GPT/Gap"]) == pytest.approx((30.0, 70.0, -40.0))
    assert (s3["Hallucination"], s3["Hallucination/Original"]) == pytest.approx((100.0, 0.0))
    assert list(s3) == ["model", "category", "severity", "images", "GPT", "Hallucination", "GPT/Original",
                        "Hallucination/Original", "GPT/Gap", "Hallucination/Gap"]
    qa_rows = {r["qa_category"]: r for r in group_table(rs, "qa_category")}
    assert qa_rows["perception"]["images"] == 4
    assert qa_rows["perception"]["GPT/Perturbed"] == pytest.approx(65.0)
    assert qa_rows["perception"]["GPT/Original"] == pytest.approx(85.0)
    assert qa_rows["prediction"]["GPT/Perturbed"] == pytest.approx(100 / 3)
    assert qa_rows["prediction"]["Hallucination/Original"] == pytest.approx(50.0)


def test_relative_robustness_on_the_headline_score():
    row = relative_table(RecordSet(RECORDS, VQA))[0]
    assert row["shadow/RelRobustness"] == pytest.approx(100 * 50 / 67.5)
    assert row["traffic_obstruction/RelRobustness"] == pytest.approx(100 * 60 / 80)
    lower_first = RecordSpec("vqa-test", VQA.fields, VQA.scores[::-1], item_key="question_id")
    row = relative_table(RecordSet(RECORDS, lower_first))[0]  # lower is better: Original / Perturbed
    assert row["shadow/RelRobustness"] == pytest.approx(100 * 25 / (400 / 6))


def test_validation_names_the_record_and_the_spec_fields():
    with pytest.raises(ValueError, match=r"record 1: missing required key\(s\) \['question_id'\]"):
        validate_records([RECORDS[0], {k: v for k, v in RECORDS[1].items() if k != "question_id"}], VQA)
    with pytest.raises(ValueError, match=r"record 0: gpt must be a number in \[0.0, 100.0\], got 130"):
        validate_records([{**RECORDS[0], "gpt": 130}], VQA)
    with pytest.raises(ValueError, match="record 0: a 'lane' record among 'vqa-test' records"):
        validate_records([{**RECORDS[0], "spec": "lane"}], VQA)
    # the same question's clean answer twice counts once; with different scores it is an error
    assert len(validate_records(RECORDS + [RECORDS[0]], VQA)) == len(RECORDS)
    with pytest.raises(ValueError, match="second clean"):
        validate_records(RECORDS + [{**RECORDS[0], "gpt": 10}], VQA)


def test_best_defense_follows_the_headline_direction():
    lower_first = RecordSpec("vqa-test", VQA.fields, VQA.scores[::-1], item_key="question_id")
    score_rows = [{"defense": "none", "average/Hallucination": 33.3}, {"defense": "x", "average/Hallucination": 100.0}]
    assert best_defense(score_rows, lower_first) == ("none", 33.3)
    assert best_defense(score_rows[::-1], lower_first) == ("none", 33.3)


def test_a_registered_spec_goes_through_the_whole_report_path(tmp_path, monkeypatch):
    monkeypatch.setitem(specs.SPECS, VQA.name, VQA)
    results = tmp_path / "run" / "per_image.jsonl"
    results.parent.mkdir()
    results.write_text("".join(json.dumps(r) + "\n" for r in RECORDS))
    headline = write_results([results], tmp_path / "out")
    assert headline == pytest.approx(360 / 7)  # GPT over all 7 perturbed answers
    main = json.loads((tmp_path / "out" / "main.json").read_text())
    assert main[0]["shadow/GPT/Gap"] == pytest.approx(-17.5)
    per_qa = json.loads((tmp_path / "out" / "per_qa_category.json").read_text())
    assert [r["qa_category"] for r in per_qa] == ["perception", "prediction"]
    summary = json.loads((tmp_path / "out" / "test_scores.json").read_text())
    assert [(r["images_kind"], r["images"]) for r in summary] == [("original", 4), ("perturbed", 7)]
    assert summary[0]["GPT"] == pytest.approx(67.5) and summary[0]["Hallucination"] == pytest.approx(25.0)
    report = (tmp_path / "out" / "report.md").read_text()
    assert "Lower is better for Hallucination" in report and "## Per qa category" in report
    assert (tmp_path / "out" / "gpt_vs_severity.png").stat().st_size > 5000
    assert (tmp_path / "out" / "gap_heatmap.png").stat().st_size > 5000
    # defense comparison on the same spec: gains per score, the lower-is-better one included
    defended = [{**r, "model": "vlm+pat++", "gpt": min(100.0, r["gpt"] + 10)} for r in RECORDS]
    gains = {(g["defense"], g["category"]): g for g in defense_gain(defense_scores({"none": RECORDS,
                                                                                   "pat++": defended}))}
    assert gains[("pat++", "shadow")]["GPT/gain"] == pytest.approx(10.0)  # every answer +10, none past the cap
    assert gains[("pat++", "shadow")]["Hallucination/gain"] == pytest.approx(0.0)
