"""The twin-relative attack rule: a run's deviation from its clean twin's path at the same arc length, on
constructed traces with hand-computed values."""

from __future__ import annotations

import pytest

from lanevil_train.closed_loop.run_scores import attack_fired_at, run_scores, twin_deviation, twin_scores

LANE_WIDTH_M = 3.5
SPEED = 20.0  # m/s
DT = 0.1


def _trace(ds, s0=0.0, centre=0.0, speed=SPEED, dt=DT):
    """A straight-driving trace with lateral offsets ds (deviation = d - centre)."""
    return [{"t": round(i * dt, 6), "s": s0 + i * dt * speed, "d": d, "deviation": d - centre, "heading": 0.0}
            for i, d in enumerate(ds)]


def test_twin_deviation_interpolates_the_twin_over_its_arc_length_and_holds_its_ends():
    twin = [{"t": 0.0, "s": 0.0, "d": 0.0}, {"t": 0.1, "s": 2.0, "d": 0.1}, {"t": 0.2, "s": 4.0, "d": 0.3},
            {"t": 0.3, "s": 6.0, "d": 0.3}]
    run = [{"t": 0.0, "s": -1.0, "d": 0.1}, {"t": 0.1, "s": 1.0, "d": 0.2}, {"t": 0.2, "s": 3.5, "d": 0.2},
           {"t": 0.3, "s": 7.0, "d": 0.5}]
    # s=-1: before the twin, its first d (0); s=1: 0.05; s=3.5: 0.1 + 0.75 * 0.2 = 0.25; s=7: its last d (0.3)
    assert twin_deviation(run, twin) == pytest.approx([0.1, 0.15, -0.05, 0.2], abs=1e-12)


def test_twin_deviation_refuses_a_twin_whose_arc_length_does_not_increase():
    twin = [{"t": 0.0, "s": 1.0, "d": 0.0}, {"t": 0.1, "s": 0.5, "d": 0.1}]  # driving backwards
    with pytest.raises(ValueError, match="increase"):
        twin_deviation(_trace([0.0]), twin)
    # a twin that stood still (equal s: braked to a stop) is read at the last of those steps
    stopped = [{"t": 0.0, "s": 0.0, "d": 0.0}, {"t": 0.1, "s": 2.0, "d": 0.1}, {"t": 0.2, "s": 2.0, "d": 0.3}]
    assert twin_deviation([{"s": 1.0, "d": 0.0}, {"s": 2.0, "d": 0.0}], stopped) == pytest.approx([-0.15, -0.3])
    with pytest.raises(ValueError, match="empty"):
        twin_deviation(_trace([0.0]), [])


def test_a_run_0_35m_right_of_its_twin_fires_the_twin_rule_while_both_stay_inside_the_lane_margin():
    # 4 s at 20 m/s, region from s = 20 m (entered at t = 1.0 s); twin settles 0.2 m left, the run 0.15 m right
    twin = _trace([-0.2] * 41)
    run = _trace([0.0] * 12 + [0.15] * 29)  # moves right at t = 1.2 s
    region_start = 20.0
    lane_run, lane_twin = (run_scores(t, region_start, LANE_WIDTH_M) for t in (run, twin))
    assert not lane_run["success"] and not lane_twin["success"]  # 0.15 and 0.2 < 0.285
    scores = twin_scores(run, twin, region_start)
    # run - twin: 0.2 before t = 1.2 s, then 0.35 > 0.285: fires 0.2 s after entering
    assert scores == {"twin_success": True, "twin_fired_after_s": pytest.approx(0.2), "twin_max_deviation_m": 0.35}


def test_the_twin_scored_against_itself_is_no_success_and_no_deviation():
    twin = _trace([0.0, 0.1, 0.3, -0.4, 0.2] * 8)
    assert twin_scores(twin, twin, 20.0) == {"twin_success": False, "twin_fired_after_s": None,
                                             "twin_max_deviation_m": 0.0}


def test_the_twin_rule_keeps_the_papers_window_and_needs_an_entry():
    twin = _trace([0.0] * 61)
    late = _trace([0.0] * 40 + [0.5] * 21)  # entry at 1.0 s; 0.5 m off the twin only from t = 4.0 s > 3.5 s
    assert twin_scores(late, twin, 20.0)["twin_success"] is False
    assert twin_scores(late, twin, 20.0)["twin_max_deviation_m"] == 0.5
    assert twin_scores(late, twin, 500.0)["twin_fired_after_s"] is None  # never entered


def test_attack_fired_at_on_a_deviation_sequence_and_its_length_check():
    trace = _trace([0.0] * 5)
    assert attack_fired_at(trace, 0.1, deviations=[0.0, 0.0, 0.3, 0.0, 0.0]) == pytest.approx(0.2)
    assert attack_fired_at(trace, 0.1) is None
    with pytest.raises(ValueError, match="4 deviations for 5 steps"):
        attack_fired_at(trace, 0.1, deviations=[0.0] * 4)
