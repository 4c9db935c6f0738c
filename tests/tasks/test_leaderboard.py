"""task=leaderboard (tasks/leaderboard.py, report/leaderboard.py): constructed cards ranked in a known order with a
tie, cards of different suites refused naming the field, and the task end to end in this process."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from lanevil_train.report.card import CARD_FILE, CardError, build_card, write_card
from lanevil_train.report.leaderboard import leaderboard_rows, write_leaderboard
from tests.tasks.cli_helpers import composed, run_in_process, write_fake_run

FS, SR = "fence_shadow", "sunlight_reflection"


def card(label, clean, shadow, reflection, severities=(1, 2, 3), cases=2):
    """A card of `label`: every case's clean image scores `clean`, every shadow variant `shadow`, every reflection
    variant `reflection` (TuSimple accuracy per image)."""
    records = []
    for i in range(cases):
        case = f"sim-{100 + i:07d}-f0"
        base = {"model": label, "dataset": "synthetic-illusions", "case_id": case, "fp": 0.0, "fn": 0.0}
        records.append({**base, "severity": 0, "illusion": None, "accuracy": clean, "key": f"{case}/clean"})
        for illusion, value in ((FS, shadow), (SR, reflection)):
            records += [{**base, "severity": s, "illusion": illusion, "accuracy": value, "key": f"{case}/{illusion}{s}"}
                        for s in severities]
    return build_card(records, identity={"family": "laneatt", "backbone": "resnet18"}, replicates=20)


# Perturbed (mean of the shadow and reflection values): m1 60, m2 60 (a tie), m3 50; Gap: m1 -30, m2 -20, m3 -40
CARDS = {"m1": card("m1", 0.9, 0.5, 0.7), "m2": card("m2", 0.8, 0.6, 0.6), "m3": card("m3", 0.9, 0.4, 0.6)}


def test_the_ranking_of_constructed_cards_with_a_tie():
    head, rows = leaderboard_rows(list(CARDS.values()), ["m1.json", "m2.json", "m3.json"])
    assert head["rank_by"] == "Accuracy/Perturbed" and head["higher_is_better"]
    assert [(r["rank"], r["label"]) for r in rows] == [(1, "m1"), (1, "m2"), (3, "m3")]
    assert [r["value"] for r in rows] == pytest.approx([60.0, 60.0, 50.0])
    assert head["categories"] == ["shadow", "reflection"]
    assert rows[2]["categories"]["shadow"]["value"] == pytest.approx(40.0) and rows[2]["n"] == 12
    _, by_gap = leaderboard_rows(list(CARDS.values()), ["m1.json", "m2.json", "m3.json"], rank_by="Gap")
    assert [(r["rank"], r["label"]) for r in by_gap] == [(1, "m2"), (2, "m1"), (3, "m3")]
    _, by_mce = leaderboard_rows(list(CARDS.values()), ["m1.json", "m2.json", "m3.json"], rank_by="mCE")
    assert all(r["rank"] is None and r["value"] is None for r in by_mce)  # no reference model: unranked
    with pytest.raises(CardError, match="the cards have no 'CIDEr/Perturbed'"):
        leaderboard_rows(list(CARDS.values()), ["a", "b", "c"], rank_by="CIDEr/Perturbed")


def test_cards_of_different_suites_are_refused_naming_what_differs(tmp_path):
    write_card(tmp_path / "a.json", card("a", 0.9, 0.5, 0.7, severities=(1, 2, 3, 4, 5)))
    write_card(tmp_path / "b.json", card("b", 0.9, 0.5, 0.7, severities=(1, 2)))
    with pytest.raises(CardError, match=r"b\.json: suite\.severities \[1,2\] differs from a\.json's \[1,2,3,4,5\]"):
        write_leaderboard([tmp_path / "a.json", tmp_path / "b.json"], tmp_path / "board")
    write_card(tmp_path / "c.json", card("c", 0.9, 0.5, 0.7, severities=(1, 2, 3, 4, 5), cases=3))
    with pytest.raises(CardError, match=r"c\.json: suite\.cases 3 differs from a\.json's 2"):
        write_leaderboard([tmp_path / "a.json", tmp_path / "c.json"], tmp_path / "board")
    assert not (tmp_path / "board").exists()


def test_a_broken_card_is_named(tmp_path):
    broken = json.loads(json.dumps(CARDS["m1"]))
    del broken["model"]["family"]
    (tmp_path / "x.json").write_text(json.dumps(broken))
    with pytest.raises(CardError, match=r"x\.json: model\.family: required field missing"):
        write_leaderboard([tmp_path / "x.json"], tmp_path / "board")


def test_task_leaderboard_end_to_end(tmp_path):
    paths = {}
    for label, c in CARDS.items():
        paths[label] = write_card(tmp_path / "runs" / f"run_{label}" / CARD_FILE, c)
    (tmp_path / "runs" / "run_m3" / "report.html").write_text("<html></html>")
    board = tmp_path / "board"
    value = run_in_process(["task=leaderboard", f"task.cards=[{paths['m3']},{paths['m2']},{paths['m1']}]"], board)
    assert value == pytest.approx(60.0)
    document = json.loads((board / "leaderboard.json").read_text())
    assert [(r["rank"], r["label"]) for r in document["rows"]] == [(1, "m1"), (1, "m2"), (3, "m3")]
    assert document["rows"][2]["report"] == "../runs/run_m3/report.html"
    assert document["rows"][0]["report"] is None
    page = (board / "leaderboard.html").read_text()
    assert 'href="../runs/run_m3/report.html"' in page and "http" not in page and "<script" not in page
    assert "| 3 | m3 | 50.00 [50.00, 50.00] | 12 |" in (board / "leaderboard.md").read_text()

    again = tmp_path / "again"  # a folder of cards: every card below it
    run_in_process(["task=leaderboard", f"task.cards={tmp_path / 'runs'}", "task.rank_by=Gap"], again)
    rows = json.loads((again / "leaderboard.json").read_text())["rows"]
    assert [r["label"] for r in rows] == ["m2", "m1", "m3"]
    assert [Path(r["card"]).parent.name for r in rows] == ["run_m2", "run_m1", "run_m3"]


def test_the_config_check_names_bad_leaderboard_keys(tmp_path):
    from lanevil_train.tasks.config_check import ConfigError, check_config

    cfg = composed(["task=leaderboard", f"task.cards=[{tmp_path / 'missing.json'}]", "task.rank_by=best"])
    with pytest.raises(ConfigError) as error:
        check_config(cfg)
    assert "task.cards: expected a card file or folder" in str(error.value) and "missing.json" in str(error.value)
    assert "task.rank_by: expected null, one of Perturbed" in str(error.value)
    check_config(composed(["task=leaderboard", f"task.cards={tmp_path}", "task.rank_by=F1/Gap"]))
    with pytest.raises(ValueError, match=r"task=leaderboard needs task.cards=\[a.json,b.json\]"):
        run_in_process(["task=leaderboard"], tmp_path / "board")  # the default: no card yet


def test_task_report_writes_each_models_card_and_the_leaderboard_ranks_them_by_mce(tmp_path):
    write_fake_run(tmp_path / "runs" / "0", "laneatt", original=0.9, perturbed=0.6)
    write_fake_run(tmp_path / "runs" / "1", "ufld", original=0.8, perturbed=0.7)
    out = tmp_path / "report"
    run_in_process(["task=report", f"task.runs=[{tmp_path / 'runs'}]", "task.baseline=laneatt", "progress=none",
                    "task.bootstrap=100", "task.html=false"], out)
    cards = sorted(p.name for p in (out / "robustness_cards").glob("*.json"))
    assert cards == ["laneatt.json", "ufld.json"] and not (out / CARD_FILE).exists()
    ufld = json.loads((out / "robustness_cards" / "ufld.json").read_text())
    # errors: ufld 30 at every type, laneatt 40: CE 0.75
    assert ufld["mce"]["reference"] == "laneatt" and ufld["mce"]["mCE"]["value"] == pytest.approx(75.0)
    assert ufld["results"]["overall"]["scores"]["Accuracy"]["Gap"]["value"] == pytest.approx(-10.0)
    assert ufld["run"]["files"] == [str((tmp_path / "runs" / "1" / "per_image.jsonl").resolve())]
    board = tmp_path / "board"
    assert run_in_process(["task=leaderboard", f"task.cards={out / 'robustness_cards'}", "task.rank_by=mCE"],
                          board) == pytest.approx(75.0)
    rows = json.loads((board / "leaderboard.json").read_text())["rows"]
    assert [(r["rank"], r["label"], r["value"]) for r in rows] == [(1, "ufld", 75.0), (2, "laneatt", 100.0)]

    single = tmp_path / "single"  # a report of one model: robustness_card.json
    run_in_process(["task=report", f"task.runs=[{tmp_path / 'runs' / '0'}]", "progress=none", "task.html=false"],
                   single)
    assert json.loads((single / CARD_FILE).read_text())["mce"] is None
