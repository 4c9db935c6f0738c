"""The closed-loop report's time-resolved columns (means beside the paired difference from the clean twins, with
its bootstrap interval) on constructed records, older records without them, and the tracking plot."""

from __future__ import annotations

import json

import pytest

from lanevil_train.closed_loop.lane_keeper import BOUNDARY_AHEAD_M
from lanevil_train.report.closed_loop import (
    MISSING,
    asr_rows,
    paired_difference,
    tracking_plot,
    write_closed_loop_report,
)

TRACE = [{"t": t / 10, "s": float(t), "d": 0.0, "deviation": 0.01 * t, "heading": 0.0} for t in range(30)]


def _record(case, perturbed, **scores):
    return {"model": "M", "key": f"{case}/fence_shadow/{int(perturbed)}", "case_id": case, "seed": 1000001,
            "illusion": "fence_shadow", "category": "shadow", "severity": 3 if perturbed else 0,
            "perturbed": perturbed, "repeat": 0, "success": perturbed, "twin_success": perturbed,
            "max_deviation_m": 0.5 if perturbed else 0.1, "first_departure_s": None, "departures_per_km": 0.0,
            "collision": False, "entry_s": 0.5, "region_m": [5.0, 15.0], **scores}


RECORDS = [  # two cases, each a perturbed run and its clean twin
    _record("c1", True, tlc_entry_s=2.0, tlc_min_s=1.0, recovered=True, recovery_s=0.4, lock_share=0.2,
            lock_longest_s=0.3),
    _record("c1", False, tlc_entry_s=5.0, tlc_min_s=4.0, recovered=None, recovery_s=None, lock_share=0.0,
            lock_longest_s=0.0),
    _record("c2", True, tlc_entry_s=3.0, tlc_min_s=2.0, recovered=False, recovery_s=None, lock_share=0.4,
            lock_longest_s=0.5),
    _record("c2", False, tlc_entry_s=6.0, tlc_min_s=5.0, recovered=None, recovery_s=None, lock_share=0.0,
            lock_longest_s=0.0),
]


def test_time_columns_are_means_beside_the_paired_difference_from_the_twins():
    row = next(r for r in asr_rows(RECORDS, "category") if r["category"] == "shadow")
    assert row["TLC at entry (s)"] == 2.5 and row["min TLC (s)"] == 1.5
    # every pair differs by exactly -3 s: every replicate too
    assert row["TLC at entry Δ twin"] == "-3.00 [-3.00, -3.00]"
    # recovery: one run came back after 0.4 s, one did not (50 %); the twins never went out: no pair
    assert row["recovery (s)"] == 0.4 and row["not recovered (%)"] == 50.0
    assert row["recovery Δ twin"] == MISSING and row["not recovered Δ twin"] == MISSING
    # lock: 20 % and 40 % of the window against 0 %: +30 points; a replicate draws c1 twice (20), c2 twice (40) or
    # both (30): the 95 % interval spans [20, 40]
    assert row["lane lock (%)"] == 30.0 and row["lane lock Δ twin"] == "+30.0 [20.0, 40.0]"
    assert row["longest lock (s)"] == 0.4 and row["longest lock Δ twin"] == "+0.40 [0.30, 0.50]"


def test_the_paired_difference_pairs_by_case_illusion_and_repeat_only():
    perturbed = [r for r in RECORDS if r["perturbed"]]
    twins = [r for r in RECORDS if not r["perturbed"]]
    assert paired_difference(perturbed, twins[:1], "tlc_min_s") == pytest.approx((-3.0, -3.0, -3.0))  # c1 only
    assert paired_difference(perturbed, [{**twins[0], "repeat": 1}], "tlc_min_s") is None


def test_records_scored_before_the_time_columns_still_report_with_dashes(tmp_path):
    names = ("tlc_entry_s", "tlc_min_s", "recovered", "recovery_s", "lock_share", "lock_longest_s")
    old = [{k: v for k, v in r.items() if k not in names} for r in RECORDS]
    path = write_closed_loop_report(old, lambda record: TRACE, tmp_path, {"cases": 2})
    rows = json.loads((tmp_path / "asr_by_category.json").read_text())
    assert rows[0]["TLC at entry (s)"] == MISSING and rows[0]["lane lock Δ twin"] == MISSING
    assert "| — |" in path.read_text() and not (tmp_path / "closed_loop_tracking.png").exists()


def test_the_tracking_plot_draws_a_run_with_tracked_boundaries(tmp_path):
    trace = [{**step, "left_boundary_m": -1.6, "right_boundary_m": 1.6 + 0.01 * i} for i, step in enumerate(TRACE)]
    run = {**RECORDS[0], "image_size": [180, 320]}
    assert BOUNDARY_AHEAD_M == 10.0
    assert tracking_plot(run, trace, tmp_path / "closed_loop_tracking.png").is_file()
    assert tracking_plot(RECORDS[0], trace, tmp_path / "none.png") is None  # no image size: an older record
    assert tracking_plot(run, TRACE, tmp_path / "none.png") is None  # no tracker in the trace


def test_the_settings_line_shows_floats_short(tmp_path):
    speed_mph = 20.1168 / 0.44704  # 45 mph back from m/s: 45.00000000000001
    path = write_closed_loop_report(RECORDS, lambda record: TRACE, tmp_path, {"cases": 2, "speed_mph": speed_mph})
    assert "Settings: cases=2, speed_mph=45.\n" in path.read_text()  # the sentence ends after 45
