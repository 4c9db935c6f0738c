"""Robustness tables against hand-computed values on a 2-model x 3-case x 2-category fixture."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from lanevil_train.report.records import validate_records as validate_with_spec
from lanevil_train.report.robustness import main_table, relative_table, severity_table, type_table, write_report
from lanevil_train.report.specs import LANE_SPEC


def validate_records(records):
    return validate_with_spec(records, LANE_SPEC)


def rec(model, case, sev, acc, fp, fn, illusion=None):
    cat = {"fence_shadow": "shadow", "sunlight_reflection": "reflection", None: None}[illusion]
    return {"model": model, "dataset": "tusimple", "case_id": case, "illusion": illusion, "category": cat,
            "severity": sev, "accuracy": acc, "fp": fp, "fn": fn}


FS, SR = "fence_shadow", "sunlight_reflection"
# c1 has shadow only, c2 shadow + reflection, c3 is clean only and must never enter an Original.
RECORDS = [
    rec("A", "c1", 0, 1.0, 0.0, 0.0), rec("A", "c2", 0, 0.8, 0.2, 0.2), rec("A", "c3", 0, 0.2, 0.6, 0.6),
    rec("A", "c1", 1, 0.6, 0.4, 0.2, FS), rec("A", "c2", 1, 0.4, 0.2, 0.4, FS), rec("A", "c1", 2, 0.2, 0.6, 0.8, FS),
    rec("A", "c2", 2, 0.5, 0.5, 0.0, SR),
    rec("B", "c1", 0, 0.5, 0.5, 0.5), rec("B", "c2", 0, 0.7, 0.3, 0.1), rec("B", "c3", 0, 1.0, 0.0, 0.0),
    rec("B", "c1", 1, 0.7, 0.1, 0.3, FS), rec("B", "c2", 1, 0.7, 0.3, 0.1, FS), rec("B", "c1", 2, 0.1, 0.2, 0.2, FS),
    rec("B", "c2", 2, 0.9, 0.1, 0.1, SR),
]


def f1(fp, fn):
    """CLRNet's TuSimple F1 by hand: tp = 1 - FP, P = tp / (tp + FP), R = tp / (tp + FN)."""
    tp = 1 - fp
    p, r = tp / (tp + fp), tp / (tp + fn)
    return 100 * 2 * p * r / (p + r)


def by_model(rows):
    return {r["model"]: r for r in rows}


def test_main_table_hand_values():
    rows = by_model(main_table(RECORDS))
    a, b = rows["A"], rows["B"]
    # A shadow: perturbed acc (.6+.4+.2)/3 = 40; fp .4, fn 1.4/3. Original = c1, c2 only: acc 90, fp .1, fn .1
    assert a["shadow/Accuracy/Perturbed"] == pytest.approx(40.0)
    assert a["shadow/Accuracy/Original"] == pytest.approx(90.0)
    assert a["shadow/Accuracy/Gap"] == pytest.approx(-50.0)
    assert a["shadow/F1/Perturbed"] == pytest.approx(58.0645161, abs=1e-6)  # P .6, R .5625
    assert a["shadow/F1/Perturbed"] == pytest.approx(f1(0.4, 1.4 / 3))
    assert a["shadow/F1/Original"] == pytest.approx(90.0)
    assert a["shadow/F1/Gap"] == pytest.approx(58.0645161 - 90.0, abs=1e-6)
    # A reflection: c2 only; perturbed acc 50, fp .5 fn 0 -> P .5, R 1 -> F1 66.67; original c2: 80 / 80
    assert a["reflection/Accuracy/Perturbed"] == pytest.approx(50.0)
    assert a["reflection/Accuracy/Original"] == pytest.approx(80.0)
    assert a["reflection/F1/Perturbed"] == pytest.approx(200 / 3)
    assert a["reflection/F1/Original"] == pytest.approx(80.0)
    # average = mean of the two categories
    assert a["average/Accuracy/Perturbed"] == pytest.approx(45.0)
    assert a["average/Accuracy/Original"] == pytest.approx(85.0)
    assert a["average/Accuracy/Gap"] == pytest.approx(-40.0)
    assert a["average/F1/Gap"] == pytest.approx(((58.0645161 - 90) + (200 / 3 - 80)) / 2, abs=1e-6)
    # B: shadow acc (.7+.7+.1)/3 = 50 vs original (.5+.7)/2 = 60; reflection 90 vs 70 (a positive gap)
    assert b["shadow/Accuracy/Gap"] == pytest.approx(-10.0)
    assert b["shadow/F1/Perturbed"] == pytest.approx(80.0)
    assert b["shadow/F1/Original"] == pytest.approx(63.1578947, abs=1e-6)  # fp .4 fn .3
    assert b["reflection/Accuracy/Gap"] == pytest.approx(20.0)
    assert b["reflection/F1/Original"] == pytest.approx(77.7777778, abs=1e-6)  # fp .3 fn .1
    assert list(a)[:7] == ["model", "shadow/Accuracy/Perturbed", "shadow/Accuracy/Original", "shadow/Accuracy/Gap",
                           "shadow/F1/Perturbed", "shadow/F1/Original", "shadow/F1/Gap"]


def test_gap_sign_perturbed_worse_is_negative():
    recs = [rec("M", "x", 0, 0.9, 0.1, 0.1), rec("M", "x", 3, 0.3, 0.5, 0.5, FS)]
    row = main_table(recs)[0]
    assert row["shadow/Accuracy/Gap"] == pytest.approx(-60.0)
    assert row["shadow/F1/Gap"] < 0


def test_original_uses_only_the_same_cases():
    # c3's clean image (A: 0.2, B: 1.0) would move the Original if it were counted
    rows = by_model(main_table(RECORDS))
    assert rows["A"]["shadow/Accuracy/Original"] == pytest.approx(90.0)  # not (1+.8+.2)/3
    assert rows["B"]["reflection/Accuracy/Original"] == pytest.approx(70.0)  # c2 only, not c1/c3
    missing = [r for r in RECORDS if not (r["model"] == "A" and r["case_id"] == "c2" and r["severity"] == 0)]
    with pytest.raises(ValueError, match="c2"):
        main_table(missing)


def test_duplicate_clean_records_count_once_and_conflicts_raise():
    dup = RECORDS + [rec("A", "c2", 0, 0.8, 0.2, 0.2)]
    assert by_model(main_table(dup))["A"]["shadow/Accuracy/Original"] == pytest.approx(90.0)
    with pytest.raises(ValueError, match="second clean"):
        validate_records(RECORDS + [rec("A", "c2", 0, 0.1, 0.2, 0.2)])
    with pytest.raises(ValueError, match="duplicate perturbed"):
        validate_records(RECORDS + [rec("A", "c2", 2, 0.1, 0.2, 0.2, SR)])


@pytest.mark.parametrize("bad, match", [
    ({"severity": 7}, "severity"), ({"accuracy": -0.1}, "accuracy"), ({"case_id": None}, "case_id"),
    ({"illusion": None, "category": None}, "illusion"),
])
def test_bad_records_raise_naming_the_record(bad, match):
    r = {**rec("A", "c1", 1, 0.5, 0.1, 0.1, FS), **bad}
    with pytest.raises(ValueError, match=f"record 1: .*{match}"):
        validate_records([rec("A", "c1", 0, 1, 0, 0), r])


def test_category_filled_from_known_illusion():
    r = {**rec("A", "c1", 1, 0.5, 0.1, 0.1, FS), "category": None}
    assert validate_records([r])[0]["category"] == "shadow"


def test_type_table():
    rows = {(r["model"], r["illusion"]): r for r in type_table(RECORDS)}
    assert list(rows) == [("A", FS), ("A", SR), ("B", FS), ("B", SR)]  # paper order: shadow before reflection
    assert rows[("A", FS)]["category"] == "shadow"
    assert rows[("A", FS)]["Accuracy/Gap"] == pytest.approx(-50.0)
    assert rows[("B", SR)]["Accuracy/Perturbed"] == pytest.approx(90.0)
    assert rows[("B", SR)]["F1/Perturbed"] == pytest.approx(90.0)


def test_severity_table_original_per_severity():
    rows = {(r["model"], r["category"], r["severity"]): r for r in severity_table(RECORDS)}
    s1, s2 = rows[("A", "shadow", 1)], rows[("A", "shadow", 2)]
    assert s1["Accuracy"] == pytest.approx(50.0) and s1["F1"] == pytest.approx(70.0)
    assert s1["Accuracy/Original"] == pytest.approx(90.0) and s1["images"] == 2
    # severity 2 exists only for c1: its Original is c1's clean image alone
    assert s2["Accuracy"] == pytest.approx(20.0) and s2["F1"] == pytest.approx(f1(0.6, 0.8))
    assert s2["Accuracy/Original"] == pytest.approx(100.0) and s2["Accuracy/Gap"] == pytest.approx(-80.0)
    assert ("A", "reflection", 1) not in rows and ("A", "reflection", 2) in rows


def test_relative_table_and_mce_by_hand():
    rows = by_model(relative_table(RECORDS, baseline="A"))
    a, b = rows["A"], rows["B"]
    assert a["shadow/RelRobustness"] == pytest.approx(100 * 40 / 90)
    assert a["average/RelRobustness"] == pytest.approx((100 * 40 / 90 + 100 * 50 / 80) / 2)
    assert b["reflection/RelRobustness"] == pytest.approx(100 * 90 / 70)
    # per-type accuracies: A fence s1 50, s2 20, orig 90; A refl s2 50, orig 80
    #                      B fence s1 70, s2 10, orig 60; B refl s2 90, orig 70
    ce_fence = ((100 - 70) + (100 - 10)) / ((100 - 50) + (100 - 20))  # 120 / 130
    ce_refl = (100 - 90) / (100 - 50)  # 0.2
    assert b["mCE"] == pytest.approx(100 * (ce_fence + ce_refl) / 2)  # 56.15
    assert b["shadow/CE"] == pytest.approx(100 * ce_fence)
    assert b["reflection/CE"] == pytest.approx(100 * ce_refl)
    rce_fence = ((60 - 70) + (60 - 10)) / ((90 - 50) + (90 - 20))  # 40 / 110
    rce_refl = (70 - 90) / (80 - 50)  # -2/3
    assert b["relative_mCE"] == pytest.approx(100 * (rce_fence + rce_refl) / 2)  # -15.15
    assert a["mCE"] == pytest.approx(100.0) and a["relative_mCE"] == pytest.approx(100.0)


def test_relative_table_without_baseline_omits_ce_and_checks_name():
    row = relative_table(RECORDS, baseline=None)[0]
    assert not any("CE" in k for k in row)
    with pytest.raises(ValueError, match="baseline model 'Z'"):
        relative_table(RECORDS, baseline="Z")


def test_write_report_files(tmp_path):
    paths = write_report(RECORDS, tmp_path / "rep", baseline="A")
    for name in ("main", "per_type", "per_severity", "relative"):
        for fmt in ("md", "csv", "json"):
            assert paths[f"{name}_{fmt}"].is_file()
    saved = json.loads(paths["main_json"].read_text())
    assert saved[0]["shadow/Accuracy/Gap"] == pytest.approx(-50.0)
    text = paths["report"].read_text()
    assert text.index("per category") < text.index("Per illusion type") < text.index("Per severity") \
        < text.index("Relative")
    assert "-50.00" in text and "56.15" in text
    assert paths["accuracy_vs_severity"].stat().st_size > 5000
    assert paths["gap_heatmap"].stat().st_size > 5000
    assert "worst_cases" not in paths  # the fixture has no images
    assert not math.isnan(saved[1]["average/F1/Gap"])


def test_f1_count_columns_beside_the_papers_f1():
    """F1_count from the records' lane counts (TP/FP/FN summed over the group) in every table, beside F1.
    Shadow: c1 silent (0 of 2 lanes), c2 1 of 2 -> TP 1, FP 0, FN 3 -> 2 / 5 = 40 (the papers' F1 from
    FP 0, FN .75: 72.73); Original c1 2 of 2, c2 1 of 2 + 1 FP -> TP 3, FP 1, FN 1 -> 6 / 8 = 75."""
    def counted(case, sev, acc, fp, fn, counts, illusion=None):
        return {**rec("A", case, sev, acc, fp, fn, illusion), **dict(zip(("tp_count", "fp_count", "fn_count"),
                                                                         counts))}

    recs = [counted("c1", 0, 1.0, 0.0, 0.0, (2, 0, 0)), counted("c2", 0, 0.5, 0.5, 0.5, (1, 1, 1)),
            counted("c1", 1, 0.0, 0.0, 1.0, (0, 0, 2), FS), counted("c2", 1, 0.5, 0.0, 0.5, (1, 0, 1), FS)]
    row = main_table(recs)[0]
    assert row["shadow/F1_count/Perturbed"] == pytest.approx(40.0)
    assert row["shadow/F1_count/Original"] == pytest.approx(75.0)
    assert row["shadow/F1_count/Gap"] == pytest.approx(-35.0)
    assert row["average/F1_count/Gap"] == pytest.approx(-35.0)
    assert row["shadow/F1/Perturbed"] == pytest.approx(f1(0.0, 0.75))  # 72.73: the silent image reads well
    assert list(row)[1:10] == [f"shadow/{s}/{k}" for s in ("Accuracy", "F1", "F1_count")
                               for k in ("Perturbed", "Original", "Gap")]
    assert type_table(recs)[0]["F1_count/Perturbed"] == pytest.approx(40.0)
    sev = severity_table(recs)[0]
    assert sev["F1_count"] == pytest.approx(40.0) and sev["F1_count/Original"] == pytest.approx(75.0)
    from lanevil_train.report.summary import summary_rows

    rows = {r["images_kind"]: r for r in summary_rows(recs)}
    assert list(rows["original"])[3:9] == ["images", "Accuracy", "FP", "FN", "F1", "F1_count"]
    assert rows["original"]["F1_count"] == pytest.approx(75.0) and rows["perturbed"]["F1_count"] == pytest.approx(40.0)
    # the bootstrap (report/intervals.py) resamples it through its summed parts: the same value
    from lanevil_train.report.specs import F1_COUNT

    additive = F1_COUNT.aggregate.additive
    pert = [r for r in recs if r["severity"]]
    assert float(additive.combine(np.sum([additive.parts(r) for r in pert], axis=0))) == pytest.approx(40.0)
    # records written before the counts existed: no F1_count column, the other columns unchanged
    assert not any("F1_count" in k for k in main_table(RECORDS)[0])
    assert "F1_count" not in summary_rows(RECORDS)[0]
