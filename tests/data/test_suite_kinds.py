"""The corruption and combined-illusion suites of images (perturbations.py), on the fly and on disk."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lanevil_train.corruptions import CORRUPTION_NAMES, CORRUPTIONS
from lanevil_train.data.illusion_set import Plan, build_illusion_set, synthetic_cases
from lanevil_train.data.suites import IllusionSetDataset, SyntheticIllusionSuite
from lanevil_train.illusions import ILLUSIONS
from lanevil_train.perturbations import case_perturbations, combined_choice, get_perturbation, suite_names
from lanevil_train.report.combined import combined_table
from lanevil_train.report.specs import record_set
from lanevil_train.taxonomy import CATEGORIES, ILLUSION_CATEGORY, PAIR_CATEGORIES

SIZE = (90, 160)


def test_combined_cases_hold_one_illusion_per_category_and_every_pair_of_them():
    singles, pairs = combined_choice(1000000, suite_names("combined"))
    assert [ILLUSION_CATEGORY[n] for n in singles] == list(CATEGORIES)
    assert [get_perturbation(p).category for p in pairs] == list(PAIR_CATEGORIES)
    assert all(p.split("+")[0] in singles and p.split("+")[1] in singles for p in pairs)
    # the draw depends on the case seed and only on allowed names
    draws = {combined_choice(seed, suite_names("combined"))[0] for seed in range(30)}
    assert len(draws) > 5
    only = ("rail_shadow", "vehicle", "road_crack")
    singles, pairs = combined_choice(7, only)
    assert set(singles) == set(only) and len(pairs) == 3


def test_combined_suite_items_are_the_second_illusion_drawn_over_the_first():
    suite = SyntheticIllusionSuite(1, 1000000, SIZE, "all", (3,), kind="combined")
    items = [suite[i] for i in range(len(suite))]
    assert len(items) == 1 + 4 + 6  # original, 4 singles, 6 pairs
    by_name = {item["meta"]["illusion"]: item for item in items}
    clean = by_name[None]["image"]
    first, second = next(n for n in by_name if n and "+" in n).split("+")
    pair = by_name[f"{first}+{second}"]
    assert pair["meta"]["category"] == f"{ILLUSION_CATEGORY[first]}+{ILLUSION_CATEGORY[second]}"
    from lanevil_train.data.illusion_set import case_source

    _, _, ctx = case_source(suite.items[0][0], suite.plan)
    seed = pair["meta"]["seed"]
    expected = ILLUSIONS[second](ILLUSIONS[first](clean, ctx, 3, seed), ctx, 3, seed)
    assert np.array_equal(pair["image"], expected)
    assert np.array_equal(by_name[first]["image"], ILLUSIONS[first](clean, ctx, 3, seed))  # the same draw alone
    for other in (clean, by_name[first]["image"], by_name[second]["image"]):
        assert np.abs(pair["image"].astype(int) - other.astype(int)).sum() > 0
    assert all(np.array_equal(item["lanes"][0], items[0]["lanes"][0]) for item in items)  # lanes never change


def test_corruption_suite_applies_every_corruption_to_the_clean_scene():
    suite = SyntheticIllusionSuite(1, 1000000, SIZE, "all", (2, 5), kind="corruptions")
    assert len(suite) == 1 + len(CORRUPTION_NAMES) * 2
    clean = suite[0]["image"]
    seen = {}
    for i in range(1, len(suite)):
        item = suite[i]
        meta = item["meta"]
        assert meta["category"] == CORRUPTIONS[meta["illusion"]].category
        expected = CORRUPTIONS[meta["illusion"]](clean, None, meta["severity"], meta["seed"])
        assert np.array_equal(item["image"], expected)
        seen[meta["illusion"], meta["severity"]] = np.abs(item["image"].astype(float) - clean).mean()
    assert all(seen[name, 5] > seen[name, 2] > 0 for name in CORRUPTION_NAMES)
    with pytest.raises(ValueError, match=r"illusions\[0\]: unknown corruption 'rail_shadow'"):
        SyntheticIllusionSuite(1, 0, SIZE, ["rail_shadow"], (1,), kind="corruptions")


@pytest.mark.parametrize("kind, names, per_case", [("corruptions", ["fog", "jpeg"], 2), ("combined", "all", 10)])
def test_built_sets_of_each_kind_read_back_as_generated(tmp_path, kind, names, per_case):
    plan = Plan(illusions=suite_names(kind, names), severities=(4,), size=SIZE, kind=kind)
    cases = synthetic_cases(2, 1000000)
    build_illusion_set(cases, plan, tmp_path, progress="none")
    assert json.loads((tmp_path / "build.json").read_text())["plan"]["kind"] == kind
    on_disk = IllusionSetDataset(tmp_path)
    fly = SyntheticIllusionSuite(2, 1000000, SIZE, names, (4,), kind=kind)
    assert len(on_disk) == len(fly) == 2 * (1 + per_case)
    for i in range(len(fly)):
        a, b = on_disk[i], fly[i]
        assert {k: a["meta"][k] for k in ("case_id", "illusion", "category", "severity")} == \
            {k: b["meta"][k] for k in ("case_id", "illusion", "category", "severity")}
        assert np.array_equal(a["image"], b["image"])  # PNG is lossless
    # another kind into the same folder is refused, naming the plan
    with pytest.raises(ValueError, match="another plan"):
        build_illusion_set(cases, Plan(illusions=tuple(ILLUSIONS), severities=(4,), size=SIZE), tmp_path,
                           progress="none")


def test_an_illusion_set_records_no_kind_so_older_sets_resume():
    from lanevil_train.data.illusion_set import plan_record

    assert "kind" not in plan_record(Plan(illusions=("rail_shadow",)))
    assert plan_record(Plan(illusions=("fog",), kind="corruptions"))["kind"] == "corruptions"


def test_perturbation_names_are_checked():
    assert get_perturbation("vehicle+rail_shadow").category == "traffic_obstruction+shadow"
    with pytest.raises(ValueError, match="both illusions are shadow"):
        get_perturbation("rail_shadow+fence_shadow")
    with pytest.raises(ValueError, match="unknown perturbation 'smoke'"):
        get_perturbation("smoke")
    with pytest.raises(ValueError, match="pairs illusions of two categories"):
        suite_names("combined", ["rail_shadow", "fence_shadow"])
    with pytest.raises(ValueError, match="suite kind"):
        case_perturbations("weather", ["fog"], 0)


def _record(case, illusion, severity, accuracy, category=None):
    return {"model": "m", "dataset": "sim", "case_id": case, "severity": severity, "illusion": illusion,
            "category": category, "accuracy": accuracy, "fp": 0.0, "fn": 0.0}


def test_combined_table_reads_each_pair_against_the_original_and_its_single_illusions():
    recs = []
    for case in ("c0", "c1"):
        recs += [_record(case, None, 0, 0.9), _record(case, "road_crack", 3, 0.8), _record(case, "vehicle", 3, 0.7),
                 _record(case, "road_crack+vehicle", 3, 0.6, "road_damage+traffic_obstruction")]
    rows = combined_table(record_set(recs))
    assert len(rows) == 1
    row = rows[0]
    assert row["pair"] == "RD+TO" and row["images"] == 2
    assert row["Accuracy/Original"] == pytest.approx(90.0) and row["Accuracy/Perturbed"] == pytest.approx(60.0)
    assert row["Accuracy/Gap"] == pytest.approx(-30.0)
    assert row["Accuracy/first alone"] == pytest.approx(80.0) and row["Accuracy/second alone"] == pytest.approx(70.0)
    assert row["Accuracy/Gap vs first"] == pytest.approx(-20.0) and \
        row["Accuracy/Gap vs second"] == pytest.approx(-10.0)
