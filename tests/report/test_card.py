"""Robustness cards (report/card.py): built from constructed records, checked against hand-computed numbers and
the shipped JSON Schema; a card with a missing field is refused naming the file and the field."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
from jsonschema import Draft202012Validator

from lanevil_train.report.card import (
    SCHEMA_FILE,
    CardError,
    build_card,
    estimate,
    read_card,
    schema,
    write_card,
)
from lanevil_train.report.robustness import main_table, relative_table

FS, SR = "fence_shadow", "sunlight_reflection"
CASES = ("sim-0000011-f0", "sim-0000012-f0", "sim-0000013-f0")


def rec(model, case, severity, accuracy, illusion=None):
    category = {FS: "shadow", SR: "reflection", None: None}[illusion]
    return {"model": model, "dataset": "synthetic-illusions", "case_id": case, "severity": severity,
            "illusion": illusion, "category": category, "accuracy": accuracy, "fp": 0.0, "fn": 0.0,
            "key": f"{case}/{illusion}/{severity}"}


def records(model, clean, fs1, fs2, sr1):
    """Per case (s1, s2, s3): clean, fence_shadow at severities 1 and 2; sunlight_reflection on s1 and s2 only."""
    out = []
    for i, case in enumerate(CASES):
        out += [rec(model, case, 0, clean[i]), rec(model, case, 1, fs1[i], FS), rec(model, case, 2, fs2[i], FS)]
        if i < len(sr1):
            out.append(rec(model, case, 1, sr1[i], SR))
    return out


B = records("b", clean=(1.0, 0.8, 0.6), fs1=(0.6, 0.4, 0.5), fs2=(0.2, 0.3, 0.4), sr1=(0.9, 0.7))
A = records("a", clean=(0.9, 0.9, 0.9), fs1=(0.5, 0.5, 0.5), fs2=(0.3, 0.3, 0.3), sr1=(0.8, 0.6))


@pytest.fixture(scope="module")
def card():
    return build_card(B + A, "b", identity={"family": "laneatt", "backbone": "resnet18", "checkpoint": "x.ckpt",
                                            "checkpoint_sha256": "0" * 64, "training_data": "synthetic"},
                      reference="a", replicates=200, created="2026-01-01T00:00:00+00:00",
                      run={"dir": "/runs/b", "files": ["per_image.jsonl"]})


def test_the_card_validates_against_the_shipped_schema(card):
    assert not list(Draft202012Validator(json.loads(SCHEMA_FILE.read_text())).iter_errors(card))
    assert card["schema_version"] == 1 and card["model"]["label"] == "b"
    assert card["model"]["family"] == "laneatt" and card["model"]["training_data"] == "synthetic"


def test_the_numbers_are_the_hand_computed_ones(card):
    shadow = card["results"]["categories"]["shadow"]
    # Perturbed: the 6 shadow images (0.6 + 0.4 + 0.5 + 0.2 + 0.3 + 0.4) / 6; Original: the 3 cases' clean images
    assert [shadow["scores"]["Accuracy"][k]["value"] for k in ("Perturbed", "Original", "Gap", "RelRobustness")] \
        == pytest.approx([40.0, 80.0, -40.0, 50.0])
    assert (shadow["n_perturbed"], shadow["n_original"], shadow["n_cases"]) == (6, 3, 3)
    # reflection: s1 and s2 only: Perturbed (0.9 + 0.7) / 2, Original (1.0 + 0.8) / 2
    reflection = card["results"]["categories"]["reflection"]
    assert [reflection["scores"]["Accuracy"][k]["value"] for k in ("Perturbed", "Original", "Gap")] \
        == pytest.approx([80.0, 90.0, -10.0])
    assert reflection["scores"]["Accuracy"]["RelRobustness"]["value"] == pytest.approx(100 * 80 / 90, abs=1e-5)
    assert (reflection["n_perturbed"], reflection["n_original"], reflection["n_cases"]) == (2, 2, 2)
    # overall: the mean of the category values, as main.md's average
    overall = card["results"]["overall"]
    assert [overall["scores"]["Accuracy"][k]["value"] for k in ("Perturbed", "Original", "Gap")] \
        == pytest.approx([60.0, 85.0, -25.0])
    assert overall["scores"]["Accuracy"]["RelRobustness"]["value"] == pytest.approx((50 + 100 * 80 / 90) / 2,
                                                                                    abs=1e-5)
    assert (overall["n_perturbed"], overall["n_original"], overall["n_cases"]) == (8, 3, 3)
    main = main_table(B)[0]
    assert overall["scores"]["Accuracy"]["Perturbed"]["value"] == pytest.approx(main["average/Accuracy/Perturbed"])
    for kind in ("Perturbed", "Original", "Gap", "RelRobustness"):  # every value inside its interval
        est = shadow["scores"]["Accuracy"][kind]
        assert est["low"] <= est["value"] <= est["high"]
    assert shadow["scores"]["Accuracy"]["Perturbed"]["low"] < shadow["scores"]["Accuracy"]["Perturbed"]["high"]


def test_the_mce_against_the_named_reference_is_imagenet_cs(card):
    # errors E = 100 - Accuracy. fence_shadow: b (50 + 70) / a (50 + 70) = 1; sunlight_reflection: b 20 / a 30.
    # relative: fence_shadow ((50-20) + (70-20)) / ((50-10) + (70-10)) = 0.8; sunlight_reflection (20-10)/(30-10)
    mce = card["mce"]
    assert mce["reference"] == "a" and mce["types"] == 2 and mce["n_cases"] == 3
    assert mce["mCE"]["value"] == pytest.approx(100 * (1 + 2 / 3) / 2, abs=1e-5)
    assert mce["relative_mCE"]["value"] == pytest.approx(100 * (0.8 + 0.5) / 2)
    assert mce["categories"]["shadow"]["value"] == pytest.approx(100.0)
    assert mce["categories"]["reflection"]["value"] == pytest.approx(100 * 2 / 3, abs=1e-5)
    row = next(r for r in relative_table(B + A, "a") if r["model"] == "b")
    assert mce["mCE"]["value"] == pytest.approx(row["mCE"], abs=1e-5)
    assert mce["mCE"]["low"] <= mce["mCE"]["value"] <= mce["mCE"]["high"]


def test_the_suite_identity(card):
    suite = card["suite"]
    assert (suite["kind"], suite["cases"], suite["seeds"]) == ("illusions", 3, [11, 12, 13])
    assert suite["severities"] == [1, 2]
    assert suite["illusions"] == [FS, SR] and suite["categories"] == ["shadow", "reflection"]
    # the same suite scored by another model: the same hash; one case fewer: another
    same = build_card(A, replicates=10)["suite"]["plan_hash"]
    fewer = build_card([r for r in A if r["case_id"] != CASES[2]], replicates=10)["suite"]["plan_hash"]
    assert suite["plan_hash"] == same != fewer


def test_a_card_reads_back_equal_and_a_missing_field_is_named(card, tmp_path):
    path = write_card(tmp_path / "card.json", card)
    assert read_card(path) == card
    broken = copy.deepcopy(card)
    del broken["suite"]["plan_hash"]
    path.write_text(json.dumps(broken))
    with pytest.raises(CardError, match=r"^card\.json: suite\.plan_hash: required field missing$"):
        read_card(path)
    broken = copy.deepcopy(card)
    broken["results"]["categories"]["shadow"]["scores"]["Accuracy"]["Gap"]["value"] = "big"
    with pytest.raises(CardError, match=r"new\.json: results\.categories\.shadow\.scores\.Accuracy\.Gap\.value: "):
        write_card(tmp_path / "new.json", broken)
    assert not (tmp_path / "new.json").exists()  # refused before anything is written
    with pytest.raises(CardError, match="schema_version: 2 is not the version"):
        write_card(tmp_path / "new.json", {**card, "schema_version": 2})


def test_closed_loop_rates_come_with_wilson_intervals():
    runs = [{"model": "b", "perturbed": True, "category": "shadow", "success": i < 3, "collision": i == 0}
            for i in range(4)] + [{"model": "b", "perturbed": False, "category": "shadow", "success": False}]
    loop = build_card(B, replicates=10, closed_loop=runs)["closed_loop"]
    assert loop["overall"]["runs"] == 4 and loop["overall"]["clean_runs"] == 1
    assert loop["overall"]["asr"]["value"] == 75.0 and loop["categories"]["shadow"]["collisions"]["value"] == 25.0
    # Wilson 95 %: 3 of 4 runs, z = 1.96: centre (0.75 + z²/8) / (1 + z²/4), half z sqrt(0.75 * 0.25 / 4 + z²/64) / ...
    z = 1.959963984540054
    centre, half = (0.75 + z * z / 8) / (1 + z * z / 4), z * (0.75 * 0.25 / 4 + z * z / 64) ** 0.5 / (1 + z * z / 4)
    assert [loop["overall"]["asr"]["low"], loop["overall"]["asr"]["high"]] == pytest.approx(
        [100 * (centre - half), 100 * (centre + half)], abs=1e-5)
    assert build_card(B, replicates=10)["closed_loop"] is None
    assert estimate(build_card(B, replicates=10, closed_loop=runs), "ASR") == loop["overall"]["asr"]


def test_a_clean_only_run_has_no_card():
    with pytest.raises(ValueError, match="no perturbed records"):
        build_card([r for r in B if r["severity"] == 0])


def test_the_wheel_ships_the_schema():
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    pyproject = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    data = pyproject["tool"]["setuptools"]["package-data"]["lanevil_train.report"]
    assert any(SCHEMA_FILE.match(pattern) for pattern in data)
    assert any(dep.startswith("jsonschema") for dep in pyproject["project"]["dependencies"])
    assert schema()["properties"]["schema_version"]["const"] == 1
