"""report/defenses.py: per-defense scores and gains over `none` on constructed records with known numbers."""

from __future__ import annotations

import cv2
import pytest

from lanevil_train.report.defenses import (
    best_defense,
    check_comparable,
    defense_gain,
    defense_scores,
    gain_pivot,
    write_defense_report,
)
from lanevil_train.report.specs import LANE_SPEC


def _records(model: str, clean: float, shadow: tuple[float, float], vehicle: float, shadow_fn: float = 0.0) -> list:
    """Two cases: a clean original each, a rail_shadow (accuracies `shadow`, fn `shadow_fn`) and a vehicle image."""
    recs = []
    for i, case in enumerate(("c1", "c2")):
        recs.append({"model": model, "dataset": "sim", "case_id": case, "severity": 0, "illusion": None,
                     "accuracy": clean, "fp": 0.0, "fn": 0.0})
        recs.append({"model": model, "dataset": "sim", "case_id": case, "severity": 3, "illusion": "rail_shadow",
                     "category": "shadow", "accuracy": shadow[i], "fp": 0.0, "fn": shadow_fn})
        recs.append({"model": model, "dataset": "sim", "case_id": case, "severity": 3, "illusion": "vehicle",
                     "accuracy": vehicle, "fp": 0.0, "fn": 0.0})  # category filled in from the illusion
    return recs


# none: clean 90, shadow 50 (fn 0.5: recall 2/3, F1 80), vehicle 70, average 60
# aam++: clean 85, shadow 70 (F1 100), vehicle 75, average 72.5
# pgd: clean 90, shadow 45, vehicle 70, average 57.5
RECORDS = {
    "none": _records("laneatt-resnet18", 0.9, (0.6, 0.4), 0.7, shadow_fn=0.5),
    "aam++": _records("laneatt-resnet18+aam++", 0.85, (0.8, 0.6), 0.75),
    "pgd": _records("laneatt-resnet18+pgd", 0.9, (0.5, 0.4), 0.7),
}


def test_scores_per_defense_are_perturbed_per_category_average_and_clean():
    rows = defense_scores(RECORDS)
    assert [r["defense"] for r in rows] == ["none", "aam++", "pgd"]
    none, aam, pgd = rows
    assert none["model"] == "laneatt-resnet18" and aam["model"] == "laneatt-resnet18+aam++"
    assert none["images"] == 4
    assert none["shadow/Accuracy"] == pytest.approx(50.0)
    assert none["shadow/F1"] == pytest.approx(80.0)
    assert none["traffic_obstruction/Accuracy"] == pytest.approx(70.0)
    assert none["average/Accuracy"] == pytest.approx(60.0)
    assert none["average/F1"] == pytest.approx(90.0)
    assert none["original/Accuracy"] == pytest.approx(90.0) and none["original/F1"] == pytest.approx(100.0)
    assert aam["shadow/Accuracy"] == pytest.approx(70.0) and aam["average/Accuracy"] == pytest.approx(72.5)
    assert aam["original/Accuracy"] == pytest.approx(85.0)
    assert pgd["average/Accuracy"] == pytest.approx(57.5)


def test_gain_is_defense_minus_none_per_category_average_and_original():
    gains = defense_gain(defense_scores(RECORDS))
    table = {(r["defense"], r["category"]): r for r in gains}
    assert list(table) == [(d, c) for d in ("aam++", "pgd")
                           for c in ("traffic_obstruction", "shadow", "average", "original")]  # paper order
    expected_acc = {("aam++", "traffic_obstruction"): 5.0, ("aam++", "shadow"): 20.0, ("aam++", "average"): 12.5,
                    ("aam++", "original"): -5.0, ("pgd", "traffic_obstruction"): 0.0, ("pgd", "shadow"): -5.0,
                    ("pgd", "average"): -2.5, ("pgd", "original"): 0.0}
    for key, gain in expected_acc.items():
        assert table[key]["Accuracy/gain"] == pytest.approx(gain), key
    assert table[("aam++", "shadow")]["Accuracy"] == pytest.approx(70.0)
    assert table[("aam++", "shadow")]["Accuracy/none"] == pytest.approx(50.0)
    assert table[("aam++", "shadow")]["F1/gain"] == pytest.approx(20.0)  # 100 - 80
    assert table[("aam++", "average")]["F1/gain"] == pytest.approx(10.0)  # 100 - 90
    assert table[("pgd", "shadow")]["F1/gain"] == pytest.approx(20.0)


def test_pivot_and_best_defense():
    gains = defense_gain(defense_scores(RECORDS))
    pivot = gain_pivot(gains)
    assert [list(r.values()) for r in pivot] == [pytest.approx(["aam++", 5.0, 20.0, 12.5, -5.0]),
                                                 pytest.approx(["pgd", 0.0, -5.0, -2.5, 0.0])]
    assert list(pivot[0]) == ["defense", "traffic_obstruction", "shadow", "average", "original"]
    assert best_defense(defense_scores(RECORDS), LANE_SPEC) == ("aam++", pytest.approx(72.5))


def test_the_reference_must_be_there_and_scored_on_the_same_images():
    with pytest.raises(ValueError, match="reference defense 'none' is missing"):
        defense_scores({"aam++": RECORDS["aam++"]})
    fewer = [r for r in RECORDS["pgd"] if not (r["case_id"] == "c2" and r.get("illusion") == "vehicle")]
    with pytest.raises(ValueError, match=r"defense 'pgd' was scored on different items.*0 item\(s\) only in 'pgd', "
                                         r"1 only in 'none'"):
        check_comparable({"none": RECORDS["none"], "pgd": fewer})
    mixed = RECORDS["pgd"][:3] + [dict(r, model="other") for r in RECORDS["pgd"][3:]]
    with pytest.raises(ValueError, match="defense 'pgd': expected the records of one model"):
        check_comparable({"none": RECORDS["none"], "pgd": mixed})
    clean_only = [r for r in RECORDS["pgd"] if r["severity"] == 0]
    with pytest.raises(ValueError, match="defense 'pgd': no perturbed"):
        check_comparable({"none": RECORDS["none"], "pgd": clean_only})
    with pytest.raises(ValueError, match="defense 'pgd': record 0: missing"):
        check_comparable({"none": RECORDS["none"], "pgd": [{"model": "x"}]})


def test_report_files(tmp_path):
    scores = defense_scores(RECORDS)
    gains = defense_gain(scores)
    paths = write_defense_report(scores, gains, tmp_path, LANE_SPEC, runs={"none": "/r/none", "aam++": "/r/aam++"})
    for name in ("defense_gain", "defense_scores"):
        for ext in ("md", "csv", "json"):
            assert (tmp_path / f"{name}.{ext}").is_file()
    assert len((tmp_path / "defense_gain.csv").read_text().splitlines()) == 1 + 8
    image = cv2.imread(str(paths["plot"]))
    assert image is not None and image.shape[0] > 100 and image.shape[1] > 200
    report = (tmp_path / "compare.md").read_text()
    assert "| aam++ | 5.00 | 20.00 | 12.50 | -5.00 |" in report
    assert "**aam++** (72.50%)" in report
    assert "![defense gain](defense_gain.png)" in report and "| aam++ | /r/aam++ |" in report
