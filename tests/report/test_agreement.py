"""Open- vs closed-loop agreement (report/agreement.py): the rank correlations, their bootstrap, the model matching
and task=report's agreement.md from evaluate and closed-loop run folders."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from lanevil_train.report.agreement import (
    ALL,
    ASR,
    BY_MODEL,
    BY_PAIR,
    MIN_TLC,
    agreement,
    kendall,
    match_models,
    scene_seed,
    spearman,
)
from lanevil_train.report.specs import record_set
from lanevil_train.results_log import ResultsLog
from lanevil_train.tasks import run_task  # noqa: F401 - the tasks' imports (seconds) once, at collection
from lanevil_train.tasks.report import closed_loop_files, results_files
from tests.tasks.cli_helpers import run_in_process

CASES = 6
ILLUSIONS = ("road_crack", "vehicle")
# per model: its open-loop Accuracy drop on each illusion (points of accuracy x 100) and how many of the CASES
# perturbed closed-loop runs of each illusion are attack successes: the more an illusion hurts open-loop, the more
# runs it wins (perfect agreement)
MODELS = {"a": ((5, 10), (1, 2)), "b": ((10, 20), (2, 3)), "c": ((15, 30), (3, 5)), "d": ((20, 40), (4, 6))}


def open_records(model: str, drops: tuple, cases: int = CASES) -> list[dict]:
    """A model's per-image records as task=evaluate writes them: each synthetic case's original (accuracy 0.9) and
    one severity-3 image per illusion, its accuracy lowered by the illusion's drop (plus a little per-case noise)."""
    records = []
    for c in range(cases):
        case = f"sim-{c:07d}-f0"
        noise = 0.01 * (c % 3)
        variants = [(None, 0, 0.9)] + [(ill, 3, 0.9 - drop / 100 - noise) for ill, drop in zip(ILLUSIONS, drops)]
        for illusion, severity, accuracy in variants:
            records.append({"spec": "lane", "model": model, "dataset": "synthetic-illusions",
                            "key": f"{case}/{illusion}", "case_id": case, "image": None, "illusion": illusion,
                            "category": None, "severity": severity, "accuracy": accuracy, "fp": 0.0,
                            "fn": round(1 - accuracy, 6), "num_pred": 4, "num_gt": 4})
    return records


def closed_records(model: str, wins: tuple, cases: int = CASES, tlc: bool = False) -> list[dict]:
    """A model's closed-loop run records as task=closed_loop writes them: per case and illusion the clean twin and
    one severity-3 run, the first `wins` cases of an illusion attack successes."""
    records = []
    for c in range(cases):
        for illusion, won in zip(ILLUSIONS, wins):
            for severity in (0, 3):
                success = bool(severity and c < won)
                record = {"key": f"{model}|case{c:03d}/{illusion}/{severity}/0", "model": model,
                          "run": f"case{c:03d}/{illusion}/{severity}/0", "case_id": f"case{c:03d}", "seed": c,
                          "illusion": illusion, "category": "x", "severity": severity, "perturbed": severity > 0,
                          "repeat": 0, "success": success, "max_deviation_m": 1.0 if success else 0.2}
                if tlc:
                    record["tlc_min_s"] = 0.5 if success else 3.0 + 0.1 * c
                records.append(record)
    return records


def write_log(path, records: list[dict]) -> None:
    """Records appended to a results log, as the tasks write per_image.jsonl and runs.jsonl."""
    log = ResultsLog(path)
    log.resume()
    log.append(records)


def inputs(models: dict = MODELS, tlc: bool = False):
    rs = record_set([r for m, (drops, _) in models.items() for r in open_records(m, drops)])
    closed = {m: closed_records(m, wins, tlc=tlc) for m, (_, wins) in models.items()}
    return rs, closed


def row(result, group: str, unit: str, open_name: str = "Accuracy", closed_name: str = ASR) -> dict:
    return next(r for r in result.rows if (r["illusion"], r["unit"], r["open-loop"], r["closed-loop"])
                == (group, unit, f"{open_name} drop", closed_name))


# ------------------------------------------------------------------------------------------- rank correlations
def test_perfect_agreement_is_one_reversed_is_minus_one_and_a_hand_checked_swap():
    x = [1.0, 2.0, 3.0, 4.0]
    for correlate in (spearman, kendall):
        assert float(correlate(x, [10, 20, 30, 40])) == pytest.approx(1.0)
        assert float(correlate(x, [40, 30, 20, 10])) == pytest.approx(-1.0)
    # one adjacent swap of 4: rho = 1 - 6 * 2 / (4 * 15) = 0.8; tau = (5 concordant - 1 discordant) / 6 pairs
    assert float(spearman(x, [1, 3, 2, 4])) == pytest.approx(0.8)
    assert float(kendall(x, [1, 3, 2, 4])) == pytest.approx(2 / 3)


def test_ties_take_mean_ranks_and_tau_b():
    # x ranks 1.5, 1.5, 3: rho = Pearson of (1.5, 1.5, 3) and (1, 2, 3) = sqrt(3) / 2; tau-b = 2 / sqrt(2 * 3)
    assert float(spearman([1, 1, 2], [1, 2, 3])) == pytest.approx(np.sqrt(3) / 2)
    assert float(kendall([1, 1, 2], [1, 2, 3])) == pytest.approx(2 / np.sqrt(6))
    assert np.isnan(spearman([1, 1, 1], [1, 2, 3])) and np.isnan(kendall([1, 1, 1], [1, 2, 3]))


def test_rank_correlations_of_each_row_match_scipy_on_tied_tables():
    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 4, size=(50, 7)).astype(float), rng.integers(0, 4, size=(50, 7)).astype(float)
    rho, tau = spearman(x, y), kendall(x, y)
    for i in range(len(x)):
        if np.ptp(x[i]) and np.ptp(y[i]):
            assert rho[i] == pytest.approx(stats.spearmanr(x[i], y[i]).statistic)
            assert tau[i] == pytest.approx(stats.kendalltau(x[i], y[i]).statistic)


# ---------------------------------------------------------------------------------------------------- agreement
def test_agreeing_models_correlate_fully_per_illusion_and_the_points_are_the_reports_values():
    rs, closed = inputs()
    result = agreement(rs, closed, replicates=200, seed=1)
    assert result.cases.startswith("paired")  # sim-<seed>-f0 and the closed loop's seeds are the same scenes
    for illusion in ILLUSIONS:
        for name in ("spearman", "kendall"):
            assert row(result, illusion, BY_MODEL)[name] == pytest.approx(1.0)
    point = next(p for p in result.points if (p["model"], p["illusion"]) == ("c", "vehicle"))
    gap = rs.by_model["c"].pog([r for r in rs.by_model["c"].pert if r["illusion"] == "vehicle"], rs.scores)
    assert point["Accuracy drop"] == pytest.approx(-gap["Accuracy/Gap"]) == pytest.approx(31.0)
    assert point["F1 drop"] == pytest.approx(-gap["F1/Gap"])
    assert point[f"{ASR} (%)"] == pytest.approx(100 * 5 / 6)
    # all, one point per (model, illusion): scipy on the points table
    pairs = [p for p in result.points if p["illusion"] != ALL]
    expected = stats.spearmanr([p["Accuracy drop"] for p in pairs], [p["ASR (%)"] for p in pairs]).statistic
    assert row(result, ALL, BY_PAIR)["spearman"] == pytest.approx(expected)
    assert row(result, ALL, BY_PAIR)["points"] == 8 and row(result, ALL, BY_MODEL)["points"] == 4


def test_the_bootstrap_interval_holds_the_estimate_and_repeats_with_its_seed():
    rng = np.random.default_rng(5)
    models = {f"m{k}": (tuple(rng.uniform(0, 30, 2)), tuple(rng.integers(0, CASES + 1, 2))) for k in range(5)}
    rs, closed = inputs(models)
    first = agreement(rs, closed, replicates=200, seed=7)
    assert agreement(rs, closed, replicates=200, seed=7).rows == first.rows
    assert agreement(rs, closed, replicates=200, seed=8).rows != first.rows
    defined = [r for r in first.rows if r["spearman"] is not None]
    assert len(defined) >= 6
    for r in defined:
        for name in ("spearman", "kendall"):
            assert r[f"{name}_low"] <= r[name] + 1e-9 and r[name] - 1e-9 <= r[f"{name}_high"]
            assert -1 <= r[f"{name}_low"] <= r[f"{name}_high"] <= 1


def test_two_models_get_a_note_and_no_nan():
    rs, closed = inputs({m: MODELS[m] for m in ("a", "b")})
    result = agreement(rs, closed, replicates=100)
    per_model = [r for r in result.rows if r["unit"] == BY_MODEL]
    assert per_model and all(r["spearman"] is None and "at least 3" in r["note"] for r in per_model)
    assert row(result, ALL, BY_PAIR)["spearman"] is not None  # 4 (model, illusion) points
    assert any("2 model(s)" in note for note in result.notes)
    json.dumps(result.rows, allow_nan=False)  # no NaN anywhere
    json.dumps(result.points, allow_nan=False)


def test_min_tlc_is_correlated_when_the_runs_carry_it_and_noted_when_not():
    rs, closed = inputs(tlc=True)
    result = agreement(rs, closed, replicates=100)
    tlc = row(result, "road_crack", BY_MODEL, closed_name=MIN_TLC)
    assert tlc["spearman"] == pytest.approx(-1.0) and tlc["agrees if"] == "< 0"  # more wins, a lower mean min TLC
    rs, closed = inputs()
    result = agreement(rs, closed, replicates=100)
    assert not [r for r in result.rows if r["closed-loop"] == MIN_TLC]
    assert any("tlc_min_s" in note for note in result.notes)


def test_tied_drops_are_noted_not_correlated():
    rs, closed = inputs({m: ((10, 10), MODELS[m][1]) for m in MODELS})
    result = agreement(rs, closed, replicates=100)
    assert row(result, "road_crack", BY_MODEL)["spearman"] is None
    assert "same Accuracy drop" in row(result, "road_crack", BY_MODEL)["note"]


def test_cases_of_other_suites_are_drawn_on_each_side_alone():
    rs, closed = inputs()
    photos = record_set([{**r, "case_id": r["case_id"].replace("sim-", "photo-")} for r in rs.records])
    result = agreement(photos, closed, replicates=100)
    assert result.cases.startswith("independent") and "6 open-loop and the 6 closed-loop cases" in result.cases
    assert row(result, "vehicle", BY_MODEL)["spearman"] == pytest.approx(1.0)


def test_models_match_by_weights_then_label():
    matched, notes = match_models({"laneatt": "aa", "ufld": None, "clrnet": "cc"},
                                  {"laneatt-r18": "aa", "ufld": "uu", "clrnet": "xx"})
    assert matched == {"laneatt-r18": "laneatt", "ufld": "ufld"}
    assert any("clrnet" in note and "not those" in note for note in notes)
    assert any("without closed-loop runs: clrnet" in note for note in notes)
    assert scene_seed("sim-0000012-f3") == 12 and scene_seed("clips/x/20.jpg") is None


# ----------------------------------------------------------------------------------------------- task=report
def test_task_report_writes_agreement_from_evaluate_and_closed_loop_folders(tmp_path):
    models = {m: MODELS[m] for m in ("a", "b", "d")}
    for model, (drops, wins) in models.items():
        folder = tmp_path / "runs" / f"eval-{model}"
        write_log(folder / "per_image.jsonl", open_records(model, drops))
        (folder / "per_image.run.json").write_text(json.dumps({"model": model, "weights_sha256": f"w{model}"}))
    closed = tmp_path / "runs" / "closed"
    labels = {"a": "a", "b": "b", "d": "d-ckpt"}  # d drove under another label: matched by its weights
    write_log(closed / "runs.jsonl", [r for m, (_, wins) in models.items() for r in closed_records(labels[m], wins)])
    for model, label in labels.items():  # what task=closed_loop claims of each label's model
        (closed / "traces" / label).mkdir(parents=True)
        (closed / "traces" / label / "model.json").write_text(json.dumps({"model": label,
                                                                           "weights_sha256": f"w{model}"}))
    assert results_files([str(closed)]) == [] and closed_loop_files([str(tmp_path)]) == [closed / "runs.jsonl"]
    out = tmp_path / "report"
    run_in_process(["task=report", f"task.runs=[{tmp_path / 'runs'}]", "task.bootstrap=100", "task.html=false",
                    "progress=none"], out)
    rows = json.loads((out / "agreement.json").read_text())
    text = (out / "agreement.md").read_text()
    assert [r["spearman"] for r in rows if r["unit"] == BY_MODEL and r["closed-loop"] == ASR
            and r["open-loop"] == "Accuracy drop"] == pytest.approx([1.0, 1.0, 1.0])  # the illusions and all
    assert "| road_crack | models | 3 | Accuracy drop | ASR | > 0 | +1.00 [" in text
    assert "paired" in text and (out / "agreement.png").stat().st_size > 2000
    points = json.loads((out / "agreement_points.json").read_text())
    assert {(p["model"], p["closed-loop model"]) for p in points if p["model"] == "d"} == {("d", "d-ckpt")}
    assert (out / "agreement.csv").is_file() and (out / "agreement_points.csv").is_file()
