"""Closed-loop differences between groups of models (<group>@<seed> labels: a defense against none over seeds), on
constructed records whose differences and bootstrap intervals are known."""

from __future__ import annotations

import json

from lanevil_train.report.closed_loop import write_closed_loop_report
from lanevil_train.report.closed_loop_groups import group_difference_rows, group_of, groups_of

TRACE = [{"t": t / 10, "s": float(t), "d": 0.0, "deviation": 0.01 * t, "heading": 0.0} for t in range(30)]

# the reference's successes per (seed, case); the defense never goes out
NONE_SUCCESS = {(0, "c1"): True, (0, "c2"): True, (1, "c1"): True, (1, "c2"): False}


def _record(model, case, perturbed, success, tlc_min_s, lock_share, illusion="fence_shadow", category="shadow"):
    return {"model": model, "key": f"{model}|{case}/{illusion}/{3 if perturbed else 0}/0", "case_id": case,
            "seed": 1000000, "illusion": illusion, "category": category, "severity": 3 if perturbed else 0,
            "perturbed": perturbed, "repeat": 0, "success": success, "twin_success": success,
            "max_deviation_m": 0.4 if success else 0.1, "first_departure_s": None, "departures_per_km": 0.0,
            "collision": False, "entry_s": 0.5, "region_m": [5.0, 15.0], "tlc_min_s": tlc_min_s,
            "lock_share": lock_share}


def _records():
    records = []
    for seed in (0, 1):
        for case in ("c1", "c2"):
            records.append(_record(f"none@{seed}", case, True, NONE_SUCCESS[seed, case], 1.0, 0.0))
            records.append(_record(f"none@{seed}", case, False, False, 5.0, 0.0))
            lock = 0.1 if case == "c1" else 0.3
            records.append(_record(f"aam++@{seed}", case, True, False, 2.0 + seed, lock))
            records.append(_record(f"aam++@{seed}", case, False, False, 5.0, 0.0))
    # a seed the reference lacks is left out of every pair
    records.append(_record("aam++@7", "c1", True, True, 0.1, 0.9))
    return records


def test_labels_name_a_group_and_a_seed():
    assert group_of("aam++@3") == ("aam++", 3) and group_of("my@model@12") == ("my@model", 12)
    assert group_of("laneatt") is None and group_of("none@x") is None
    assert groups_of(_records()) == {"none": {0: "none@0", 1: "none@1"},
                                     "aam++": {0: "aam++@0", 1: "aam++@1", 7: "aam++@7"}}
    assert groups_of([{**r, "model": "laneatt"} for r in _records()]) is None  # a label without a seed
    assert groups_of([r for r in _records() if r["model"].startswith("none")]) is None  # one group


def test_the_differences_pair_runs_of_one_seed_case_and_illusion():
    rows = group_difference_rows(_records())
    assert [(r["group"], r["vs"], r["category"]) for r in rows] == [("aam++", "none", "shadow"),
                                                                    ("aam++", "none", "all")]
    row = rows[-1]
    assert row["seeds"] == 2 and row["runs"] == 4  # aam++@7 has no partner
    # ASR per seed: none 100 % and 50 % (75 ± 35.4); aam++ 0 % on both
    assert row["none ASR (%)"] == "75.0 ± 35.4" and row["aam++ ASR (%)"] == "0.0 ± 0.0"
    # the pairs differ by -1, -1, -1, 0: mean -75 points; a replicate of 4 units draws the 0 at least 3 times with
    # probability 5.1 % (-25 or more) and never draws it with 31.6 % (-100): the 95 % interval is [-100, -25]
    assert row["ASR Δ (pts)"] == "-75.0 [-100.0, -25.0]" and row["excludes 0"] == "yes"
    assert row["max dev Δ (m)"] == "-0.225 [-0.300, -0.075]"
    # min TLC: +1 s (seed 0) and +2 s (seed 1) per pair: mean +1.5, every replicate within [1, 2]
    low, high = (float(v) for v in row["min TLC Δ (s)"].split("[")[1].rstrip("]").split(","))
    assert row["min TLC Δ (s)"].startswith("+1.50 ") and 1.0 <= low < 1.5 < high <= 2.0
    # lock: +10 points (c1) and +30 (c2): mean +20
    assert row["lane lock Δ (pts)"].startswith("+20.00 [")


def test_a_difference_whose_interval_spans_zero_does_not_exclude_it():
    records = [r for r in _records() if r["model"] != "aam++@7"]
    flipped = [{**r, "success": not r["success"]} if r["model"] == "aam++@1" and r["case_id"] == "c2"
               and r["perturbed"] else r for r in records]  # seed 1, c2: the defense goes out, none does not
    row = group_difference_rows(flipped)[-1]
    assert row["ASR Δ (pts)"].startswith("-50.0 [") and row["excludes 0"] == "no"


def test_the_report_writes_the_group_table(tmp_path):
    path = write_closed_loop_report(_records(), lambda record: TRACE, tmp_path, {"cases": 2})
    rows = json.loads((tmp_path / "group_difference.json").read_text())
    assert rows[-1]["ASR Δ (pts)"] == "-75.0 [-100.0, -25.0]"
    assert "## Groups compared" in path.read_text()
    plain = tmp_path / "plain"
    write_closed_loop_report([{**r, "model": "M"} for r in _records()[:4]], lambda record: TRACE, plain,
                             {"cases": 2})
    assert not (plain / "group_difference.json").exists()
