"""report/intervals.py: seed spread and paired-bootstrap intervals of gains, on constructed records with known
answers."""

from __future__ import annotations

import numpy as np
import pytest

from lanevil_train.report.intervals import SeedRuns, gain_rows, gain_text, seed_rows


def _records(model: str, shadow: list[float], clean: list[float] | None = None, fn: float = 0.0) -> list[dict]:
    """One case per value: a clean original (accuracy `clean[i]`, default 0.9) and a rail_shadow image (`shadow[i]`)."""
    clean = clean or [0.9] * len(shadow)
    recs = []
    for i, (acc, orig) in enumerate(zip(shadow, clean)):
        case = f"c{i}"
        recs.append({"model": model, "dataset": "sim", "case_id": case, "severity": 0, "illusion": None,
                     "accuracy": orig, "fp": 0.0, "fn": 0.0})
        recs.append({"model": model, "dataset": "sim", "case_id": case, "severity": 3, "illusion": "rail_shadow",
                     "accuracy": acc, "fp": 0.0, "fn": fn})
    return recs


RNG = np.random.default_rng(3)
NOISY = [list(RNG.uniform(0.3, 0.9, size=40)) for _ in range(3)]  # three seeds' per-case accuracies


def _gain(rows, category="shadow"):
    return next(r for r in rows if r["category"] == category)


def test_a_gain_of_exactly_zero_is_not_distinguishable():
    # the defense scores exactly what `none` scores on every case, seed by seed: gain 0, interval [0, 0]
    runs = SeedRuns({"none": {s: _records("m", NOISY[s]) for s in range(3)},
                     "same": {s: _records("m+same", NOISY[s]) for s in range(3)}})
    row = _gain(gain_rows(runs, "none", replicates=400))
    assert row["Accuracy/gain"] == 0.0 and row["Accuracy/low"] == 0.0 and row["Accuracy/high"] == 0.0
    assert row["Accuracy/distinguishable"] is False
    assert row["paired_seeds"] is True


def test_a_large_constant_gain_is_distinguishable_and_exact():
    # +20 points on every case and every seed: the interval is the gain itself
    runs = SeedRuns({"none": {s: _records("m", [a * 0.5 for a in NOISY[s]]) for s in range(3)},
                     "aam++": {s: _records("m+aam++", [a * 0.5 + 0.2 for a in NOISY[s]]) for s in range(3)}})
    rows = gain_rows(runs, "none", replicates=400)
    shadow, average, original = (_gain(rows, c) for c in ("shadow", "average", "original"))
    assert shadow["Accuracy/gain"] == pytest.approx(20.0)
    assert shadow["Accuracy/low"] == pytest.approx(20.0) and shadow["Accuracy/high"] == pytest.approx(20.0)
    assert shadow["Accuracy/distinguishable"] is True
    assert average["Accuracy/gain"] == pytest.approx(20.0)  # one category: the average is that category
    assert original["Accuracy/gain"] == pytest.approx(0.0) and not original["Accuracy/distinguishable"]
    assert gain_text(shadow, "Accuracy") == "+20.00 [+20.00, +20.00] *"


def test_noise_around_zero_gives_an_interval_holding_zero_and_case_noise_widens_it():
    # the defense = none plus independent per-case noise of mean ~0: not distinguishable; the interval's width is
    # about 2 x 1.96 x the standard error of a mean gain over 40 cases and 3 seeds
    noise = [RNG.normal(0.0, 0.1, size=40) for _ in range(3)]
    noise = [n - n.mean() for n in noise]  # exactly zero mean gain per seed
    runs = SeedRuns({"none": {s: _records("m", NOISY[s]) for s in range(3)},
                     "noisy": {s: _records("m+noisy", list(np.clip(np.array(NOISY[s]) + noise[s], 0, 1)))
                               for s in range(3)}})
    row = _gain(gain_rows(runs, "none", replicates=1000))
    assert row["Accuracy/low"] < row["Accuracy/gain"] < row["Accuracy/high"]
    assert row["Accuracy/low"] < 0 < row["Accuracy/high"] and not row["Accuracy/distinguishable"]
    sem = 100 * 0.1 / np.sqrt(40 * 3)
    assert 2.0 * sem < row["Accuracy/high"] - row["Accuracy/low"] < 6.0 * sem


def test_seed_spread_alone_makes_an_interval():
    # every case gains the same within a seed, but the seeds disagree (+2, +8, +5): the case bootstrap alone would
    # give a zero-width interval; the seed level spreads it over the seeds' gains
    runs = SeedRuns({"none": {s: _records("m", [0.5] * 20) for s in range(3)},
                     "d": {s: _records("m+d", [0.5 + g] * 20) for s, g in enumerate((0.02, 0.08, 0.05))}})
    row = _gain(gain_rows(runs, "none", replicates=2000))
    assert row["Accuracy/gain"] == pytest.approx(5.0)
    assert row["Accuracy/low"] == pytest.approx(2.0, abs=1.01) and row["Accuracy/high"] == pytest.approx(8.0, abs=1.01)
    assert row["Accuracy/low"] > 0 and row["Accuracy/distinguishable"]


def test_seed_rows_give_each_seed_its_score_and_the_mean_and_std():
    runs = SeedRuns({"none": {0: _records("m", [0.5, 0.7]), 1: _records("m", [0.6, 0.8]),
                              2: _records("m", [0.7, 0.9])}})
    row = next(r for r in seed_rows(runs) if r["category"] == "shadow")
    assert row["Accuracy/runs"] == [60.0, 70.0, 80.0]
    assert row["Accuracy"] == pytest.approx(70.0) and row["Accuracy/std"] == pytest.approx(10.0)
    # F1 is resampled through its totals: no FP, no FN -> 100 on every seed
    assert row["F1"] == pytest.approx(100.0) and row["F1/std"] == pytest.approx(0.0)


def test_f1_of_the_totals_equals_the_score_of_the_records():
    from lanevil_train.report.specs import TUSIMPLE_F1

    recs = _records("m", [0.6, 0.4, 0.8], fn=0.5)
    runs = SeedRuns({"none": {0: recs}})
    row = next(r for r in seed_rows(runs) if r["category"] == "shadow")
    assert row["F1"] == pytest.approx(TUSIMPLE_F1.aggregate([r for r in recs if r["severity"]]))
    assert row["F1"] == pytest.approx(80.0)  # FN 0.5: recall 2/3, precision 1


def test_runs_on_different_cases_are_refused():
    with pytest.raises(ValueError, match="different test cases"):
        SeedRuns({"none": {0: _records("m", [0.5, 0.6])}, "d": {0: _records("m+d", [0.5, 0.6, 0.7])}})
    runs = SeedRuns({"none": {0: _records("m", [0.5, 0.6])}, "d": {0: _records("m+d", [0.5, 0.6])}})
    with pytest.raises(ValueError, match="reference 'x'"):
        gain_rows(runs, "x")
    with pytest.raises(ValueError, match="replicates"):
        gain_rows(runs, "none", replicates=10)


def test_a_score_without_an_additive_form_is_resampled_record_by_record_to_the_same_interval(monkeypatch):
    from lanevil_train.report.specs import ACCURACY

    runs = {"none": {s: _records("m", NOISY[s]) for s in range(2)},
            "d": {s: _records("m+d", [min(1.0, a + 0.05) for a in NOISY[(s + 1) % 3]]) for s in range(2)}}
    fast = _gain(gain_rows(SeedRuns(runs), "none", replicates=150, seed=5))
    monkeypatch.delattr(ACCURACY.aggregate, "additive")
    slow = _gain(gain_rows(SeedRuns(runs), "none", replicates=150, seed=5))
    for key in ("Accuracy/gain", "Accuracy/low", "Accuracy/high"):
        assert slow[key] == pytest.approx(fast[key])
