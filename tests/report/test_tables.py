"""Result tables: the same rows come back from JSON and CSV, and read right as markdown."""

from __future__ import annotations

import csv
import json

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
