"""Result tables: the same rows come back from JSON and CSV, and read right as markdown."""

from __future__ import annotations

import csv
import json
import os

import matplotlib.pyplot as plt
import pytest

from lanevil_train.report.plots import save_figure
from lanevil_train.report.tables import markdown_table, write_table


def test_write_table_round_trips_and_formats(tmp_path):
    rows = [{"model": "laneatt", "Accuracy": 91.23456, "F1": 80.0, "images": 100},
            {"model": "ufld", "Accuracy": 70.5, "F1": 61.25, "images": 100}]
    paths = write_table(rows, tmp_path, "scores")
    assert json.loads(paths["json"].read_text()) == rows
    with open(paths["csv"]) as handle:
        back = list(csv.DictReader(handle))
    assert [r["model"] for r in back] == ["laneatt", "ufld"]
    assert float(back[0]["Accuracy"]) == 91.23456
    assert paths["md"].read_text().splitlines() == [
        "| model | Accuracy | F1 | images |",
        "|---|---|---|---|",
        "| laneatt | 91.23 | 80.00 | 100 |",
        "| ufld | 70.50 | 61.25 | 100 |",
    ]


def test_markdown_table_of_nothing_says_so():
    assert markdown_table([]) == "(no rows)"


def test_tables_and_figures_are_replaced_whole_or_not_at_all(tmp_path, monkeypatch):
    write_table([{"model": "a", "Accuracy": 1.0}], tmp_path, "t")
    save_figure(plt.figure(), tmp_path / "f.png")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}

    def killed(*args):
        raise KeyboardInterrupt  # the moment before a file would replace the old one

    monkeypatch.setattr(os, "replace", killed)
    with pytest.raises(KeyboardInterrupt):
        write_table([{"model": "b", "Accuracy": 2.0}], tmp_path, "t")
    with pytest.raises(KeyboardInterrupt):
        save_figure(plt.figure(), tmp_path / "f.png")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert sorted(before) == ["f.png", "t.csv", "t.json", "t.md"] and before["f.png"].startswith(b"\x89PNG")
